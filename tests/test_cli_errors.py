"""Bad input gets a one-line error naming the culprit and exit code 2, never a traceback."""

import signal
import struct
import subprocess
import sys

import numpy as np
import pytest
import typer
from helpers import assert_one_line_error, invoke

from plotmosaic.io import PointCloud, write_cloud


def run_info(*args):
    return invoke("info", *args)


@pytest.fixture
def good_laz(tmp_path):
    rng = np.random.default_rng(0)
    return write_cloud(
        tmp_path / "good.laz", PointCloud(rng.uniform(0, 10, (40_000, 3)) + [470000, 3810000, 2000])
    )


def test_missing_file(tmp_path):
    assert_one_line_error(run_info(tmp_path / "nope.laz"), "nope.laz", "file not found")


def test_not_a_las_file(tmp_path):
    bad = tmp_path / "text.laz"
    bad.write_text("this is not a point cloud\n" * 20)
    assert_one_line_error(run_info(bad), "text.laz", "not a readable LAS/LAZ file")


def test_truncated_laz(tmp_path, good_laz):
    data = good_laz.read_bytes()
    cut = tmp_path / "cut.laz"
    cut.write_bytes(data[: len(data) // 2])
    assert_one_line_error(run_info(cut, "--full"), "cut.laz")


def test_zero_points(tmp_path):
    empty = write_cloud(tmp_path / "empty.laz", PointCloud(np.zeros((0, 3))))
    assert_one_line_error(run_info(empty), "empty.laz", "no points")


def test_nan_coordinates(tmp_path, good_laz):
    # LAS stores integers; NaN coordinates arise from a NaN scale factor (header offset 131 = x scale)
    data = bytearray(good_laz.read_bytes())
    data[131:139] = struct.pack("<d", float("nan"))
    nan = tmp_path / "nan.laz"
    nan.write_bytes(bytes(data))
    assert_one_line_error(run_info(nan, "--full"), "nan.laz", "NaN")


def manifest(tmp_path, good_laz, body):
    path = tmp_path / "m.toml"
    path.write_text(body.replace("GOOD", good_laz.name))
    return path


def test_unknown_kind(tmp_path, good_laz):
    m = manifest(tmp_path, good_laz, '[[scans]]\nid = "s1"\npath = "GOOD"\nkind = "radar"\n')
    assert_one_line_error(run_info(m), "m.toml", "scan 's1'", "field 'kind'")


def test_duplicate_scan_ids(tmp_path, good_laz):
    body = '[[scans]]\nid = "s1"\npath = "GOOD"\n[[scans]]\nid = "s1"\npath = "GOOD"\n'
    assert_one_line_error(run_info(manifest(tmp_path, good_laz, body)), "duplicate scan id 's1'")


def test_wrong_type_field(tmp_path, good_laz):
    m = manifest(
        tmp_path, good_laz, '[[scans]]\nid = "s1"\npath = "GOOD"\nreference = "yes please"\n'
    )
    assert_one_line_error(run_info(m), "scan 's1'", "field 'reference'")


def test_valid_inputs_describe_themselves(tmp_path, good_laz):
    m = manifest(tmp_path, good_laz, '[[scans]]\nid = "s1"\npath = "GOOD"\n')
    result = run_info(m, "--full")
    assert result.exit_code == 0, result.output
    assert "40,000 points" in result.output and "s1" in result.output


def test_console_script_entry_point_reports_version():
    out = subprocess.run(
        [sys.executable, "-m", "plotmosaic", "--version"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert out.stdout.startswith("plotmosaic ")


def test_sigterm_while_the_command_layer_imports_is_an_interrupt():
    """A batch scheduler's SIGTERM in the first second (the command's module and its numpy, laspy,
    ... still importing) exits 130 with one line, like one mid-run, not 143. `-X importtime`
    reports each import as it finishes, so the signal lands inside the command's import chain."""
    proc = subprocess.Popen(
        [sys.executable, "-X", "importtime", "-m", "plotmosaic", "info", "no-such-file.laz"],
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    for line in proc.stderr:  # wait until numpy (imported by the command layer) is in
        if line.split("|")[-1].strip() == "numpy":
            break
    proc.send_signal(signal.SIGTERM)
    rest = proc.stderr.read()
    proc.wait(timeout=60)
    assert proc.returncode == 130, rest[-500:]
    assert rest.rstrip().splitlines()[-1] == "interrupted"


def test_clicks_abort_exits_130_with_one_line(good_laz, monkeypatch):
    """click's Ctrl-C at a prompt (typer.Abort) ends as an interrupt; the handler that catches it
    once named a class typer does not have, and turned any error passing by into an AttributeError."""

    def aborted(*args, **kwargs):
        raise typer.Abort()

    monkeypatch.setattr("plotmosaic.commands.info._describe_file", aborted)
    result = run_info(good_laz)
    assert result.exit_code == 130 and "interrupted" in result.output

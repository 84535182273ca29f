"""Inputs are sacred: no command writes over a file it reads or a file the user made (issue 38, item 1).

Each refusal is exit 2 with one line naming the culprit, before any work: the inputs' bytes are
unchanged and no file is added or left anywhere (no temporaries, no empty output folder).
"""

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import assert_one_line_error, invoke, write_e57

from plotmosaic.commands.register import register_plan, tie_plan
from plotmosaic.errors import InputError
from plotmosaic.io.outputs import (
    RECORD,
    OutputPlan,
    check_outputs,
    claimed,
    inputs_of,
    read_record,
)
from plotmosaic.manifest import dump_manifest, load_manifest


def tree(root: Path) -> dict[str, str]:
    """Every file under `root` (symlinks as their target) with its sha256: contents and leftovers."""
    found = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            if p.is_symlink():
                found[rel] = "-> " + os.readlink(p)
            elif p.is_file():
                found[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
            else:
                found[rel] = "dir"
    return found


@pytest.fixture
def plot(small_sim, tmp_path):
    """A private copy of the small simulated plot (manifest, 5 scans, ALS, ground truth)."""
    root = tmp_path / "plot"
    shutil.copytree(small_sim.outdir, root)
    return root


def refused(root: Path, args: list, *needles):
    """Run the command; it must be refused (exit 2, one line naming `needles`), `root` untouched."""
    before = tree(root)
    result = invoke(*args)
    assert_one_line_error(result, *needles)
    assert tree(root) == before
    return result


# ---------------------------------------------------------------- align


@pytest.mark.parametrize("which", ["source", "target"])
def test_align_out_onto_its_scan_is_refused(plot, which):
    src, tgt = plot / "P1" / "P1-S1.laz", plot / "P1" / "P1-S0.laz"
    out = src if which == "source" else tgt
    refused(plot, ["align", src, tgt, "--out", out], str(out), which.upper())


def test_align_out_onto_init_or_config_is_refused(plot):
    src, tgt = plot / "P1" / "P1-S1.laz", plot / "P1" / "P1-S0.laz"
    init = plot / "init.json"
    init.write_text(json.dumps({"transform": np.eye(4).tolist()}))
    refused(plot, ["align", src, tgt, "--init", init, "--out", init], str(init), "--init file")
    config = plot / "r.config-used.toml"
    config.write_text("")
    # the settings sidecar of --out r.json is r.config-used.toml: the --config file
    refused(
        plot,
        ["align", src, tgt, "--config", config, "--out", plot / "r.json"],
        str(config),
        "--config file",
    )


def test_align_out_through_a_symlink_or_hard_link_is_refused(plot):
    src, tgt = plot / "P1" / "P1-S1.laz", plot / "P1" / "P1-S0.laz"
    (plot / "link.json").symlink_to(src)
    refused(plot, ["align", src, tgt, "--out", plot / "link.json"], "link.json", "SOURCE")
    os.link(tgt, plot / "hard.json")
    refused(plot, ["align", src, tgt, "--out", plot / "hard.json"], "hard.json", "TARGET")


@pytest.mark.parametrize("name", ["r.json", "r.matrix.txt", "r.config-used.toml"])
def test_align_refuses_each_existing_file_it_would_write_unless_forced(plot, name):
    """RESULT.json and the two files beside it: refused before any work (exit 2 within a second,
    the file unchanged); --force replaces them."""
    src, tgt = plot / "P1" / "P1-S1.laz", plot / "P1" / "P1-S0.laz"
    res = plot / "res"
    res.mkdir()
    (res / name).write_text("mine\n")
    start = time.perf_counter()
    refused(plot, ["align", src, tgt, "--out", res / "r.json"], str(res / name), "--force")
    assert time.perf_counter() - start < 1.0
    forced = invoke("align", src, tgt, "--out", res / "r.json", "--force")
    assert forced.exit_code == 0, forced.output
    assert json.loads((res / "r.json").read_text())["transform"]
    assert (res / "r.matrix.txt").read_text().count("\n") >= 4
    assert (res / "r.config-used.toml").read_text().startswith("#")


def test_align_save_levels_never_writes_an_input(plot):
    src, tgt = plot / "P1" / "P1-S1.laz", plot / "P1" / "P1-S0.laz"
    levels = plot / "levels"
    levels.mkdir()
    named = levels / "source_levels.laz"  # a scan the user keeps under a name --save-levels writes
    shutil.copy(src, named)
    refused(plot, ["align", named, tgt, "--save-levels", levels], str(named), "SOURCE")
    config = levels / "config-used.toml"  # without --out the settings go into the levels folder
    named.unlink()
    config.write_text("")
    refused(
        plot,
        ["align", src, tgt, "--save-levels", levels, "--config", config],
        str(config),
        "--config file",
    )


# ---------------------------------------------------------------- merge


def test_merge_force_never_overwrites_a_scan(plot):
    scan = plot / "P1" / "P1-S0.laz"
    args = ["merge", plot / "manifest.toml", "--poses", plot / "ground_truth.json"]
    refused(plot, [*args, "--out", scan, "--force"], str(scan), "scan 'P1-S0'")
    als = next((plot / "als").glob("*.laz"))
    refused(plot, [*args, "--out", als, "--force"], str(als), "ALS tile")


def test_merge_sidecars_never_hit_an_input(plot):
    args = ["merge", plot / "manifest.toml", "--poses", plot / "ground_truth.json", "--force"]
    poses = plot / "m.laz.json"  # the sidecar of --out m.laz
    shutil.copy(plot / "ground_truth.json", poses)
    refused(
        plot,
        ["merge", plot / "manifest.toml", "--poses", poses, "--out", plot / "m.laz", "--force"],
        str(poses),
        "poses file",
    )
    config = plot / "m.config-used.toml"
    config.write_text("")
    refused(plot, [*args, "--config", config, "--out", plot / "m.laz"], str(config), "--config")


def test_merge_tiles_never_replace_a_folder_of_inputs(plot):
    args = ["merge", plot / "manifest.toml", "--poses", plot / "ground_truth.json"]
    # the whole tile folder is swapped for the new one: the scans in it would be lost
    refused(plot, [*args, "--tiles", "--out", plot / "P1", "--force"], str(plot / "P1"), "scan")


# ---------------------------------------------------------------- register-plot, tie-to-als


def test_tie_to_als_never_replaces_the_poses_it_was_given(plot):
    reg = plot / "reg"
    reg.mkdir()
    shutil.copy(plot / "ground_truth.json", reg / "poses.json")
    (reg / "graph.json").write_text("{}")
    args = ["tie-to-als", plot / "manifest.toml", "--poses", reg / "poses.json", "--out", reg]
    refused(plot, args, str(reg / "poses.json"), "poses file")
    refused(plot, [*args, "--force"], str(reg / "poses.json"), "poses file")


@pytest.mark.parametrize("force", [False, True])
def test_register_plot_never_replaces_the_users_files(plot, force):
    project = plot / "project"
    project.mkdir()
    (project / "report.md").write_text("my field notes\n")
    (project / "poses.json").write_text('{"mine": true}\n')
    args = ["register-plot", plot / "manifest.toml", "--out", project]
    refused(plot, args + (["--force"] if force else []), "project", "not written by plotmosaic")


def test_register_plot_needs_force_beside_other_files(plot):
    project = plot / "project"
    project.mkdir()
    (project / "notes.txt").write_text("mine\n")
    refused(
        plot, ["register-plot", plot / "manifest.toml", "--out", project], "notes.txt", "--force"
    )


def test_register_plot_config_used_is_never_the_config(plot):
    out = plot / "out"
    out.mkdir()
    config = out / "config-used.toml"
    config.write_text("")
    # an earlier run's folder, then its settings given back with --config into the same folder
    plan = OutputPlan("register-plot", folder=out, names=("config-used.toml",))
    with claimed(plan):
        pass
    args = ["register-plot", plot / "manifest.toml", "--out", out, "--config", config]
    refused(plot, args, str(config), "--config file")


# ---------------------------------------------------------------- simulate, demo, bench, report


@pytest.mark.parametrize(
    "args, name",
    [
        (["simulate", "{out}", "--force"], "manifest.toml"),
        (["demo", "{out}", "--force"], "merged.laz"),
        (["bench", "a.laz", "b.laz", "--gt", "identity", "--out", "{out}", "--force"], "table.md"),
    ],
)
def test_output_folders_never_replace_a_user_file_of_their_naming(plot, tmp_path, args, name):
    out = tmp_path / "out"
    out.mkdir()
    (out / name).write_text("mine\n")
    if args[0] == "bench":
        args = [plot / "P1" / "P1-S0.laz", plot / "P1" / "P1-S1.laz", *args[3:]]
        args = ["bench", *args]
    refused(tmp_path, [str(out) if a == "{out}" else a for a in args], str(out / name))


def test_report_never_writes_into_the_registration_folder_it_reads(plot):
    reg = plot / "reg"
    reg.mkdir()
    shutil.copy(plot / "ground_truth.json", reg / "poses.json")
    (reg / "report.html").write_text("<html>register-plot's page</html>\n")
    refused(plot, ["report", reg, "--out", reg], str(reg))
    refused(plot, ["report", reg, "--out", reg, "--force"], str(reg / "report.html"))


def test_report_on_a_damaged_run_folder_leaves_every_file_as_it_was(plot):
    """A failed command writes nothing: the folder's record is not touched before its inputs load."""
    reg = plot / "reg"
    plan = OutputPlan("register-plot", folder=reg, names=("poses.json", "graph.json"))
    with claimed(check_outputs(plan)):
        (reg / "poses.json").write_text('{"frame": "plot", "scans": {"P1-S0": ')  # cut short
        (reg / "graph.json").write_text("{}")
    refused(plot, ["report", reg], "poses.json")


def test_manifest_from_never_writes_over_the_e57(tmp_path):
    xyz = np.random.default_rng(0).uniform(-5, 5, (500, 3))
    e57 = write_e57(tmp_path / "scans.e57", [("s0", xyz, np.eye(4), {})])
    refused(tmp_path, ["manifest-from", e57, "--out", e57, "--force"], str(e57), "E57 file")


# ---------------------------------------------------------------- the folder record


def test_a_rerun_of_the_same_command_may_replace_what_it_wrote(tmp_path):
    out = tmp_path / "out"
    plan = OutputPlan("register-plot", folder=out, names=("poses.json", "pairs"))
    with claimed(check_outputs(plan)):
        (out / "poses.json").write_text("{}")
    check_outputs(plan)  # the same command again: its own files may be replaced
    other = OutputPlan("tie-to-als", folder=out, names=("poses.json",), force=True)
    with pytest.raises(InputError, match="not written by plotmosaic tie-to-als"):
        check_outputs(other)
    (out / "notes.txt").write_text("mine\n")
    with pytest.raises(InputError, match="notes.txt"):
        check_outputs(plan)
    forced = OutputPlan("register-plot", folder=out, names=plan.names, force=True)
    check_outputs(forced)  # beside the user's file, which stays as it is
    assert (out / "notes.txt").read_text() == "mine\n"


def test_a_failed_run_leaves_no_record_and_no_folder(tmp_path):
    out = tmp_path / "a" / "b"
    plan = OutputPlan("register-plot", folder=out, names=("poses.json",))
    with pytest.raises(InputError), claimed(check_outputs(plan)):
        assert (out / RECORD).is_file()
        raise InputError("bad scan")
    assert list(tmp_path.iterdir()) == []


def test_an_input_under_an_output_subfolder_is_caught(tmp_path):
    scan = tmp_path / "out" / "pairs" / "mine.laz"
    scan.parent.mkdir(parents=True)
    scan.write_bytes(b"x")
    plan = OutputPlan(
        "register-plot", inputs_of([(scan, "scan")]), folder=tmp_path / "out", names=("pairs",)
    )
    with pytest.raises(InputError, match="would replace the scan"):
        check_outputs(plan)


# ---------------------------------------------------------------- the names the plans list are real


def _two_scans(plot: Path) -> Path:
    """The plot's manifest with two of its scans: one pair to register."""
    m = load_manifest(plot / "manifest.toml")
    keep = [s for s in m.plots[0].scans if s.id in ("P1-S0", "P1-S2")]
    sub = m.model_copy(update={"plots": [m.plots[0].model_copy(update={"scans": keep})]})
    path = plot / "two.toml"
    path.write_text(dump_manifest(sub))
    return path


@pytest.mark.slow
def test_register_and_tie_write_only_the_names_they_claim(plot):
    manifest = _two_scans(plot)
    m, reg, geo = load_manifest(manifest), plot / "reg", plot / "geo"
    assert invoke("register-plot", manifest, "--out", reg, "-j", "1").exit_code == 0
    names = register_plan(m, None, reg, False).names
    assert {n for n in os.listdir(reg) if n != RECORD} <= set(names)
    assert read_record(reg).names("register-plot") == tuple(sorted(names))
    report = invoke("report", reg, "--points", "3000", "--no-levels")  # into reg/report
    assert report.exit_code == 0, report.output
    again = invoke("register-plot", manifest, "--out", reg, "-j", "1")  # the cache re-run
    assert again.exit_code == 0 and "0 registered now" in again.output, again.output
    tie = invoke("tie-to-als", manifest, "--poses", reg / "poses.json", "--out", geo, "-j", "1")
    assert tie.exit_code == 0, tie.output
    names = tie_plan(m, reg / "poses.json", None, geo, False).names
    assert {n for n in os.listdir(geo) if n != RECORD} <= set(names)


def test_merge_never_writes_over_an_e57_project_it_reads(tmp_path):
    """A manifest scan inside an E57 project (`plot.e57`, `scan = 1`) reads the E57 file itself."""
    rng = np.random.default_rng(0)
    scans = [(f"s{k}", rng.uniform(-5, 5, (500, 3)), np.eye(4), {}) for k in range(2)]
    e57 = write_e57(tmp_path / "plot.e57", scans)
    (tmp_path / "m.toml").write_text(
        '[[scans]]\nid = "a"\npath = "plot.e57"\nscan = 0\n'
        '[[scans]]\nid = "b"\npath = "plot.e57"\nscan = 1\n'
    )
    poses = {"frame": "plot", "scans": {s: {"transform": np.eye(4).tolist()} for s in "ab"}}
    (tmp_path / "poses.json").write_text(json.dumps(poses))
    args = ["merge", tmp_path / "m.toml", "--poses", tmp_path / "poses.json", "--out", e57]
    refused(tmp_path, [*args, "--force"], str(e57), "scan 'a'", "input")

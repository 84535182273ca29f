"""`plotmosaic align`: RESULT.json contract, exit 3 on a pair that cannot be registered, exit 2 on bad input."""

from __future__ import annotations

import json

import laspy
import numpy as np
import pytest
from helpers import SIM_PAIR_MAX_DEG
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from plotmosaic.align.pipeline import AlignRequest, align_files
from plotmosaic.align.result import PairResult
from plotmosaic.cli import app
from plotmosaic.commands.align import kind_lines, summary_lines
from plotmosaic.io.las import PointCloud, read_cloud, write_cloud
from plotmosaic.poses import load_poses

runner = CliRunner()


def invoke(*args):
    result = runner.invoke(app, ["align", *map(str, args)])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    return result


def one_line_error(result, code):
    assert result.exit_code == code, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    return lines[0]


@pytest.fixture(scope="module")
def pair(small_sim, tmp_path_factory):
    truth = load_poses(small_sim.ground_truth_path)
    T_true = np.linalg.inv(truth.transform("P1-S0")) @ truth.transform("P1-S1")
    P = np.eye(4)
    P[:3, :3] = Rotation.from_euler("xyz", [4.0, -3.0, 6.0], degrees=True).as_matrix()
    P[:3, 3] = [1.0, -1.5, 0.5]
    init = tmp_path_factory.mktemp("init") / "init.json"
    init.write_text(json.dumps({"transform": (T_true @ P).tolist()}))
    return small_sim.scan_paths["P1-S1"], small_sim.scan_paths["P1-S0"], T_true, init


@pytest.mark.slow
def test_align_writes_result_and_levels(pair, tmp_path):
    src, tgt, T_true, init = pair
    out = tmp_path / "result.json"
    res = invoke(
        src, tgt, "--init", init, "--no-coarse", "--out", out, "--save-levels", tmp_path / "levels"
    )
    assert res.exit_code == 0, res.output
    assert "fitness" in res.output and "confidence" in res.output
    data = json.loads(out.read_text())
    check_user_figures(res.output, data, src, out)
    for key in (
        "transform",
        "fitness",
        "inlier_rmse",
        "overlap",
        "information",
        "levels",
        "seconds",
        "method",
        "version",
    ):
        assert key in data
    T = np.asarray(data["transform"])
    D = np.linalg.inv(T_true) @ T
    assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < SIM_PAIR_MAX_DEG
    assert np.linalg.norm(D[:3, 3]) < 0.03
    assert np.asarray(data["information"]).shape == (6, 6)
    assert len(data["levels"]["source"]) == 3 and len(data["levels"]["target"]) == 3
    for row in data["levels"]["source"]:
        assert {"size", "kappa", "complexity", "matched"} <= set(row)
    lv = laspy.read(tmp_path / "levels" / "source_levels.laz")
    assert set(np.unique(lv["level"])) == {0, 1, 2}
    assert (tmp_path / "levels" / "levels.png").stat().st_size > 10_000
    # a previous RESULT.json is a valid --init
    again = invoke(src, tgt, "--init", out, "--no-coarse")
    assert again.exit_code == 0, again.output


def check_user_figures(output: str, data: dict, src, out) -> None:
    """The printout and RESULT.json say what the pose does to the source, in figures a user can check."""
    T = np.asarray(data["transform"])
    xyz = read_cloud(src, attributes=False).xyz
    centre = (xyz.min(axis=0) + xyz.max(axis=0)) / 2
    moves = T[:3, :3] @ centre + T[:3, 3] - centre
    np.testing.assert_allclose(data["source_centre"], centre, atol=1e-9)
    np.testing.assert_allclose(data["motion_at_centre_m"], moves, atol=1e-9)
    angle = Rotation.from_matrix(T[:3, :3]).magnitude()
    assert data["rotation_deg"] == pytest.approx(np.degrees(angle), abs=1e-6)
    assert f"rotation: {data['rotation_deg']:.4f} deg" in output
    assert f"dx {moves[0]:+.4f}, dy {moves[1]:+.4f}, dz {moves[2]:+.4f} m" in output
    assert f"{T[0, 3]:+.4f}" not in output  # the translation about the file origin is not printed
    # timings hold seconds only; what the steps did is under `steps`
    for value in data["timings"].values():
        seconds = value.values() if isinstance(value, dict) else [value]
        assert all(isinstance(v, float) and v >= 0 for v in seconds), data["timings"]
    assert {"correction_deg", "correction_m", "final_iterations"} <= set(data["steps"])
    # neither kind given: both detected, each printed with why
    assert data["source_kind"] == data["target_kind"] == "tls"
    assert set(data["detected_kinds"]) == {"source", "target"}
    assert "source kind: tls (detected: ground-based" in output
    assert "target kind: tls (detected: ground-based" in output
    matrix = out.with_name(f"{out.stem}.matrix.txt")
    np.testing.assert_array_equal(np.loadtxt(matrix), T)
    assert f"matrix: {matrix}" in output and "source file -> target file" in output


@pytest.mark.slow
def test_real_pair_kinds_detected_as_given(spanner_dir):
    """UAS -> ALS with no kinds: detected uls -> als, the same confidence as with the kinds given."""
    src, tgt = spanner_dir / "UAS_Clip.laz", spanner_dir / "ALS_Clip.laz"
    found = align_files(src, tgt)
    given = align_files(src, tgt, AlignRequest(source_kind="uls", target_kind="als"))
    assert (found.source_kind, found.target_kind) == ("uls", "als"), found.detected_kinds
    assert found.confidence == given.confidence and given.detected_kinds == {}
    np.testing.assert_array_equal(found.transform, given.transform)


def test_printout_and_json_say_what_the_pose_does_to_the_source():
    """A UTM pair turned 2 deg about z: the motion printed is the source centre's (cm), not the
    translation of the file origin (km); the JSON carries the same figures at its top level."""
    centre = np.array([470641.0, 3810235.0, 2296.0])
    R = Rotation.from_euler("z", 2.0, degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = centre + [0.01, -0.02, 0.03] - R @ centre  # the centre moves by 1, -2, 3 cm
    result = PairResult(
        transform=T,
        fitness=0.5,
        inlier_rmse=0.1,
        overlap=0.6,
        information=np.eye(6),
        levels={},
        seconds=1.0,
        source_kind="uls",
        target_kind="als",
        source_centre=centre.tolist(),
        detected_kinds={"target": {"kind": "als", "reason": "airborne (figures)", "evidence": {}}},
    )
    text = "\n".join(kind_lines(result) + summary_lines(result))
    assert "rotation: 2.0000 deg" in text
    assert "dx +0.0100, dy -0.0200, dz +0.0300 m" in text
    assert f"{T[0, 3]:+.4f}" not in text and f"{T[0, 3]:.1f}" not in text
    assert "source kind: uls (given by --source-kind)" in text
    assert "target kind: als (detected: airborne (figures))" in text
    data = json.loads(json.dumps(result.to_dict()))
    np.testing.assert_allclose(data["motion_at_centre_m"], [0.01, -0.02, 0.03], atol=1e-9)
    assert data["rotation_deg"] == pytest.approx(2.0)
    again = PairResult.from_dict(data)
    assert again.source_centre == result.source_centre
    assert again.detected_kinds == result.detected_kinds


def test_non_overlapping_pair_exits_3(pair, tmp_path):
    src, tgt, _, _ = pair
    cloud = read_cloud(tgt, attributes=False)
    far = write_cloud(tmp_path / "far.laz", PointCloud(cloud.xyz + [400.0, 0.0, 0.0]))
    line = one_line_error(invoke(src, far, "--no-coarse"), 3)
    assert "cannot be registered" in line and "fitness" in line and "overlap" in line


def test_bad_input_exits_2(pair, tmp_path):
    src, tgt, _, _ = pair
    assert "nope.laz" in one_line_error(invoke(tmp_path / "nope.laz", tgt), 2)
    assert "--source-kind" in one_line_error(invoke(src, tgt, "--source-kind", "sonar"), 2)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"transform": [[1, 0], [0, 1]]}))
    assert "bad.json" in one_line_error(invoke(src, tgt, "--init", bad), 2)
    assert "--levels-target" in one_line_error(invoke(src, tgt, "--levels-target", "0"), 2)


@pytest.mark.slow
def test_ambiguous_pair_exits_3_instead_of_a_silent_wrong_transform(small_sim, tmp_path):
    """Corner scans 32 m apart at 50k points share too little: the coarse stage's best pose (the two
    scanners pulled together, fitness 0.33 from the dense ground) is barely ahead of distinct rivals.
    That is refused with the figures, not returned as a success."""
    out = tmp_path / "r.json"
    result = invoke(small_sim.scan_paths["P1-S1"], small_sim.scan_paths["P1-S3"], "--out", out)
    line = one_line_error(result, 3)
    assert "ambiguous" in line and "confidence" in line
    assert not out.exists()

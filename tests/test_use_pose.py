"""Stored poses (E57 `use_pose = true`): a right one skips the coarse search, a wrong one never wins."""

import numpy as np
import pytest
from helpers import SIM_PAIR_MAX_DEG, SIM_PAIR_MAX_M, invoke, write_e57
from scipy.spatial.transform import Rotation

from plotmosaic.align.pair import Start, register_prepared
from plotmosaic.align.pipeline import prepare_pair
from plotmosaic.config.align import AlignConfig
from plotmosaic.errors import RegistrationFailed
from plotmosaic.io.frame import inverse, pose_error
from plotmosaic.io.las import read_cloud
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import load_poses

SUBSET = ["P1-S0", "P1-S2", "P1-S3"]  # neighbours, as in test_register.py and test_e57.py


def _off(T: np.ndarray, deg: float, metres: float) -> np.ndarray:
    """T moved by `deg` about a tilted axis and `metres` sideways: a wrong stored pose."""
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(
        np.radians(deg) * np.array([0.2, 0.1, 1.0]) / 1.025
    ).as_matrix()
    D[:3, 3] = [metres * 0.8, metres * 0.6, 0.0]
    return D @ T


@pytest.fixture(scope="module")
def scans(small_sim):
    manifest = load_manifest(small_sim.manifest_path)
    truth = load_poses(small_sim.ground_truth_path)
    clouds = {
        s: read_cloud(manifest.resolve(manifest.scan(s).path), attributes=False).xyz for s in SUBSET
    }
    poses = {s: inverse(truth.transform(SUBSET[0])) @ truth.transform(s) for s in SUBSET}
    return clouds, poses


@pytest.fixture(scope="module")
def pair(scans):
    """S2 -> S0 prepared once, with the true S2 -> S0 transform."""
    from plotmosaic.io.las import PointCloud

    clouds, poses = scans
    cfg = AlignConfig()
    src, tgt = prepare_pair(
        PointCloud(clouds["P1-S2"]), PointCloud(clouds["P1-S0"]), ("tls", "tls"), (3, 3), cfg
    )
    return src, tgt, inverse(poses["P1-S0"]) @ poses["P1-S2"], cfg


def test_right_stored_pose_skips_the_search(pair):
    src, tgt, T, cfg = pair
    res = register_prepared(src, tgt, cfg, T, start=Start.STORED)
    assert res.steps.get("coarse_skipped") == "stored pose verified"
    assert res.coarse["skipped"] == "stored pose verified" and res.coarse["stored_pose"]["verified"]
    assert "hypotheses" not in res.coarse  # no search ran
    rot, trans = pose_error(res.transform, T)
    assert trans < SIM_PAIR_MAX_M and rot < SIM_PAIR_MAX_DEG, (trans, rot)
    # the same pose as a plain prior (not stored): the search runs
    plain = register_prepared(src, tgt, cfg, T)
    assert "coarse_skipped" not in plain.steps and "hypotheses" in plain.coarse


@pytest.mark.parametrize("deg, metres", [(30.0, 5.0), (0.0, 0.0)])
def test_wrong_stored_pose_runs_the_search(pair, deg, metres):
    """30 deg / 5 m off, or identity (what many exports store): verified never, right or refused."""
    src, tgt, T, cfg = pair
    stored = _off(T, deg, metres) if deg or metres else np.eye(4)
    try:
        res = register_prepared(src, tgt, cfg, stored, start=Start.STORED)
    except RegistrationFailed as exc:  # refused is allowed, a wrong pose with exit 0 is not
        assert exc.result is None or "coarse_skipped" not in exc.result.steps
        return
    assert "coarse_skipped" not in res.steps
    assert res.coarse["stored_pose"]["verified"] is False and res.coarse["stored_pose"]["failed"]
    rot, trans = pose_error(res.transform, T)
    assert trans < SIM_PAIR_MAX_M and rot < SIM_PAIR_MAX_DEG, (trans, rot)


@pytest.mark.slow
def test_register_plot_use_pose(scans, tmp_path):
    """A 3-scan E57 with stored poses, S3's deliberately wrong: S0-S2 skips the search, every scan right."""
    clouds, poses = scans
    stored = dict(poses)
    stored["P1-S3"] = _off(poses["P1-S3"], 30.0, 5.0)
    rows = [(s, clouds[s], stored[s], {}) for s in SUBSET]
    path = write_e57(tmp_path / "plot.e57", rows)
    toml = tmp_path / "m.toml"
    toml.write_text(
        'plot_id = "P1"\n'
        + "".join(
            f'[[scans]]\nid = "{s}"\npath = "{path}"\nscan = {i}\nuse_pose = true\n'
            for i, s in enumerate(SUBSET)
        )
    )
    result = invoke("register-plot", toml, "--out", tmp_path / "out", "-j", "1")
    assert result.exit_code == 0, result.output
    got = load_poses(tmp_path / "out" / "poses.json")
    ref = got.transform(SUBSET[0])
    for sid in SUBSET:  # the true poses in S0's frame
        rot, trans = pose_error(inverse(ref) @ got.transform(sid), poses[sid])
        assert trans < 0.02 and rot < 0.1, (sid, trans, rot)
    import json

    records = [json.loads(p.read_text()) for p in (tmp_path / "out" / "pairs").glob("*.json")]
    by_pair = {frozenset((r["source"], r["target"])): r for r in records}
    right = by_pair[frozenset(("P1-S0", "P1-S2"))]
    assert right["status"] == "ok" and right["steps"].get("coarse_skipped")
    # S3's first pair checks its wrong stored pose and searches; its other pair then starts from
    # the pose the graph implies (no longer the stored one), and may skip the search
    s3 = [by_pair[frozenset((other, "P1-S3"))] for other in ("P1-S0", "P1-S2")]
    searched = [r for r in s3 if r["status"] != "ok" or "coarse_skipped" not in r["steps"]]
    assert searched  # the wrong stored pose never skips the search
    for r in searched:
        assert r["status"] != "ok" or r["coarse"]["stored_pose"]["verified"] is False
    for r in records:  # no pair, verified first or searched, holds a wrong pose
        if r["status"] == "ok":
            true = inverse(poses[r["target"]]) @ poses[r["source"]]
            rot, trans = pose_error(np.asarray(r["transform"]), true)
            assert trans < SIM_PAIR_MAX_M and rot < SIM_PAIR_MAX_DEG, (r["source"], r["target"])

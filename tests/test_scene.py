"""The scene check: a cloud that is not a forest (a pump, a room, random points) is refused before
any pose is weighed, naming the cloud and the figure; the simulated forest scans pass it."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import assert_one_line_error, invoke

from plotmosaic.align import judge, scene
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.config.align import AlignConfig
from plotmosaic.errors import RegistrationFailed
from plotmosaic.io.las import PointCloud, read_cloud


def _room(rng: np.random.Generator, spacing: float = 0.04) -> np.ndarray:
    """A box room 8 x 6 x 3 m: floor, ceiling and four walls, 5 mm noise."""
    faces = [
        ((0, 0, 0), (8, 0, 0), (0, 6, 0)),
        ((0, 0, 3), (8, 0, 0), (0, 6, 0)),
        ((0, 0, 0), (8, 0, 0), (0, 0, 3)),
        ((0, 6, 0), (8, 0, 0), (0, 0, 3)),
        ((0, 0, 0), (0, 6, 0), (0, 0, 3)),
        ((8, 0, 0), (0, 6, 0), (0, 0, 3)),
    ]
    parts = []
    for o, u, v in map(lambda f: [np.asarray(x, float) for x in f], faces):
        n = int(np.linalg.norm(u) * np.linalg.norm(v) / spacing**2)
        a, b = rng.random((2, n))
        parts.append(o + a[:, None] * u + b[:, None] * v + rng.normal(0, 0.005, (n, 3)))
    return np.vstack(parts)


def test_pump_onto_a_forest_scan_exits_3_naming_the_scene(small_sim, e57_dir, tmp_path):
    """Issue 38: the industrial pump (E57, 155k points) onto a simulated forest scan is refused with
    exit 3 and one line naming the cloud and its figures; nothing is written."""
    out = tmp_path / "r.json"
    pump = e57_dir / "pumpAVisualReferenceImage.e57"
    res = invoke("align", pump, small_sim.scan_paths["P1-S0"], "--out", out)
    assert_one_line_error(res, "the source is not a forest scene", "spans", code=3)
    assert "target" not in res.output.split("forest scene")[1], res.output  # the forest passes
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_room_and_random_clouds_are_no_forest_scene(small_sim):
    """A room (walls on a floor) and random clouds (no stems, nothing on lines above a ground) are
    refused by the scene check, naming the figure; the simulated forest scans pass it."""
    cfg = AlignConfig()
    rng = np.random.default_rng(3)
    clouds = {
        "room": (_room(rng), "across its main planes"),
        "uniform box": (rng.random((60_000, 3)) * [30.0, 30.0, 15.0], "stems (< 3)"),
        "gaussian blob": (rng.normal(0, 1, (60_000, 3)) * [6.0, 6.0, 3.0], "stems (< 3)"),
    }
    forest = prepare_cloud(
        read_cloud(small_sim.scan_paths["P1-S0"], attributes=False), "tls", 3, cfg, 1, "target"
    )
    assert scene.problems(scene.figures(forest, cfg.judge), cfg.judge) == []
    for name, (xyz, why) in clouds.items():
        other = prepare_cloud(PointCloud(xyz), "tls", 3, cfg, 0, "source")
        found = scene.problems(scene.figures(other, cfg.judge), cfg.judge)
        assert any(why in p for p in found), (name, found)
        for src, tgt, role in ((other, forest, "source"), (forest, other, "target")):
            with pytest.raises(RegistrationFailed, match=f"the {role} is not a forest scene"):
                judge.judge(src, tgt, np.eye(4), [], cfg.judge)
    off = cfg.judge.model_copy(
        update={"scene": cfg.judge.scene.model_copy(update={"enabled": False})}
    )
    scene.check(other, forest, off)  # the check can be turned off

"""Sensor kinds detected from the clouds (align/kinds.py): every real input and the simulator's scans."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from plotmosaic.align.kinds import (
    DEFAULT_KIND,
    KindEvidence,
    decide,
    detect_kind,
    occupied_cells,
)
from plotmosaic.align.pipeline import pair_kinds
from plotmosaic.config.align import AlignConfig
from plotmosaic.config.kinds import KindConfig
from plotmosaic.io.las import read_cloud
from plotmosaic.poses import load_poses

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
CONFIG = AlignConfig()


def kind_of(xyz: np.ndarray) -> str:
    return detect_kind(xyz, CONFIG.kinds, CONFIG.viewpoint).kind


def data_file(relative: str) -> Path:
    path = DATA / relative
    if not path.is_file():
        pytest.skip(f"shared/data/{relative} not present")
    return path


@pytest.mark.parametrize(
    ("relative", "expected"),
    [
        ("spanner/ALS_Clip.laz", "als"),
        ("spanner/UAS_Clip.laz", "uls"),
        ("spanner/MLS_Clip.laz", "mls"),
        # a merged tripod plot: ground-based, no single station, the ground seen all round
        ("treels/pine_plot.laz", "tls"),
        # single terrestrial scans (an industrial scene, an object, a synthetic cube)
        ("e57/pumpAVisualReferenceImage.e57", "tls"),
        ("e57/bunnyDouble.e57", "tls"),
        ("e57/ColouredCubeFloat.e57", "tls"),
    ],
)
def test_real_inputs_get_their_kind(relative, expected):
    xyz = read_cloud(data_file(relative), attributes=False).xyz
    found = detect_kind(xyz, CONFIG.kinds, CONFIG.viewpoint)
    assert found.kind == expected, found.reason
    assert found.reason and "\n" not in found.reason


def test_simulated_scans_and_tile_get_their_kind(small_sim):
    truth = load_poses(small_sim.ground_truth_path)
    merged = []
    for scan_id, path in small_sim.scan_paths.items():
        xyz = read_cloud(path, attributes=False).xyz
        found = detect_kind(xyz, CONFIG.kinds, CONFIG.viewpoint)
        assert found.kind == "tls", (scan_id, found.reason)
        assert found.evidence.station, (scan_id, found.reason)  # scanner frame: the origin crowds
        T = truth.transform(scan_id)
        merged.append(xyz @ T[:3, :3].T + T[:3, 3])
    for path in small_sim.als_paths:
        assert kind_of(read_cloud(path, attributes=False).xyz) == "als"
    # the scans merged in the plot frame: no single station any more, still tripod scans
    plot = detect_kind(np.vstack(merged), CONFIG.kinds, CONFIG.viewpoint)
    assert plot.kind == "tls" and not plot.evidence.station, plot.reason


def test_same_seed_same_figures(small_sim):
    xyz = read_cloud(small_sim.als_paths[0], attributes=False).xyz
    assert detect_kind(xyz, CONFIG.kinds, CONFIG.viewpoint, seed=3) == detect_kind(
        xyz, CONFIG.kinds, CONFIG.viewpoint, seed=3
    )


def test_too_small_to_tell_is_the_default_kind():
    rng = np.random.default_rng(0)
    few = rng.uniform(0, 50, (200, 3))  # wide but a handful of points
    tiny = rng.uniform(0, 0.5, (20_000, 3))  # many points, an object's size
    for xyz in (few, tiny):
        found = detect_kind(xyz, CONFIG.kinds, CONFIG.viewpoint)
        assert found.kind == DEFAULT_KIND and "too small" in found.reason
        assert found.to_dict()["evidence"]["coverage"] is None  # JSON: not measured is null


@pytest.mark.parametrize("n", [1, 7, 5000])
def test_occupied_cells_are_numpys_unique_rows(n):
    # a wide, far-off and uneven cloud: cells in both directions, many sharing a row or a column
    rng = np.random.default_rng(n)
    xy = rng.normal(size=(n, 2)) * [40.0, 3.0] + [4.0e5, -6.0e6]
    xy[: n // 2, 1] = xy[0, 1]  # half the points in one row of cells
    idx = np.floor((xy - xy.min(axis=0)) / 0.5).astype(np.int64)
    cells, inverse, counts = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    got = occupied_cells(xy, 0.5)
    assert got[0].dtype == cells.dtype
    np.testing.assert_array_equal(got[0], cells)
    np.testing.assert_array_equal(got[1], inverse.ravel())
    np.testing.assert_array_equal(got[2], counts)


AIRBORNE = KindEvidence(
    points=30_000,
    extent_m=27.0,
    density_per_m2=40.0,
    coverage=1.0,
    dense_share=0.1,
    understorey_share=0.02,
    ground_share=0.25,
    crowding=0.0,
    station=False,
)


def test_decision_follows_the_thresholds():
    cfg = KindConfig()
    assert decide(AIRBORNE, cfg).kind == "als"
    dense = replace(AIRBORNE, density_per_m2=cfg.min_uls_density)
    assert decide(dense, cfg).kind == "uls"
    # uneven strips still airborne while the canopy hides the understorey; not once it shows
    strips = replace(AIRBORNE, dense_share=0.2)
    assert decide(strips, cfg).kind == "als"
    below = replace(strips, understorey_share=0.15)
    assert decide(below, cfg).kind == "tls"
    assert decide(replace(below, ground_share=0.02), cfg).kind == "mls"
    # holes between the rays: ground-based whatever its evenness
    assert decide(replace(AIRBORNE, coverage=0.7), cfg).kind == "tls"
    # an open field (no canopy) seen from above: the even density decides
    assert decide(replace(AIRBORNE, understorey_share=float("nan")), cfg).kind == "als"
    assert decide(replace(strips, understorey_share=float("nan")), cfg).kind == "tls"
    looser = cfg.model_copy(update={"min_uls_density": 30.0})
    assert decide(AIRBORNE, looser).kind == "uls"


def test_given_kind_overrides_detection(small_sim):
    als = read_cloud(small_sim.als_paths[0], attributes=False).xyz
    scan = read_cloud(small_sim.scan_paths["P1-S0"], attributes=False).xyz
    sk, tk, detected = pair_kinds(als, scan, "TLS", None, CONFIG)
    assert (sk, tk) == ("tls", "tls") and set(detected) == {"target"}
    sk, tk, detected = pair_kinds(als, None, None, "mls", CONFIG)
    assert (sk, tk) == ("als", "mls") and set(detected) == {"source"}

"""The fine stage between two sparse terrestrial scans: stems seen from opposite sides must not pull
the scanners together (issue 16's contraction on the `large` preset)."""

from __future__ import annotations

import numpy as np
import pytest

from plotmosaic.align.config import AlignConfig
from plotmosaic.align.pipeline import _fine_schedule, final_icp
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.io.frame import to_global_transform, to_local_transform, translation
from plotmosaic.io.las import PointCloud

A, B = np.array([0.0, 0.0, 1.5]), np.array([18.0, 0.0, 1.5])  # two scanners 18 m apart along x


def _scan(scanner: np.ndarray, stems: list, rng: np.random.Generator) -> np.ndarray:
    """First-hit-like points in the scanner's frame: undulating ground, and of each vertical stem
    only the half facing this scanner; density falling with range, 3 mm range noise."""
    g = rng.uniform((-20.0, -20.0), (38.0, 20.0), (36_000, 2))
    parts = [np.column_stack([g, 0.3 * np.sin(g[:, 0] / 7) + 0.2 * np.cos(g[:, 1] / 5)])]
    for cx, cy, r in stems:
        a = rng.uniform(0, 2 * np.pi, max(8, int(2 * np.pi * r / 0.04)) * 60)
        p = np.column_stack([cx + r * np.cos(a), cy + r * np.sin(a), rng.uniform(0, 8, len(a))])
        facing = (p[:, 0] - cx) * (scanner[0] - p[:, 0]) + (p[:, 1] - cy) * (scanner[1] - p[:, 1])
        parts.append(p[facing > 0])
    p = np.concatenate(parts)
    rng_m = np.linalg.norm(p - scanner, axis=1)
    p = p[rng.random(len(p)) < np.clip((6.0 / rng_m) ** 2, 0.02, 1.0)]
    d = p - scanner
    r = np.linalg.norm(d, axis=1)
    return d * ((r + rng.normal(0, 0.003, len(r))) / r)[:, None]


@pytest.fixture(scope="module")
def sparse_pair():
    rng = np.random.default_rng(0)
    n = 40
    stems = list(
        zip(rng.uniform(-8, 26, n), rng.uniform(-12, 12, n), rng.uniform(0.06, 0.2, n), strict=True)
    )
    cfg = AlignConfig()
    src = prepare_cloud(PointCloud(_scan(A, stems, rng)), "tls", 3, cfg, 0)
    tgt = prepare_cloud(PointCloud(_scan(B, stems, rng)), "tls", 3, cfg, 1)
    return src, tgt, translation(A - B)  # source scanner frame -> target scanner frame


def _baseline_error_cm(src, tgt, truth, config) -> np.ndarray:
    """Error (cm) of the source scanner's position after the final ICP started at the truth."""
    T = final_icp(src, tgt, to_local_transform(truth, src.frame, tgt.frame), config)[0]
    return 100 * (to_global_transform(T, src.frame, tgt.frame)[:3, 3] - truth[:3, 3])


def test_stems_seen_from_opposite_sides_do_not_shorten_the_baseline(sparse_pair):
    src, tgt, truth = sparse_pair
    scaled = AlignConfig(
        final_polish_fixed_kinds=[]
    )  # the polish stretched by sparseness: left out
    assert len(_fine_schedule(src, tgt, scaled)[0]) == len(scaled.final_schedule)
    before = _baseline_error_cm(src, tgt, truth, scaled)
    # +x: the source scanner moved toward the target one (seeds 0-4: 1.2-1.7 cm)
    assert before[0] > 0.8
    cfg = AlignConfig()
    stages, kernel = _fine_schedule(src, tgt, cfg)
    assert stages[-1].max_distance == cfg.final_polish_distance
    assert kernel == cfg.final_polish_kernel
    after = _baseline_error_cm(src, tgt, truth, cfg)
    assert abs(after[0]) < 0.5 and np.linalg.norm(after) < 0.7


def test_airborne_pairs_keep_the_scaled_polish(sparse_pair):
    src, tgt, _ = sparse_pair
    cfg = AlignConfig()
    src.kind = "als"  # a sparse ALS tile: its planes are 1 m normals, a 3 cm kernel would starve
    try:
        assert len(_fine_schedule(src, tgt, cfg)[0]) == len(cfg.final_schedule)
    finally:
        src.kind = "tls"


def test_symmetric_fine_stage_uses_both_scans_planes(sparse_pair):
    """One direction matches only the source's sample to the target's planes: on this sparse pair it
    ends 0.4 cm across the baseline; each scan's sample on the other's planes, in one solve, 0.13 cm."""
    src, tgt, truth = sparse_pair
    one_way = _baseline_error_cm(src, tgt, truth, AlignConfig(final_symmetric_kinds=[]))
    both = _baseline_error_cm(src, tgt, truth, AlignConfig())
    assert np.linalg.norm(one_way) > 0.3
    assert np.linalg.norm(both) < 0.2
    # only pairs of the listed kinds: a TLS -> MLS pair stays one way
    src.kind = "mls"
    try:
        mixed = _baseline_error_cm(src, tgt, truth, AlignConfig())
        mixed_one_way = _baseline_error_cm(src, tgt, truth, AlignConfig(final_symmetric_kinds=[]))
    finally:
        src.kind = "tls"
    np.testing.assert_allclose(mixed, mixed_one_way, atol=1e-12)


def test_mirror_rows_are_the_reverse_matches_in_target_coordinates():
    """Each reverse row is a source point moved by T, the target sample point matched to it, and the
    source normal turned by T: zero residual where the two clouds coincide under T."""
    from scipy.spatial import cKDTree

    from plotmosaic.align.icp import Mirror

    rng = np.random.default_rng(3)
    source = rng.uniform(-5, 5, (500, 3))
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    c, s = np.cos(0.3), np.sin(0.3)
    T = np.array([[c, -s, 0, 1.0], [s, c, 0, -2.0], [0, 0, 1, 0.5], [0, 0, 0, 1]])
    target_sample = source[:50] @ T[:3, :3].T + T[:3, 3]
    m = Mirror(target_sample, source, cKDTree(source), lambda j: normals[j])
    empty = np.zeros((0, 3))
    a, b, n = m.stacked(T, 0.01, empty, empty, empty)
    assert len(a) == 50
    np.testing.assert_allclose(a, b, atol=1e-9)
    np.testing.assert_allclose(n, normals[:50] @ T[:3, :3].T, atol=1e-12)

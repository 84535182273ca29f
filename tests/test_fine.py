"""The fine stage between two sparse terrestrial scans: stems seen from opposite sides must not pull
the scanners together (issue 16's contraction on the `large` preset)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial import cKDTree

from plotmosaic.align.fine import final_icp
from plotmosaic.align.fine import fine_schedule as _fine_schedule
from plotmosaic.align.icp import Mirror, facing
from plotmosaic.align.normals import LazyNormals
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.align.viewpoint import crowding, scanner_viewpoint
from plotmosaic.config.align import AlignConfig, ViewpointConfig
from plotmosaic.graph.prepared import load_prepared, save_prepared
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


def _blind(cloud):
    """The same prepared cloud without its scanner position (no side test)."""
    return dataclasses.replace(cloud, viewpoint=None)


def _planes(cloud):
    """The same prepared cloud with plane normals everywhere (no circles on its stems)."""
    t = cloud.target_normals
    return dataclasses.replace(
        cloud, target_normals=LazyNormals(cloud.points, cloud.tree, t.radius, t.max_nn)
    )


def _baseline_error_cm(src, tgt, truth, config) -> np.ndarray:
    """Error (cm) of the source scanner's position after the final ICP started at the truth."""
    T = final_icp(src, tgt, to_local_transform(truth, src.frame, tgt.frame), config).T
    return 100 * (to_global_transform(T, src.frame, tgt.frame)[:3, 3] - truth[:3, 3])


def test_stems_seen_from_opposite_sides_do_not_shorten_the_baseline(sparse_pair):
    src, tgt, truth = sparse_pair
    scaled = AlignConfig(
        final_polish_fixed_kinds=[]
    )  # the polish stretched by sparseness: left out
    assert len(_fine_schedule(src, tgt, scaled)[0]) == len(scaled.final_schedule)
    src, tgt = _planes(src), _planes(tgt)
    before = _baseline_error_cm(_blind(src), _blind(tgt), truth, scaled)
    # +x: the source scanner moved toward the target one (seeds 0-2: 1.0-1.3 cm)
    assert before[0] > 0.8
    cfg = AlignConfig()
    stages, kernel = _fine_schedule(src, tgt, cfg)
    assert stages[-1].max_distance == cfg.final_polish_distance
    assert kernel == cfg.final_polish_kernel
    after = _baseline_error_cm(_blind(src), _blind(tgt), truth, cfg)
    assert abs(after[0]) < 0.5 and np.linalg.norm(after) < 0.7


def test_circle_normals_on_the_stems_halve_the_shortening(sparse_pair):
    """Blind and unpolished, plane normals leave the baseline 1.0-1.3 cm short (seeds 0-2) and up to
    1.1 cm across; each stem point's radial normal leaves 0.4-0.6 cm and 0.14 cm."""
    src, tgt, truth = sparse_pair
    unpolished = AlignConfig(final_polish_fixed_kinds=[])
    planes = _baseline_error_cm(_blind(_planes(src)), _blind(_planes(tgt)), truth, unpolished)
    circles = _baseline_error_cm(_blind(src), _blind(tgt), truth, unpolished)
    assert circles[0] < 0.7 < planes[0]
    assert abs(circles[1]) < 0.3 < abs(planes[1])


def test_the_side_test_keeps_the_two_faces_of_a_stem_apart(sparse_pair):
    """With both scanners known, a match whose plane has them on opposite sides is left out: the
    unpolished stage no longer shortens the baseline (blind: > 0.8 cm above)."""
    src, tgt, truth = sparse_pair
    assert src.viewpoint is not None and tgt.viewpoint is not None
    unpolished = _baseline_error_cm(src, tgt, truth, AlignConfig(final_polish_fixed_kinds=[]))
    assert abs(unpolished[0]) < 0.4
    assert np.linalg.norm(_baseline_error_cm(src, tgt, truth, AlignConfig())) < 0.4
    # one scanner unknown: no side test, the blind result exactly
    np.testing.assert_allclose(
        _baseline_error_cm(src, _blind(tgt), truth, AlignConfig()),
        _baseline_error_cm(_blind(src), _blind(tgt), truth, AlignConfig()),
        atol=1e-12,
    )


def test_a_scanner_is_trusted_only_where_the_cloud_crowds_around_it(sparse_pair):
    """The file origin is the scanner of a single scan in its own frame (1/r^2 density about it); the
    same scan in a project frame, a cloud of even density, or a mobile cloud get none."""
    src, _, _ = sparse_pair
    np.testing.assert_allclose(src.frame.to_global(src.viewpoint), 0.0, atol=1e-12)
    cfg, rng = ViewpointConfig(), np.random.default_rng(0)
    # density falls only beyond 6 m here: a flatter peak than a real scan's
    xyz = _scan(A, [(4.0, 3.0, 0.2)], rng)
    assert crowding(xyz, cfg, rng) > cfg.min_crowding
    assert scanner_viewpoint(xyz + (40.0, 0.0, 0.0), "tls", cfg, rng) is None  # project frame
    even = rng.uniform((-20, -20, 0), (20, 20, 8), (40_000, 3))
    assert scanner_viewpoint(even, "tls", cfg, rng) is None
    assert scanner_viewpoint(xyz, "mls", cfg, rng) is None
    assert scanner_viewpoint(xyz, "tls", cfg, rng) is not None


def test_facing_tells_the_two_sides_of_a_plane_apart():
    n = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]])
    x = np.zeros((3, 3))
    a = np.array([-3.0, 0.0, 1.5])
    b = np.array([[4.0, 0.0, 1.5], [-2.0, 1.0, 1.5], [5.0, 0.0, 1.5]])
    # a vertical face between the scanners; both in front of it; ground below both
    assert facing(n[:1], x[:1], a, b[0]).tolist() == [False]
    assert facing(n[1:2], x[1:2], a, b[1]).tolist() == [True]
    assert facing(n[2:], x[2:], a, b[2]).tolist() == [True]


def test_airborne_pairs_keep_the_scaled_polish(sparse_pair):
    src, tgt, _ = sparse_pair
    cfg = AlignConfig()
    # a sparse ALS tile: its planes are 1 m normals, a 3 cm kernel would starve
    als = dataclasses.replace(src, kind="als")
    assert len(_fine_schedule(als, tgt, cfg)[0]) == len(cfg.final_schedule)


def test_symmetric_fine_stage_uses_both_scans_planes(sparse_pair):
    """One direction matches only the source's sample to the target's planes: on this sparse pair it
    ends 0.4 cm across the baseline; each scan's sample on the other's planes, in one solve, 0.13 cm."""
    # plane normals: the stems' circle normals leave little bias either way (0.08 cm one way)
    src, tgt = _blind(_planes(sparse_pair[0])), _blind(_planes(sparse_pair[1]))
    truth = sparse_pair[2]
    one_way = _baseline_error_cm(src, tgt, truth, AlignConfig(final_symmetric_kinds=[]))
    both = _baseline_error_cm(src, tgt, truth, AlignConfig())
    assert np.linalg.norm(one_way) > 0.3
    assert np.linalg.norm(both) < 0.2
    # only pairs of the listed kinds: a TLS -> MLS pair stays one way
    mls = dataclasses.replace(src, kind="mls")
    mixed = _baseline_error_cm(mls, tgt, truth, AlignConfig())
    mixed_one_way = _baseline_error_cm(mls, tgt, truth, AlignConfig(final_symmetric_kinds=[]))
    np.testing.assert_allclose(mixed, mixed_one_way, atol=1e-12)


def test_mirror_rows_are_the_reverse_matches_in_target_coordinates():
    """Each reverse row is a source point moved by T, the target sample point matched to it, and the
    source normal turned by T: zero residual where the two clouds coincide under T."""
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


def test_the_scanner_survives_the_prepared_cache(sparse_pair, tmp_path):
    """A cached prepared cloud keeps its scanner (or its lack of one) across runs."""
    src, _, _ = sparse_pair
    for cloud, name in ((src, "seen.npz"), (_blind(src), "blind.npz")):
        again = load_prepared(save_prepared(tmp_path / name, cloud))
        if cloud.viewpoint is None:
            assert again.viewpoint is None
        else:
            np.testing.assert_array_equal(again.viewpoint, cloud.viewpoint)


def test_only_sparse_ground_based_scans_get_stem_normals(sparse_pair, tmp_path):
    """The sparse radius on a TLS scan brings circle normals; a dense scan, or the same points
    called airborne, keeps plane normals; the prepared cache keeps the choice."""
    src, _, _ = sparse_pair
    cfg = AlignConfig()
    assert src.normal_radius == cfg.normal_radius_sparse
    assert src.target_normals.stems == cfg.stem_normals
    cloud = PointCloud(_scan(A, [(5.0, 0.0, 0.15)], np.random.default_rng(2)))
    assert prepare_cloud(cloud, "als", 3, cfg, 0).target_normals.stems is None
    assert (
        prepare_cloud(
            cloud, "tls", 3, AlignConfig(stem_normals={"kinds": []}), 0
        ).target_normals.stems
        is None
    )
    # planes found within the normal radius itself (not the sparse rule's): no circles
    wide = AlignConfig(normal_radius=1.0)
    dense = prepare_cloud(cloud, "tls", 3, wide, 0)
    assert dense.normal_radius == wide.normal_radius and dense.target_normals.stems is None
    again = load_prepared(save_prepared(tmp_path / "c.npz", src))
    assert again.target_normals.stems == src.target_normals.stems
    idx = np.arange(0, len(src.points), 97)
    np.testing.assert_array_equal(again.target_normals(idx), src.target_normals(idx))

"""numpy voxel grids and neighbourhood shapes (normals, eigen-features), eager and lazy."""

from __future__ import annotations

import numpy as np
from builders import plane_basis
from scipy.spatial import cKDTree

from plotmosaic.align.normals import (
    LazyNormals,
    eigenvalues_sym3,
    eigenvector_sym3,
    level_shape,
    local_shape,
    stem_normals,
)
from plotmosaic.align.voxel import (
    FACE_PHASE,
    KEY_BLOCK,
    cube_keys,
    thin,
    voxel_centroids,
    voxelize,
)
from plotmosaic.config.align import StemNormalConfig
from plotmosaic.io.frame import column_bounds


def test_voxel_centroids_match_a_plain_group_by_and_come_in_cube_order():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 7, (20_000, 3)) + [470_000.0, 3_810_000.0, 2_100.0]  # UTM-sized
    got = voxel_centroids(pts, 0.5)
    cells = {}
    for p in pts:
        cells.setdefault(tuple(np.floor(p / 0.5 - FACE_PHASE).astype(np.int64)), []).append(p)
    assert len(got) == len(cells)
    want = np.array(
        [np.mean(cells[k], axis=0) for k in sorted(cells)]
    )  # lexicographic = cube order
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-7)
    keys = cube_keys(got, 0.5)
    assert np.all(np.diff(keys) > 0)  # one point per cube, sorted


def test_grid_of_quantised_coordinates_does_not_change_under_a_utm_offset():
    """LAS coordinates sit on a 1 mm lattice, many of them on multiples of the cube size; the grid
    of the local coordinates must be the same whether they were read as such or as UTM - offset."""
    rng = np.random.default_rng(3)
    local = np.round(rng.uniform(-5, 5, (50_000, 3)), 3)
    offset = np.array([470_123.0, 3_810_456.0, 2_100.0])
    base, shifted = voxelize(local, 0.05), voxelize(local + offset, 0.05, offset)
    assert len(base.centroids) == len(shifted.centroids)
    np.testing.assert_allclose(shifted.centroids, base.centroids, rtol=0, atol=1e-8)


def test_cube_keys_by_blocks_equal_whole_column_arithmetic():
    """Keys are computed in cache-sized blocks from the columns' bounds: the same float operations as
    on whole columns, so every key is identical (across block edges, with an offset, given bounds)."""
    rng = np.random.default_rng(5)
    offset = np.array([470_123.0, 3_810_456.0, 2_100.0])
    pts = rng.normal(0, 20, (3 * KEY_BLOCK + 17, 3)) + offset
    for size in (0.05, 0.3):
        cols = []
        for i in range(3):  # the plain definition: floor((x - offset) / size - phase) - its minimum
            c = np.floor((pts[:, i] - offset[i]) * (1.0 / size) - FACE_PHASE)
            cols.append(c - c.min())
        dims = [c.max() + 1.0 for c in cols]
        want = ((cols[0] * dims[1] + cols[1]) * dims[2] + cols[2]).astype(np.int64)
        np.testing.assert_array_equal(cube_keys(pts, size, offset), want)
        np.testing.assert_array_equal(cube_keys(pts, size, offset, column_bounds(pts)), want)
    assert len(cube_keys(np.zeros((0, 3)), 0.1)) == 0


def test_members_lists_every_point_of_the_chosen_cubes():
    rng = np.random.default_rng(4)
    pts = rng.uniform(0, 2, (3000, 3))
    grid = voxelize(pts, 0.5)
    cubes = np.array([0, 5, 17])
    keys = cube_keys(pts, 0.5)
    wanted = np.flatnonzero(np.isin(keys, np.unique(keys)[cubes]))
    np.testing.assert_array_equal(np.sort(grid.members(cubes)), wanted)
    np.testing.assert_allclose(pts[grid.members(cubes[:1])].mean(axis=0), grid.centroids[0])


def test_thin_keeps_the_first_point_of_each_cube():
    pts = np.array([[0.05, 0.01, 0.01], [0.1, 0.1, 0.1], [0.25, 0.01, 0.01], [0.01, 0.02, 0.03]])
    np.testing.assert_array_equal(thin(pts, 0.2), [0, 2])
    assert len(thin(np.zeros((0, 3)), 0.2)) == 0


def test_local_shape_on_a_plane_a_line_and_a_scatter():
    rng = np.random.default_rng(1)
    n, u, v = plane_basis([0.3, -0.2, 1.0])
    ab = rng.uniform(-2, 2, (8000, 2))
    plane = ab[:, :1] * u + ab[:, 1:] * v + rng.normal(0, 0.002, (8000, 1)) * n
    line = np.column_stack([rng.normal(0, 0.003, (2000, 2)), rng.uniform(0, 4, 2000)]) + [
        10.0,
        0,
        0,
    ]  # a thin stem
    blob = rng.normal(0, 0.3, (3000, 3)) + [20.0, 0, 0]
    pts = np.vstack([plane, line, blob])
    tree = cKDTree(pts)
    normals, feats, counts = local_shape(pts, tree, pts[[0, 8000, 10_000]], 0.25, 30)
    assert abs(normals[0] @ n) > 0.999
    assert feats[0, 1] > 0.8  # planarity
    assert feats[1, 0] > 0.9  # linearity
    assert feats[2, 2] > 0.1 and counts.min() >= 3  # scattering
    # nobody within the radius: no plane, called fully scattered
    lone = np.vstack([pts, [[100.0, 100.0, 100.0]]])
    _, f_lone, c_lone = local_shape(lone, cKDTree(lone), lone[-1:], 0.25, 30)
    assert c_lone[0] == 0 and f_lone[0, 2] == 1.0  # count 0: no plane
    # the lazy target normals are the eager ones, computed once
    lazy = LazyNormals(pts, tree, 0.25, 30)
    idx = np.array([5, 9000, 5, 10_500])
    np.testing.assert_allclose(lazy(idx), local_shape(pts, tree, pts[idx], 0.25, 30)[0])
    assert lazy.known.sum() == 3


def test_level_shape_sees_a_stem_as_a_vertical_line_and_the_ground_as_a_level_plane():
    """Dense input thinned to a support cloud: the 0.25 m normal and the 0.5 m features span their spheres."""
    rng = np.random.default_rng(5)
    ground = np.column_stack([rng.uniform(-3, 3, (60_000, 2)), rng.normal(0, 0.003, 60_000)])
    a = rng.uniform(0, 2 * np.pi, 20_000)
    stem = np.column_stack(
        [0.15 * np.cos(a) + 10, 0.15 * np.sin(a), rng.uniform(0.5, 3.5, 20_000)]
    )  # 30 cm stem
    pts = np.vstack([ground, stem])
    support = pts[thin(pts, 0.1)]
    normals, feats, counts = level_shape(
        support, cKDTree(support), np.array([[0.0, 0.0, 0.0], [10.15, 0.0, 2.0]]), 0.25, 32
    )
    assert (
        abs(normals[0, 2]) > 0.99 and feats[0, 1] > 0.6 and feats[0, 2] < 0.05 and feats[0, 3] < 0.2
    )  # level plane
    assert abs(normals[1, 2]) < 0.2 and feats[1, 3] > 0.9  # vertical surface, vertical main axis
    assert counts.min() >= 3


def test_closed_form_eigen_matches_lapack_on_planes_lines_and_scatter():
    rng = np.random.default_rng(6)
    R = np.linalg.qr(rng.normal(size=(300, 3, 3)))[0]
    spectra = np.concatenate(
        [
            np.tile([1e-2, 1e-2, 1e-8], (100, 1)),
            np.tile([1e-1, 1e-4, 1e-5], (100, 1)),
            rng.uniform(1e-4, 1e-2, (100, 3)),
        ]
    )  # planes, lines, scatter
    A = np.einsum("nij,nj,nkj->nik", R, spectra, R)
    c = {(a, b): A[:, a, b] for a in range(3) for b in range(a, 3)}
    l1, l2, l3 = eigenvalues_sym3(c)
    vals, vecs = np.linalg.eigh(A)
    np.testing.assert_allclose(np.column_stack([l3, l2, l1]), vals, rtol=1e-6, atol=1e-12)
    small, large = eigenvector_sym3(c, l3), eigenvector_sym3(c, l1)
    # axial: compare up to sign, where the eigenvalue is well separated (planes' normals, lines' axes)
    assert np.all(np.abs(np.einsum("ij,ij->i", small[:100], vecs[:100, :, 0])) > 1 - 1e-6)
    assert np.all(np.abs(np.einsum("ij,ij->i", large[100:200], vecs[100:200, :, 2])) > 1 - 1e-6)


def test_eigenvectors_are_the_longest_np_cross_product_to_the_bit():
    rng = np.random.default_rng(7)
    A = rng.normal(size=(5000, 3, 3)) * rng.lognormal(size=(5000, 1, 1)) * 1e-2
    A = A @ A.transpose(0, 2, 1)
    c = {(a, b): A[:, a, b] for a in range(3) for b in range(a, 3)}
    lam = eigenvalues_sym3(c)[2]
    rows = A - lam[:, None, None] * np.eye(3)
    crosses = [np.cross(rows[:, a], rows[:, b]) for a, b in ((0, 1), (0, 2), (1, 2))]
    norms = np.column_stack([np.einsum("ij,ij->i", v, v) for v in crosses])
    want = np.choose(norms.argmax(axis=1)[:, None], crosses)
    want /= np.sqrt(norms.max(axis=1))[:, None]
    assert np.array_equal(eigenvector_sym3(c, lam), want)


def _sparse_stem_and_ground(rng: np.random.Generator):
    """A 0.15 m stem 8 m from the scanner at the origin, seen over 5 columns of a 0.45 deg scan
    (the 130 deg arc facing it), 2 mm noise; level ground around it at the same sparse spacing."""
    cx, r = 8.0, 0.15
    az = np.radians(np.arange(-0.9, 0.91, 0.45))  # the columns (deg) seen from the origin
    z = np.arange(0.0, 3.0, 0.11)
    pts = []
    for a in az:  # the first hit of each ray on the circle
        d = np.array([np.cos(a), np.sin(a)])
        b = d @ [cx, 0.0]
        t = b - np.sqrt(b**2 - (cx**2 - r**2))
        pts += [np.column_stack([np.full_like(z, t * d[0]), np.full_like(z, t * d[1]), z])]
    stem = np.vstack(pts)
    stem += rng.normal(0, 0.002, stem.shape)
    g = rng.uniform((3.0, -3.0), (7.0, 3.0), (600, 2))
    ground = np.column_stack([g, rng.normal(0, 0.002, len(g))])
    radial = np.column_stack([stem[:, :2] - [cx, 0.0], np.zeros(len(stem))])
    return stem, ground, radial / np.linalg.norm(radial, axis=1, keepdims=True)


def test_stem_normals_are_radial_where_a_sparse_plane_fit_sees_the_view_direction():
    stem, ground, radial = _sparse_stem_and_ground(np.random.default_rng(3))
    pts = np.vstack([stem, ground])
    tree, cfg = cKDTree(pts), StemNormalConfig()
    angle = lambda a, b: np.degrees(np.arccos(np.clip(np.abs((a * b).sum(axis=1)), 0, 1)))  # noqa: E731
    plane = local_shape(pts, tree, stem, 1.0, 20)[0]
    circle, fitted = stem_normals(pts, tree, stem, 1.0, cfg, 20)
    assert fitted.mean() > 0.9
    # the outer columns are 50-60 deg off the view direction; the circle's normals follow the bark
    assert np.percentile(angle(plane, radial), 90) > 30
    assert np.percentile(angle(circle[fitted], radial[fitted]), 90) < 5
    # the ground is a disc, not a stem: no circle
    assert not stem_normals(pts, tree, ground, 1.0, cfg, 20)[1].any()
    # the lazy normals: circles where fitted, planes elsewhere, each computed once
    lazy = LazyNormals(pts, tree, 1.0, 20, cfg)
    idx = np.array([0, len(stem) + 5, 0])
    got = lazy(idx)
    assert angle(got[:1], radial[:1])[0] < 5
    np.testing.assert_allclose(got[1], local_shape(pts, tree, pts[idx[1:2]], 1.0, 20)[0][0])
    assert lazy.known.sum() == 2
    # too few neighbours, a radius out of bounds: plane normals kept
    assert not stem_normals(pts, tree, stem, 1.0, StemNormalConfig(min_points=1000), 20)[1].any()
    assert not stem_normals(pts, tree, stem, 1.0, StemNormalConfig(max_radius=0.05), 20)[1].any()


def test_stem_normals_planes_are_local_shapes_to_the_bit_also_among_equally_near_neighbours():
    rng = np.random.default_rng(9)
    grid = np.stack(np.meshgrid(*[np.arange(0.0, 1.2, 0.1)] * 3), axis=-1).reshape(-1, 3)
    pts = np.vstack([grid, rng.uniform(0, 1.2, (400, 3))])  # ties on the grid, none off it
    tree, cfg = cKDTree(pts), StemNormalConfig()
    normals, fitted = stem_normals(pts, tree, pts, 0.35, cfg, 20)
    plane = local_shape(pts, tree, pts, 0.35, 20)[0]
    assert not fitted.all()
    assert normals[~fitted].tobytes() == plane[~fitted].tobytes()

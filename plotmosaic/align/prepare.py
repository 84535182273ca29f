"""One cloud ready for ForestAlign: local frame, voxel grids, KD-tree, normals and complexity levels of a sample."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.align.complexity import fit_levels
from plotmosaic.align.normals import LazyNormals, level_shape, local_shape
from plotmosaic.align.outliers import stray_mask
from plotmosaic.align.sampling import sample
from plotmosaic.align.viewpoint import scanner_viewpoint
from plotmosaic.align.voxel import thin, thin_with_counts, voxel_centroids, voxelize
from plotmosaic.config.align import AlignConfig, StrayConfig
from plotmosaic.errors import InputError
from plotmosaic.io.frame import Frame, column_bounds
from plotmosaic.io.las import PointCloud

MIN_POINTS = 50
SPARSE_PROBE = (
    5_000  # sample points whose neighbour count decides the sparse rule (its median is stable)
)
# Widest cloud registered (m, any axis, after stray points are dropped): a plot or a cropped ALS tile
# is far smaller, a wider cloud mixes places or frames. Memory does not follow the extent below it:
# grids over a cloud are sparse (occupied cells only) or grow their cell to a fixed size.
MAX_EXTENT_M = 20_000.0


@dataclass(frozen=True, eq=False)
class PreparedCloud:
    """One cloud ready to register; never changed once made (what the stages compute from it is
    kept in memos owned by the pair or the run: align/memo.py)."""

    frame: Frame
    kind: str
    points: np.ndarray  # (N, 3) local, delta0 voxel centroids in cube order (spatially coherent)
    tree: cKDTree  # over `points`: normals, final-ICP correspondences, quality figures
    level_points: (
        np.ndarray
    )  # (M, 3) the labelled sample: one delta0 point per `level_cell` cube (capped)
    normals: (
        np.ndarray
    )  # (M, 3) at level_points, from the 0.25 m neighbourhood (see normals.level_shape)
    features: np.ndarray  # (M, 4) linearity, planarity, scattering, verticality at 0.5 m
    levels: np.ndarray  # (M,) 0 = least complex
    level_stats: list[dict]
    fine_points: np.ndarray  # seeded sample of the delta (final ICP) grid: this cloud as a source
    target_normals: LazyNormals  # normals of `points`, computed where this cloud is an ICP target
    normal_radius: float
    input_points: int
    seconds: dict = field(default_factory=dict)
    stray_points: int = 0  # input points dropped as detached from the cloud (see align.outliers)
    viewpoint: np.ndarray | None = None  # the scanner, local coordinates (align/viewpoint.py)

    @property
    def k(self) -> int:
        return len(self.level_stats)

    def subset(self, levels) -> tuple[np.ndarray, np.ndarray]:
        """(points, normals) of the labelled sample whose level is in `levels`."""
        sel = np.isin(self.levels, list(levels))
        return self.level_points[sel], self.normals[sel]


def prepare_cloud(
    cloud: PointCloud,
    kind: str,
    levels: int,
    config: AlignConfig,
    seed: int = 0,
    name: str = "cloud",
    robust: RobustPoints | None = None,
    scanner: np.ndarray | None = None,
) -> PreparedCloud:
    """The cloud in its local frame: delta0 grid and its KD-tree, the final ICP's source sample, the
    labelled level sample with its normals and shape features, and the scanner where it is known.
    Every random draw comes from `seed`, in a fixed order. `robust`: the cloud's `robust_points`
    when the caller has them already (align detects kinds on them), so they are made once.
    `scanner`: where the scan was taken from (file coordinates) when the caller knows it; else the
    file origin where the cloud crowds around it (align/viewpoint.py)."""
    t0 = time.perf_counter()
    if len(cloud) < MIN_POINTS:
        raise InputError(
            f"{name}: only {len(cloud)} points, at least {MIN_POINTS} needed to register"
        )
    if levels < 1:
        raise InputError(f"{name}: levels must be >= 1, got {levels}")
    rng = np.random.default_rng(seed)
    robust = robust or robust_points(
        cloud.xyz, getattr(config, "stray", None) or StrayConfig(), name
    )
    xyz, strays, bounds = robust.xyz, robust.dropped, robust.bounds
    frame = Frame.of_bounds(bounds)
    points, fine_points = _grids(xyz, frame, bounds, config, rng, name)
    tree = cKDTree(
        points, balanced_tree=False, compact_nodes=False
    )  # half the build time; points are in cube order
    t1 = time.perf_counter()
    lvs = _level_sample(points, tree, kind, config, rng)
    t2 = time.perf_counter()
    # the mixture is fitted at the delta0 cloud's density, as in the paper (each sample point weighs
    # as many delta0 points as share its cube): on the even sample, far canopy fills most cubes and
    # the components split foliage while ground (3 % of the cubes of a dense scan) gets none
    lv = fit_levels(
        lvs.normals,
        lvs.features,
        levels,
        config.complexity,
        config.vmf,
        seed,
        valid=lvs.counts >= 3,
        weights=lvs.cube_sizes,
    )
    t3 = time.perf_counter()
    # last of the seeded draws, so the samples above are the same whether a kind has a viewpoint or not
    view = scanner_viewpoint(xyz, kind, config.viewpoint, rng)
    view = view if scanner is None else np.asarray(scanner, dtype=float)
    return PreparedCloud(
        frame=frame,
        kind=kind,
        points=points,
        tree=tree,
        level_points=lvs.points,
        normals=lvs.normals,
        features=lvs.features,
        levels=lv.labels,
        level_stats=lv.stats,
        fine_points=fine_points,
        target_normals=LazyNormals(points, tree, lvs.radius, config.normal_max_nn, lvs.stems),
        normal_radius=lvs.radius,
        input_points=len(cloud),
        seconds={"voxel": t1 - t0, "normals": t2 - t1, "levels": t3 - t2},
        stray_points=strays,
        viewpoint=None if view is None else frame.to_local(view),
    )


def _grids(
    xyz: np.ndarray,
    frame: Frame,
    bounds: np.ndarray,
    config: AlignConfig,
    rng: np.random.Generator,
    name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """(delta0 voxel centroids in cube order, the final ICP's source sample), local coordinates."""
    grid = voxelize(
        xyz, config.voxel, frame.offset, bounds
    )  # local coordinates, no shifted copy of 8M points
    points = grid.centroids
    if len(points) < MIN_POINTS:
        raise InputError(
            f"{name}: only {len(points)} points after {config.voxel} m voxels, too few to register"
        )
    # final-ICP source: the delta grid of a seeded sample of delta0 cubes, which is a sample of the
    # whole cloud's delta grid without building that grid over all (8M) input points
    cubes = sample(len(points), config.final_max_source_points, rng)
    fine = voxel_centroids(frame.to_local(xyz[grid.members(cubes)]), config.final_voxel)
    return points, fine[sample(len(fine), config.final_max_source_points, rng)]


@dataclass(frozen=True, eq=False)
class _LevelSample:
    """The even sample the levels are fitted on, with its normals and shape features."""

    points: np.ndarray
    cube_sizes: np.ndarray  # delta0 points in each sample point's level cube
    normals: np.ndarray
    features: np.ndarray
    counts: np.ndarray  # neighbours behind each normal
    radius: float  # normal radius (wider for a sparse cloud)
    stems: object  # circle-normal settings for a sparse ground scan's stems, or None


def _level_sample(
    points: np.ndarray, tree: cKDTree, kind: str, config: AlignConfig, rng: np.random.Generator
) -> _LevelSample:
    """The level sample: one point per level cube (evens out TLS's 1/r^2 density around the scanner),
    its normals over a radius widened for a sparse cloud."""
    keep, cube_sizes = thin_with_counts(points, config.level_cell)
    chosen = sample(len(keep), config.level_max_points, rng)
    level_points, cube_sizes = points[keep[chosen]], cube_sizes[chosen]
    probe = level_points[sample(len(level_points), SPARSE_PROBE, rng)]
    # airborne or far-range: too few points for a plane within normal_radius
    sparse = (
        np.median(local_shape(points, tree, probe, config.normal_radius, config.normal_max_nn)[2])
        < config.sparse_min_neighbors
    )
    radius = (
        max(config.normal_radius, config.normal_radius_sparse) if sparse else config.normal_radius
    )
    # a sparse ground-based scan's stems get circle normals (a 1 m plane fit sees the whole arc)
    stems = config.stem_normals if sparse and kind in config.stem_normals.kinds else None
    support = points[thin(points, config.level_support_ratio * radius)]
    support_tree = cKDTree(support, balanced_tree=False, compact_nodes=False)
    normals, features, counts = level_shape(
        support, support_tree, level_points, radius, config.level_max_nn
    )
    return _LevelSample(level_points, cube_sizes, normals, features, counts, radius, stems)


@dataclass(frozen=True, eq=False)
class RobustPoints:
    """A cloud's points without its detached stray points."""

    xyz: np.ndarray  # the input array itself when nothing was dropped
    dropped: int
    bounds: np.ndarray  # (3, 2) columns' (min, max): shared by the stray check, frame and grid


def robust_points(xyz: np.ndarray, stray: StrayConfig, name: str) -> RobustPoints:
    """The cloud without its detached stray points (align.outliers); refuses an extent no grid can
    hold."""
    bounds = column_bounds(xyz)
    keep = stray_mask(xyz, stray, bounds)
    dropped = int(len(keep) - keep.sum())
    if dropped:
        xyz = xyz[keep]
        bounds = column_bounds(xyz) if len(xyz) else bounds
    if len(xyz) < MIN_POINTS:
        raise InputError(
            f"{name}: only {len(xyz)} points left after dropping {dropped} stray points"
        )
    span = bounds[:, 1] - bounds[:, 0]
    if span.max() > MAX_EXTENT_M:
        raise InputError(
            f"{name}: the cloud spans {span.round(0).tolist()} m (after dropping {dropped} stray "
            f"points), more than {MAX_EXTENT_M:.0f} m; crop it or remove the far points"
        )
    return RobustPoints(xyz, dropped, bounds)

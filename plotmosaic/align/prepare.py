"""One cloud ready for ForestAlign: local frame, voxel grids, normals, complexity levels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from plotmosaic.align.complexity import fit_levels
from plotmosaic.align.config import AlignConfig
from plotmosaic.align.normals import estimate_normals, is_sparse, normals_and_features
from plotmosaic.errors import InputError
from plotmosaic.io.frame import Frame
from plotmosaic.io.las import PointCloud

MIN_POINTS = 50


def to_pcd(points: np.ndarray) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    return pcd


def thin(points: np.ndarray, cell: float) -> np.ndarray:
    """Indices of one point per occupied cube of side `cell` (the first one met), sorted."""
    keys = np.floor(points / cell).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


@dataclass
class PreparedCloud:
    frame: Frame
    kind: str
    points: np.ndarray  # (N, 3) local, voxel delta0
    normals: np.ndarray  # (N, 3)
    features: np.ndarray  # (N, 3) linearity, planarity, scattering
    levels: np.ndarray  # (N,) 0 = least complex
    level_stats: list[dict]
    pcd: o3d.geometry.PointCloud  # points + normals, local
    fine_pcd: o3d.geometry.PointCloud  # voxel delta (final ICP), local; normals on demand
    normal_radius: float
    input_points: int
    seconds: dict = field(default_factory=dict)

    @property
    def k(self) -> int:
        return len(self.level_stats)

    def subset(self, levels, cell: float = 0.0) -> o3d.geometry.PointCloud:
        """The delta0 points (with normals) whose level is in `levels`, thinned to one point per
        `cell` (a kept point, not an average: averaging axial normals of either sign cancels them)."""
        idx = np.flatnonzero(np.isin(self.levels, list(levels)))
        if cell > 0 and len(idx):
            idx = idx[thin(self.points[idx], cell)]
        return self.pcd.select_by_index(idx)

    def fine_with_normals(self, max_nn: int) -> o3d.geometry.PointCloud:
        if not self.fine_pcd.has_normals():
            estimate_normals(self.fine_pcd, self.normal_radius, max_nn)
        return self.fine_pcd


def prepare_cloud(cloud: PointCloud, kind: str, levels: int, config: AlignConfig, seed: int = 0,
                  name: str = "cloud") -> PreparedCloud:
    import time

    t0 = time.perf_counter()
    if len(cloud) < MIN_POINTS:
        raise InputError(f"{name}: only {len(cloud)} points, at least {MIN_POINTS} needed to register")
    if levels < 1:
        raise InputError(f"{name}: levels must be >= 1, got {levels}")
    frame = Frame.around(cloud.xyz)
    full = to_pcd(frame.to_local(cloud.xyz))
    fine = full.voxel_down_sample(config.final_voxel)
    del full
    # delta0 grid from the delta grid: same cells to within a voxel, a fraction of the work on 8M points
    pcd = fine.voxel_down_sample(config.voxel)
    points = np.asarray(pcd.points)
    if len(points) < MIN_POINTS:
        raise InputError(f"{name}: only {len(points)} points after {config.voxel} m voxels, too few to register")
    t1 = time.perf_counter()
    radius = config.normal_radius
    if is_sparse(points, radius, config.sparse_min_neighbors):
        radius = max(radius, config.normal_radius_sparse)
    normals, features = normals_and_features(pcd, radius, config.normal_max_nn)
    t2 = time.perf_counter()
    lv = fit_levels(normals, features, levels, config.complexity, config.vmf, seed)
    t3 = time.perf_counter()
    return PreparedCloud(
        frame=frame, kind=kind, points=points, normals=normals, features=features, levels=lv.labels,
        level_stats=lv.stats, pcd=pcd, fine_pcd=fine, normal_radius=radius, input_points=len(cloud),
        seconds={"voxel": t1 - t0, "normals": t2 - t1, "levels": t3 - t2},
    )

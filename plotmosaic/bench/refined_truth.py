"""A truth for two real clips that share a frame only roughly: three fine registrations, their mean.

refine_truth(source, target, init=None, voxel=0.1) -> (4x4 source -> target, meta with the spread)
"""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from plotmosaic.io.frame import apply_transform, inverse, rotation_deg, translation


def _pcd(xyz: np.ndarray, voxel: float):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz)).voxel_down_sample(voxel)


def refine_truth(
    source: np.ndarray,
    target: np.ndarray,
    init: np.ndarray | None = None,
    voxel: float = 0.1,
    distances: tuple[float, ...] = (1.0, 0.3, 0.1),
) -> tuple[np.ndarray, dict]:
    """Mean of three independent fine registrations from `init` (source -> target) and their spread.

    Each runs the sparser cloud onto the denser one (a sparse target biases point-to-point ICP and is slow to
    query); point-to-point ICP, point-to-plane ICP (planes from the denser cloud) and generalised ICP.
    """
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    offset = np.floor(target.mean(axis=0))  # local frame: UTM keeps its millimetres in Open3D
    src, tgt = _pcd(source - offset, voxel), _pcd(target - offset, voxel)
    T0 = translation(-offset) @ (np.eye(4) if init is None else init) @ translation(offset)
    flip = len(src.points) > len(tgt.points)
    moving, fixed, start = (tgt, src, inverse(T0)) if flip else (src, tgt, T0)
    for pcd in (moving, fixed):
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    crit = reg.ICPConvergenceCriteria(max_iteration=60, relative_fitness=1e-8, relative_rmse=1e-8)
    runs = {
        "icp-point": lambda d, T: reg.registration_icp(
            moving, fixed, d, T, reg.TransformationEstimationPointToPoint(), crit
        ),
        "icp-plane": lambda d, T: reg.registration_icp(
            moving, fixed, d, T, reg.TransformationEstimationPointToPlane(), crit
        ),
        "gicp": lambda d, T: reg.registration_generalized_icp(
            moving, fixed, d, T, reg.TransformationEstimationForGeneralizedICP(), crit
        ),
    }
    results = {}
    for name, run in runs.items():
        T = start.copy()
        for d in distances:
            T = np.asarray(run(d, T).transformation)
        results[name] = inverse(T) if flip else T
    Ts = list(results.values())
    mean = np.eye(4)
    mean[:3, :3] = Rotation.from_matrix([t[:3, :3] for t in Ts]).mean().as_matrix()
    mean[:3, 3] = np.mean([t[:3, 3] for t in Ts], axis=0)
    centre = target.mean(axis=0) - offset
    spread_rot = max(rotation_deg(inverse(a) @ b) for a in Ts for b in Ts)
    spread_t = max(
        float(np.linalg.norm(apply_transform(a, centre) - apply_transform(b, centre)))
        for a in Ts
        for b in Ts
    )
    moved = float(np.linalg.norm(apply_transform(mean, centre) - apply_transform(T0, centre)))
    meta = {
        "methods": list(results),
        "direction": "target onto source" if flip else "source onto target",
        "spread_deg": spread_rot,
        "spread_m": spread_t,
        "from_init_deg": rotation_deg(inverse(T0) @ mean),
        "from_init_m": moved,
    }
    return translation(offset) @ mean @ translation(-offset), meta

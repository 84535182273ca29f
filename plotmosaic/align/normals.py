"""Normals and local eigen-features from one spherical neighbourhood per point (one KD-tree build).

Open3D's compiled code gathers each neighbourhood's covariance; numpy's batched eigh then gives
the plane normal (smallest eigenvector) and the eigenvalues l1 >= l2 >= l3 behind the features
linearity (l1-l2)/l1, planarity (l2-l3)/l1 and scattering l3/l1 (Weinmann et al. 2015).
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

FEATURE_NAMES = ("linearity", "planarity", "scattering")


def is_sparse(points: np.ndarray, radius: float, min_neighbors: int) -> bool:
    """Whether a typical point has fewer than `min_neighbors` within `radius` (cell counting, no tree).

    Cells of side 2r hold about twice a sphere of radius r, so half the per-point cell count
    estimates the neighbours; the median over points resists a few dense spots.
    """
    if len(points) == 0:
        return True
    keys = np.floor(points / (2.0 * radius)).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return float(np.median(counts[inverse.ravel()])) / 2.0 < min_neighbors


def normals_and_features(pcd: o3d.geometry.PointCloud, radius: float, max_nn: int, chunk: int = 1_000_000):
    """Set pcd.normals; return (normals (N,3), features (N,3)) from the covariance eigen-decomposition."""
    pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    cov = np.asarray(pcd.covariances)
    n = len(cov)
    normals = np.empty((n, 3))
    features = np.empty((n, 3))
    for s in range(0, n, chunk):
        vals, vecs = np.linalg.eigh(cov[s : s + chunk])  # ascending eigenvalues
        vals = np.clip(vals, 0.0, None)
        l1, l2, l3 = vals[:, 2], vals[:, 1], vals[:, 0]
        ok = l2 > 1e-10  # at least 3 non-collinear neighbours, else no plane
        inv = np.where(ok, 1.0 / np.where(ok, l1, 1.0), 0.0)
        # A point without a plane carries no shape: call it fully scattered (scattering = 1).
        features[s : s + chunk] = np.column_stack([(l1 - l2) * inv, (l2 - l3) * inv, np.where(ok, l3 * inv, 1.0)])
        nv = vecs[:, :, 0]
        nv[~ok] = (0.0, 0.0, 1.0)
        normals[s : s + chunk] = nv
    pcd.normals = o3d.utility.Vector3dVector(normals)
    pcd.covariances = o3d.utility.Matrix3dVector(np.empty((0, 3, 3)))  # free the memory
    return normals, features


def estimate_normals(pcd: o3d.geometry.PointCloud, radius: float, max_nn: int) -> None:
    """Normals only (target of the final ICP): Open3D's own eigen solver, multi-threaded."""
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))

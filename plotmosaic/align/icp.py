"""ICP stages (Open3D point-to-plane), quality figures and the information matrix."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from plotmosaic.align.config import IcpStage

reg = o3d.pipelines.registration


def run_icp(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, init: np.ndarray,
            stages: list[IcpStage], robust_kernel: float = 0.0, relative_fitness: float = 1e-6,
            relative_rmse: float = 1e-6):
    """Point-to-plane ICP through a coarse-to-fine list of correspondence distances.

    The Tukey kernel width follows the stage distance (never above `robust_kernel` once the
    distances are small) so far-off foliage correspondences do not drag the estimate.
    """
    T = np.asarray(init, dtype=np.float64)
    result = None
    for st in stages:
        kernel = reg.TukeyLoss(k=max(robust_kernel, st.max_distance / 2)) if robust_kernel > 0 else None
        est = reg.TransformationEstimationPointToPlane(kernel) if kernel else reg.TransformationEstimationPointToPlane()
        crit = reg.ICPConvergenceCriteria(relative_fitness=relative_fitness, relative_rmse=relative_rmse,
                                          max_iteration=st.iterations)
        result = reg.registration_icp(source, target, st.max_distance, T, est, crit)
        T = np.asarray(result.transformation)
    return T, result


def evaluate(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, T: np.ndarray, distance: float):
    """(fitness, inlier RMSE, correspondences) of source under T against target within `distance`."""
    r = reg.evaluate_registration(source, target, distance, T)
    return float(r.fitness), float(r.inlier_rmse), np.asarray(r.correspondence_set)


def point_to_plane_jacobian(p: np.ndarray, n: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rows d r_i / d xi for r_i = n_i.(T Exp(xi) p_i - q_i), xi = (w, v) (GTSAM Pose3 order)."""
    m = n @ R  # rows R^T n_i
    return np.hstack([np.cross(p, m), m])


def information_matrix(p: np.ndarray, q: np.ndarray, n: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, float]:
    """J^T J / sigma^2 for the point-to-plane problem, sigma^2 = inlier residual variance.

    p: source points, q and n: matched target points and normals, all in the coordinates T maps
    between (file coordinates for the stored result). Returns (information 6x6, sigma).
    """
    R, t = T[:3, :3], T[:3, 3]
    r = np.einsum("ij,ij->i", n, p @ R.T + t - q)
    sigma2 = float(np.mean(r**2)) if len(r) else float("nan")
    sigma2 = max(sigma2, 1e-8)
    J = point_to_plane_jacobian(p, n, R)
    return J.T @ J / sigma2, float(np.sqrt(sigma2))


def _exp_se3(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential, xi = (w, v)."""
    w, v = xi[:3], xi[3:]
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        R, V = np.eye(3) + K, np.eye(3)
    else:
        a, b, c = np.sin(th) / th, (1 - np.cos(th)) / th**2, (th - np.sin(th)) / th**3
        R = np.eye(3) + a * K + b * K @ K
        V = np.eye(3) + b * K + c * K @ K
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, V @ v
    return T


def guarded_icp(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray, init: np.ndarray,
                stages: list[IcpStage], tree=None, min_eig_ratio: float = 0.02, tol: float = 1e-7):
    """Point-to-plane ICP (Tukey-weighted Gauss-Newton) that moves only along well-constrained directions.

    A level such as ground alone constrains height, roll and pitch but hardly x, y and yaw; a plain
    solver lets noise and the uneven overlap slide it there (we saw tens of degrees of yaw on
    sloped ground). Each step is solved in the eigenbasis of the (scaled) normal matrix and
    directions whose eigenvalue is below `min_eig_ratio` x the largest are left for the next,
    richer level (degeneracy-aware ICP, Zhang et al. 2016). Returns (T, fitness, rmse, constrained dims).
    """
    from scipy.spatial import cKDTree

    tree = tree if tree is not None else cKDTree(target)
    T = np.asarray(init, dtype=np.float64).copy()
    centre = source.mean(axis=0)
    # work about the source centroid so rotation and translation are on comparable scales
    C = np.eye(4)
    C[:3, 3] = centre
    p0 = source - centre
    scale = max(np.sqrt((p0**2).sum(axis=1).mean()), 1e-3)
    fitness = rmse = 0.0
    rank = 6
    for st in stages:
        k = max(st.max_distance / 2, 0.05)
        for _ in range(st.iterations):
            moved = source @ T[:3, :3].T + T[:3, 3]
            d, j = tree.query(moved, distance_upper_bound=st.max_distance, workers=2)
            ok = np.isfinite(d)
            if ok.sum() < 12:
                return T, 0.0, float("nan"), 0
            n = target_normals[j[ok]]
            r = np.einsum("ij,ij->i", n, moved[ok] - target[j[ok]])
            wgt = np.where(np.abs(r) < k, (1 - (r / k) ** 2) ** 2, 0.0)  # Tukey
            # residual as a function of a left perturbation about the moved centroid
            c = T[:3, :3] @ centre + T[:3, 3]
            q = moved[ok] - c
            J = np.hstack([np.cross(q, n) / scale, n])
            H = (J * wgt[:, None]).T @ J
            g = (J * wgt[:, None]).T @ r
            vals, vecs = np.linalg.eigh(H)
            keep = vals > min_eig_ratio * vals[-1]
            rank = int(keep.sum())
            step = -(vecs[:, keep] @ ((vecs[:, keep].T @ g) / vals[keep]))
            step[:3] /= scale
            Tc = np.eye(4)
            Tc[:3, 3] = c
            T = Tc @ _exp_se3(step) @ np.linalg.inv(Tc) @ T
            fitness = float(ok.mean())
            rmse = float(np.sqrt(np.mean(d[ok] ** 2)))
            if np.linalg.norm(step[:3]) * scale + np.linalg.norm(step[3:]) < tol * scale:
                break
    return T, fitness, rmse, rank

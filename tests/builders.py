"""Synthetic scenes and pose graphs shared by several test modules (a test module never imports another)."""

import gtsam
import numpy as np

from plotmosaic.graph.posegraph import inverse
from plotmosaic.io.las import PointCloud

UTM = np.array([470250.0, 3810150.0, 2100.0])


def synthetic_plot(seed: int = 0, size: float = 30.0, trees: int = 20) -> PointCloud:
    """Undulating ground, stems and crowns at UTM coordinates: enough structure for ICP/RANSAC."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-size / 2, size / 2, (15000, 2))

    def ground(x, y):
        return 0.8 * np.sin(x / 5) + 0.5 * np.cos(y / 4) + 0.05 * x

    parts = [np.c_[xy, ground(xy[:, 0], xy[:, 1])]]
    for _ in range(trees):
        cx, cy = rng.uniform(-size / 2 + 2, size / 2 - 2, 2)
        r, h = rng.uniform(0.15, 0.4), rng.uniform(8, 15)
        a, z = rng.uniform(0, 2 * np.pi, 500), rng.uniform(0, h, 500)
        base = ground(cx, cy)
        parts.append(np.c_[cx + r * np.cos(a), cy + r * np.sin(a), base + z])
        crown = rng.normal(0, 1.5, (400, 3))
        parts.append(np.c_[cx + crown[:, 0], cy + crown[:, 1], base + h + 0.8 * crown[:, 2]])
    return PointCloud(np.vstack(parts) + UTM)


def split_pair(cloud: PointCloud, seed: int = 1) -> tuple[PointCloud, PointCloud]:
    """Two independent halves of one scene (different points, same surfaces), slightly noisy."""
    rng = np.random.default_rng(seed)
    idx = rng.permutation(len(cloud))
    src, tgt = cloud.select(idx[::2]), cloud.select(idx[1::2])
    return PointCloud(src.xyz + rng.normal(0, 0.005, src.xyz.shape)), tgt


def random_pose(rng, spread=15.0, tilt_deg=2.0):
    angles = np.radians([rng.normal(0, tilt_deg), rng.normal(0, tilt_deg), rng.uniform(-180, 180)])
    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Ypr(angles[2], angles[1], angles[0]).matrix()
    T[:3, 3] = [rng.uniform(-spread, spread), rng.uniform(-spread, spread), rng.normal(0, 0.3)]
    return T


def _icp_information(rng, n=400, sigma=0.003):
    """J^T J / sigma^2 from a random tree-like point set: a realistic, anisotropic 6x6 (right perturbation)."""
    pts = np.column_stack([rng.uniform(-15, 15, n), rng.uniform(-15, 15, n), rng.uniform(0, 12, n)])
    normals = rng.normal(size=(n, 3))
    normals[:, 2] *= 0.3  # mostly vertical stems: horizontal normals
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    J = np.column_stack([np.cross(pts, normals), normals])  # d(n . (R p + t)) / (w, v)
    return J.T @ J / sigma**2


def synthetic_pose_graph(n_scans=5, seed=0, rot_noise_deg=0.002, trans_noise=0.0005, outlier=None):
    """(truth, nodes, edges) of a plot whose every pair is an edge with small noise; `outlier`
    (source, target) names one edge turned 10 deg and 2 m wrong."""
    rng = np.random.default_rng(seed)
    truth = {f"s{k}": random_pose(rng) for k in range(n_scans)}
    ref = "s0"
    truth = {k: inverse(truth[ref]) @ T for k, T in truth.items()}  # plot frame = reference scan
    edges = []
    for a in range(n_scans):
        for b in range(a + 1, n_scans):
            i, j = f"s{b}", f"s{a}"  # source, target
            T = inverse(truth[j]) @ truth[i]
            xi = np.concatenate(
                [np.radians(rng.normal(0, rot_noise_deg, 3)), rng.normal(0, trans_noise, 3)]
            )
            T = T @ gtsam.Pose3.Expmap(xi).matrix()
            edges.append(
                {
                    "source": i,
                    "target": j,
                    "transform": T,
                    "fitness": 0.8,
                    "inlier_rmse": 0.01,
                    "overlap": 0.6,
                    "information": _icp_information(rng),
                }
            )
    if outlier is not None:
        e = next(e for e in edges if (e["source"], e["target"]) == outlier)
        e["transform"] = (
            e["transform"]
            @ gtsam.Pose3(gtsam.Rot3.Rz(np.radians(10)), np.array([2.0, 0.5, 0.0])).matrix()
        )
    nodes = {name: {"kind": "tls", "plot": "P1"} for name in truth}
    return truth, nodes, edges

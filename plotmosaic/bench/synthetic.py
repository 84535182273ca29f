"""Synthetic pose graphs with exact truth: scans on a grid, edges between neighbours, some edges wrong.

For the scaling test and benchmark of the pose graph (issue 16): the measurements are what
register-plot would produce (small noise, an anisotropic ICP-like information), the wrong edges
what a coarse stage that locked onto the wrong trees would (metres and degrees off).
"""

from __future__ import annotations

import gtsam
import numpy as np

from plotmosaic.io.frame import inverse


def _pose(rng: np.random.Generator, x: float, y: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = gtsam.Rot3.Ypr(
        rng.uniform(-np.pi, np.pi), np.radians(rng.normal(0, 1)), np.radians(rng.normal(0, 1))
    ).matrix()
    T[:3, 3] = [x + rng.normal(0, 1), y + rng.normal(0, 1), rng.normal(0, 0.3)]
    return T


def _information(rng: np.random.Generator, n: int = 200, sigma: float = 0.003) -> np.ndarray:
    """J^T J / sigma^2 of a random stem-like point set: anisotropic, as from point-to-plane ICP."""
    pts = np.column_stack([rng.uniform(-15, 15, n), rng.uniform(-15, 15, n), rng.uniform(0, 12, n)])
    normals = rng.normal(size=(n, 3))
    normals[:, 2] *= 0.3
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    J = np.column_stack([np.cross(pts, normals), normals])
    return J.T @ J / sigma**2


def grid_graph(
    n_scans: int,
    wrong_share: float = 0.05,
    spacing: float = 15.0,
    seed: int = 0,
    rot_noise_deg: float = 0.002,
    trans_noise: float = 0.0005,
):
    """(truth poses, nodes, edges, wrong edge ids): scans on a near-square grid, edges to the 8 grid neighbours.

    Truth is in the frame of scan "s0000" (the reference). Wrong edges are off by 3-20 deg and 1-5 m.
    """
    rng = np.random.default_rng(seed)
    cols = int(np.ceil(np.sqrt(n_scans)))
    cells = [(k % cols, k // cols) for k in range(n_scans)]
    names = [f"s{k:04d}" for k in range(n_scans)]
    truth = {n: _pose(rng, i * spacing, j * spacing) for n, (i, j) in zip(names, cells)}
    ref = inverse(truth[names[0]])
    truth = {n: ref @ T for n, T in truth.items()}
    index = {c: n for n, c in zip(names, cells)}
    pairs = []
    for n, (i, j) in zip(names, cells):
        for di, dj in ((1, 0), (0, 1), (1, 1), (1, -1)):
            m = index.get((i + di, j + dj))
            if m is not None:
                pairs.append((m, n) if m > n else (n, m))
    n_wrong = int(round(wrong_share * len(pairs)))
    wrong = {pairs[k] for k in rng.choice(len(pairs), n_wrong, replace=False)}
    edges = []
    for source, target in pairs:
        T = inverse(truth[target]) @ truth[source]
        xi = np.concatenate(
            [np.radians(rng.normal(0, rot_noise_deg, 3)), rng.normal(0, trans_noise, 3)]
        )
        T = T @ gtsam.Pose3.Expmap(xi).matrix()
        if (source, target) in wrong:
            axis = rng.normal(size=3) * [0.1, 0.1, 1.0]
            angle = np.radians(rng.uniform(3, 20)) * axis / np.linalg.norm(axis)
            shift = rng.normal(size=3) * [1, 1, 0.2]
            shift *= rng.uniform(1, 5) / np.linalg.norm(shift)
            T = T @ gtsam.Pose3.Expmap(np.concatenate([angle, shift])).matrix()
        edges.append(
            {
                "source": source,
                "target": target,
                "transform": T,
                "fitness": 0.8,
                "inlier_rmse": 0.01,
                "overlap": 0.6,
                "confidence": 0.9,
                "information": _information(rng),
            }
        )
    nodes = {n: {"kind": "tls", "plot": "P1"} for n in names}
    return truth, nodes, edges, sorted(wrong)


def stem_map_grid(
    side: int,
    seed: int = 0,
    spacing: float = 18.0,
    seen: float = 20.0,
    density: float = 0.03,
    occluded: float = 0.2,
    noise: float = 0.05,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """(scan positions, per-scan stem maps) of `side` x `side` scans in one random forest.

    Each scan sees the stems within `seen` m (`density` stems per m2; 0.03 = 300 / ha) less an
    `occluded` share, with `noise` m of centre error, in its own rotated and shifted frame: what
    the stem-map signature of a scan without position gets (graph/signature.py)."""
    rng = np.random.default_rng(seed)
    extent = (side - 1) * spacing + 2 * seen
    forest = rng.uniform(-seen, extent - seen, size=(int(extent**2 * density), 2))
    positions = np.array([(i * spacing, j * spacing) for j in range(side) for i in range(side)])
    maps = []
    for p in positions:
        xy = forest[np.linalg.norm(forest - p, axis=1) < seen]
        xy = xy[rng.random(len(xy)) > occluded] - p
        xy = xy + rng.normal(0, noise, xy.shape)
        a = rng.uniform(0, 2 * np.pi)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        maps.append(xy @ R.T + rng.uniform(-50, 50, 2))
    return positions, maps

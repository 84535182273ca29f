"""Line of sight through a point cloud (simulate/from_cloud.py): a dense occupancy grid of the cloud,
rays marched through it from a scanner, and the local surface normals that set how close to its
own point a ray may pass occupied voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.config.cuts import CutConfig


def surface_normals(tree: cKDTree, local: np.ndarray, query: np.ndarray, k: int) -> np.ndarray:
    """Unit normals (smallest principal axis of the k nearest cloud points) at `query`, chunked."""
    out = np.empty((len(query), 3))
    k = min(k, len(local))
    for start in range(0, len(query), 100_000):
        q = query[start : start + 100_000]
        _, idx = tree.query(q, k=k)
        nb = local[idx] - local[idx].mean(axis=1, keepdims=True)
        cov = np.einsum("mki,mkj->mij", nb, nb)
        _, vec = np.linalg.eigh(cov)
        out[start : start + 100_000] = vec[:, :, 0]
    return out


@dataclass(frozen=True)
class OccupancyGrid:
    occupied: np.ndarray  # flat bool
    origin: np.ndarray
    shape: tuple[int, int, int]
    voxel: float


def occupancy_grid(
    local: np.ndarray, lo: np.ndarray, hi: np.ndarray, cfg: CutConfig
) -> OccupancyGrid:
    """Dense occupancy of the cloud inside [lo, hi]; the voxel grows until the grid fits `max_grid_cells`."""
    voxel = cfg.voxel
    span = np.maximum(hi - lo, voxel)
    while np.prod(np.ceil(span / voxel) + 1) > cfg.max_grid_cells:
        voxel *= 1.25
    shape = tuple(int(v) for v in np.ceil(span / voxel) + 1)
    inside = np.all((local >= lo) & (local <= hi), axis=1)
    ijk = np.floor((local[inside] - lo) / voxel).astype(np.int64)
    occupied = np.zeros(int(np.prod(shape)), dtype=bool)
    occupied[(ijk[:, 0] * shape[1] + ijk[:, 1]) * shape[2] + ijk[:, 2]] = True
    return OccupancyGrid(occupied, lo, shape, voxel)


def visible(
    grid: OccupancyGrid, scanner: np.ndarray, pts: np.ndarray, tol: np.ndarray, cfg: CutConfig
) -> np.ndarray:
    """True where the ray scanner -> point crosses no occupied voxel between min_range and r - tol."""
    d = pts - scanner
    r = np.linalg.norm(d, axis=1)
    u = d / np.maximum(r, 1e-9)[:, None]
    stop = r - tol  # march up to here
    seen = np.ones(len(pts), dtype=bool)
    step = grid.voxel / 2.0
    order = np.argsort(stop)  # similar ray lengths in one chunk: little padding

    def steps(length: float) -> int:
        return max(1, int(np.ceil((length - cfg.min_range) / step)))

    shape = np.array(grid.shape)
    start = 0
    while start < len(order):
        sel = order[start : start + max(1, cfg.chunk_samples // steps(stop[order[start]]))]
        while len(sel) > 1 and len(sel) * steps(stop[sel[-1]]) > cfg.chunk_samples:
            sel = sel[: len(sel) // 2]
        start += len(sel)
        if stop[sel[-1]] <= cfg.min_range:
            continue  # these rays end inside the free zone around the scanner: nothing can block them
        n_steps = steps(stop[sel[-1]])
        t = (cfg.min_range + step * np.arange(n_steps)).astype(np.float32)
        p = (scanner - grid.origin).astype(np.float32) + u[sel, None, :].astype(np.float32) * t[
            None, :, None
        ]
        ijk = np.floor(p / np.float32(grid.voxel)).astype(np.int32)
        ok = np.all((ijk >= 0) & (ijk < shape), axis=2) & (t[None, :] < stop[sel, None])
        flat = (ijk[..., 0].astype(np.int64) * shape[1] + ijk[..., 1]) * shape[2] + ijk[..., 2]
        hit = np.zeros(ok.shape, dtype=bool)
        hit[ok] = grid.occupied[flat[ok]]
        seen[sel] = ~hit.any(axis=1)
    return seen

"""Voxel grids in numpy, returned in a spatially sorted order.

One integer key per cube and one sort replace Open3D's hash map (4-6x slower on 8M points here).
The sort also puts neighbouring cubes next to each other in memory, which makes every later
KD-tree query several times faster than on hash-ordered points.
"""

from __future__ import annotations

import numpy as np

from plotmosaic.errors import InputError


def cube_keys(points: np.ndarray, size: float) -> np.ndarray:
    """One int64 per point naming its cube of side `size` (lexicographic in x, y, z)."""
    points = np.asarray(points, dtype=np.float64)
    cols, dims = [], []
    for i in range(3):  # column by column: axis-0 reductions over (N, 3) are ~5x slower
        c = np.floor(points[:, i] * (1.0 / size))
        c -= c.min()
        cols.append(c)
        dims.append(c.max() + 1.0)
    if float(np.prod(dims)) >= 2.0**53:  # beyond exact float64 integers (a continent at 1 cm)
        raise InputError(f"cloud extent {np.ptp(points, axis=0).round(0)} m is too large for {size} m voxels")
    cols[0] *= dims[1]
    cols[0] += cols[1]
    cols[0] *= dims[2]
    cols[0] += cols[2]
    return cols[0].astype(np.int64)


def _groups(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order that sorts the keys, start of each run of equal keys in that order)."""
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    starts = np.flatnonzero(np.concatenate(([True], sorted_keys[1:] != sorted_keys[:-1])))
    return order, starts


def voxel_centroids(points: np.ndarray, size: float) -> np.ndarray:
    """The centroid of each occupied cube of side `size`, in cube-key order."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return points.reshape(0, 3)
    order, starts = _groups(cube_keys(points, size))
    counts = np.diff(np.append(starts, len(order)))
    out = np.empty((len(starts), 3))
    for i in range(3):
        out[:, i] = np.add.reduceat(points[:, i][order], starts) / counts
    return out


def thin(points: np.ndarray, cell: float) -> np.ndarray:
    """Indices of one point per occupied cube of side `cell` (the first one in input order), sorted.

    A kept point, not an average: averaging axial normals of either sign would cancel them.
    """
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    order, starts = _groups(cube_keys(points, cell))
    return np.sort(order[starts])

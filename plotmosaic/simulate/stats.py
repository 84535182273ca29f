"""Figures about simulated scans: overlap between scans, ALS density."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.io.las import read_cloud


def overlap_fraction(a: np.ndarray, b: np.ndarray, radius: float = 0.05) -> float:
    """Fraction of the points of `a` within `radius` of some point of `b` (same frame, float64)."""
    if len(a) == 0 or len(b) == 0:
        return 0.0
    # query near the origin: UTM-sized coordinates lose precision in the tree
    offset = a.min(axis=0)
    d, _ = cKDTree(b - offset).query(a - offset, distance_upper_bound=radius, workers=2)
    return float(np.isfinite(d).mean())


def scan_in_world(path, transform: np.ndarray) -> np.ndarray:
    """A scan's points mapped by its pose (float64, the pose's frame)."""
    xyz = read_cloud(path, attributes=False).xyz
    T = np.asarray(transform, dtype=np.float64)
    # = apply_transform, faster on millions of points
    return np.einsum("ij,kj->ik", xyz, T[:3, :3]) + T[:3, 3]


def density(xy: np.ndarray, extent: tuple[float, float, float, float]) -> float:
    """Points per m2 inside extent (xmin, ymin, xmax, ymax)."""
    inside = (
        (xy[:, 0] >= extent[0])
        & (xy[:, 0] < extent[2])
        & (xy[:, 1] >= extent[1])
        & (xy[:, 1] < extent[3])
    )
    return float(inside.sum() / ((extent[2] - extent[0]) * (extent[3] - extent[1])))

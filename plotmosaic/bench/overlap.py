"""Crop an aligned pair down to a chosen overlap, like the paper's Table 1 (28/15/5/1 %).

Overlap is the paper's figure: the share of source points that have a target point within
25 cm when the pair is aligned. Real low-overlap pairs are scans that see different parts
of the plot, so the crop is spatial, not a thinning: whole columns of the source are removed
where it shares most with the target (see `crop_to_overlap`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.errors import InputError
from plotmosaic.io.las import PointCloud

OVERLAP_DISTANCE = 0.25  # metres, the paper's definition


def overlap_fraction(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    distance: float = OVERLAP_DISTANCE,
    tree: cKDTree | None = None,
) -> float:
    """Share of source points with a target point within `distance` (both in one frame)."""
    if len(source_xyz) == 0 or len(target_xyz) == 0:
        return 0.0
    tree = tree or cKDTree(target_xyz)
    d, _ = tree.query(source_xyz, k=1, distance_upper_bound=distance)
    return float(np.mean(np.isfinite(d)))


@dataclass(frozen=True)
class Cropped:
    source: PointCloud
    target: PointCloud
    overlap: float  # achieved overlap, 0..1
    wanted: float


def crop_to_overlap(
    source: PointCloud, target: PointCloud, wanted: float, cell: float = 4.0
) -> Cropped:
    """Crop the source of an ALIGNED pair (source in target coordinates) to about `wanted` overlap (0..1).

    The source is cut into `cell`-metre columns (x, y); columns are removed in order of how much
    of them the target also sees, most shared first, until the overlap is closest to `wanted`.
    The source then lacks parts of the shared area, as a scan behind a ridge or a thicket does.
    The target is kept whole. An overlap above the pair's own is not reachable: it stays as is.
    """
    if not 0.0 < wanted < 1.0:
        raise InputError(f"--overlap: {wanted * 100:g}% is not between 0 and 100")
    d, _ = cKDTree(target.xyz).query(source.xyz, k=1, distance_upper_bound=OVERLAP_DISTANCE)
    hit = np.isfinite(d)
    ij = np.floor(source.xyz[:, :2] / cell).astype(np.int64)
    _, col, counts = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    col = col.ravel()
    hits = np.bincount(col, weights=hit, minlength=len(counts))
    order = np.lexsort((np.arange(len(counts)), -hits / counts))  # most shared first, ties by index
    # overlap after removing the first j columns, j = 0..n-1 (always keep at least one)
    kept_pts = counts.sum() - np.concatenate([[0], np.cumsum(counts[order])[:-1]])
    kept_hits = hits.sum() - np.concatenate([[0], np.cumsum(hits[order])[:-1]])
    frac = kept_hits / kept_pts
    min_points = max(1000, len(source) // 20)  # never leave a source too small to register
    usable = kept_pts >= min(min_points, len(source))
    miss = np.where(usable, np.abs(frac - wanted), np.inf)
    j = int(np.argmin(miss))  # the fewest columns removed among equally close cuts
    keep = ~np.isin(col, order[:j])
    return Cropped(source.select(keep), target, float(frac[j]), wanted)

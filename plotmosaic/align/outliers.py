"""Stray points: the few returns far from the rest of a cloud (multipath, sky hits, a NaN written as
x = -2,147,483 m by laspy) that would stretch every extent, raster and voxel grid built from it.

Per axis, the bulk of the cloud (a central quantile range of a strided sample, widened by a margin)
is kept as it is; points outside it stay while they chain back to the bulk without an empty gap
wider than `max_gap`; whatever lies beyond such a gap is dropped when it holds at most
`detached_max_fraction` of the points (a large detached part is real data: kept, and what lies
beyond a further gap past it is judged the same way). Linear time
(one pass per axis, a sort of the few points outside the bulk), memory a few arrays of N.
"""

from __future__ import annotations

import numpy as np

from plotmosaic.config.align import StrayConfig


def _axis_strays(
    v: np.ndarray, keep: np.ndarray, config: StrayConfig, lo_hi: tuple[float, float] | None = None
) -> None:
    """Clear `keep` for the detached tails of one coordinate column (a strided view: no copy of N);
    `lo_hi`: the column's (min, max) when already known."""
    step = max(1, len(v) // config.sample_points)
    sample = v[::step][keep[::step]]
    lo, hi = np.quantile(sample, [config.core_quantile, 1.0 - config.core_quantile])
    margin = max(config.core_margin * (hi - lo), config.min_margin_m)
    vmin, vmax = lo_hi if lo_hi is not None else (v.min(), v.max())
    for sign, edge in ((1.0, hi + margin), (-1.0, lo - margin)):
        if (vmax <= edge) if sign > 0 else (vmin >= edge):
            continue  # the usual case: nothing beyond the bulk's margin, one cheap pass
        outside = np.flatnonzero((v > edge if sign > 0 else v < edge) & keep)
        if len(outside) == 0:
            continue
        # distance beyond the bulk's edge, sorted outward; a gap wider than max_gap detaches what lies beyond
        d = sign * (v[outside] - edge)
        ds = np.sort(d)
        gaps = np.flatnonzero(np.diff(ds, prepend=0.0) > config.max_gap_m)
        # the innermost gap beyond which few enough points lie: a real far part may sit between
        small = gaps[len(ds) - gaps <= config.detached_max_fraction * int(keep.sum())]
        if len(small):
            keep[outside[d >= ds[int(small[0])]]] = False


def stray_mask(
    xyz: np.ndarray, config: StrayConfig | None = None, bounds: np.ndarray | None = None
) -> np.ndarray:
    """Boolean mask of the points to keep (all True when nothing is detached); `bounds`: the
    columns' (min, max) as a (3, 2) array when already known (checked once per axis, not recomputed)."""
    config = config or StrayConfig()
    keep = np.ones(len(xyz), dtype=bool)
    if not config.enabled or len(xyz) < 2:
        return keep
    for i in range(3):
        _axis_strays(xyz[:, i], keep, config, None if bounds is None else tuple(bounds[i]))
    return keep

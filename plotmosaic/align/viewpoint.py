"""Where a single-station scan was taken from, when its file says so.

A terrestrial scan exported in its own scanner frame has the scanner at the file origin. Knowing it
lets the final ICP tell the two sides of a thin stem or branch apart: a point one scanner saw on
the far side of a surface cannot belong to the side the other scanner saw (align/icp.facing). The
origin is trusted only where the cloud crowds around it as one scan's 1/r^2 density does; a merged
cloud, a cut of one, or a scan in a project frame has no such peak and gets no viewpoint.
"""

from __future__ import annotations

import numpy as np

from plotmosaic.align.sampling import sample
from plotmosaic.config.align import ViewpointConfig


def crowding(xyz: np.ndarray, config: ViewpointConfig, rng: np.random.Generator) -> float:
    """Mean points per occupied `cell` within `radius` (horizontally) of the file origin, over the
    mean of all occupied cells, on a seeded sample; 0 when nothing lies that close."""
    xy = xyz[sample(len(xyz), config.probe_points, rng), :2]
    ij = np.floor(xy / config.cell).astype(np.int64)
    # one integer per cell: a 1-D unique, many times faster than unique rows (the counts are
    # integers, so the means below do not depend on the cells' order)
    lo = ij.min(axis=0)
    rows = int(ij[:, 1].max() - lo[1]) + 1
    keys, counts = np.unique((ij[:, 0] - lo[0]) * rows + (ij[:, 1] - lo[1]), return_counts=True)
    cells = np.column_stack([keys // rows + lo[0], keys % rows + lo[1]])
    centres = (cells + 0.5) * config.cell
    near = np.hypot(centres[:, 0], centres[:, 1]) <= config.radius
    return float(counts[near].mean() / counts.mean()) if near.any() else 0.0


def scanner_viewpoint(
    xyz: np.ndarray, kind: str, config: ViewpointConfig, rng: np.random.Generator
) -> np.ndarray | None:
    """The scanner in file coordinates (the origin) when `xyz` is one scan of a viewpoint kind
    crowding around it, else None."""
    if kind not in config.kinds or len(xyz) == 0:
        return None
    return np.zeros(3) if crowding(xyz, config, rng) >= config.min_crowding else None

"""Candidate pairs within a plot: every pair whose footprints can overlap.

With approximate positions for all scans of a plot (in one frame) a pair is kept when the scanners
stood at most `max_distance` apart; without them every pair in the plot is tried.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from plotmosaic.manifest import Plot, Scan


def candidate_pairs(plot: Plot, max_distance: float | None = None) -> list[tuple[Scan, Scan]]:
    """(source, target) pairs; the later scan in the manifest is the source."""
    scans = plot.scans
    frames = {s.approx_position_frame for s in scans}
    known = all(s.approx_position is not None for s in scans) and len(frames) == 1
    pairs = []
    for target, source in combinations(scans, 2):
        if known and max_distance is not None:
            d = np.linalg.norm(np.subtract(source.approx_position, target.approx_position)[:2])
            if d > max_distance:
                continue
        pairs.append((source, target))
    return pairs

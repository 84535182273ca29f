"""Distinct correlation peaks: what the raster search and the slice search both hand on as hypotheses."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True, kw_only=True, eq=False)
class Peak:
    """A correlation peak: the levelled source turned by `yaw` about `centre`, then shifted by
    `t_xy` (the searches' convention), found on cells of `cell` metres."""

    score: float
    yaw: float
    t_xy: np.ndarray
    overlap: float  # share of the source the shift puts over the target
    centre: np.ndarray | None = None  # set with `cell` when the peak is kept (distinct_peaks)
    cell: float | None = None
    fine: bool = False  # from the raster search's finer cells (a narrow scene)


def angle_diff(a: float, b: float) -> float:
    """|a - b| in radians, wrapped to [0, pi]."""
    return abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def distinct_peaks(
    candidates: list[Peak],
    yaw_deg: float,
    shift_m: float,
    most: int,
    *,
    centre: np.ndarray,
    cell: float,
) -> list[Peak]:
    """The best `most` of `candidates` (sorted best first), each one more than `yaw_deg` or `shift_m`
    from every one kept before it (near copies of one peak are one pose), with the search's `centre`
    and `cell`."""
    chosen: list[Peak] = []
    for c in candidates:
        if all(
            angle_diff(c.yaw, o.yaw) > np.radians(yaw_deg)
            or np.linalg.norm(c.t_xy - o.t_xy) > shift_m
            for o in chosen
        ):
            chosen.append(replace(c, centre=centre, cell=cell))
        if len(chosen) >= most:
            break
    return chosen

"""Distinct correlation peaks: what the raster search and the slice search both hand on as hypotheses."""

from __future__ import annotations

import numpy as np


def angle_diff(a: float, b: float) -> float:
    """|a - b| in radians, wrapped to [0, pi]."""
    return abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def distinct_peaks(
    candidates: list[dict], yaw_deg: float, shift_m: float, most: int, **extra
) -> list[dict]:
    """The best `most` of `candidates` (sorted best first; each with 'yaw' and 't_xy'), each one more
    than `yaw_deg` or `shift_m` from every one kept before it: near copies of one peak are one pose."""
    chosen: list[dict] = []
    for c in candidates:
        if all(
            angle_diff(c["yaw"], o["yaw"]) > np.radians(yaw_deg)
            or np.linalg.norm(c["t_xy"] - o["t_xy"]) > shift_m
            for o in chosen
        ):
            chosen.append({**c, **extra})
        if len(chosen) >= most:
            break
    return chosen

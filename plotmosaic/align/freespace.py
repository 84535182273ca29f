"""Free space: what a scanner saw through. A single-station scan with a known scanner (align/
viewpoint.py) records, in every direction, the nearest surface its beams hit; the space in front of
it is empty. A pose that puts many of the other cloud's points there is ruled out by the scene
itself, however many of its points find partners: at thin overlap a wrong pose overlaps more of
the two clouds by chance than the right one, and it does so by pushing stems into the gaps the
other scanner looked through.

`Scanner` is one cloud's nearest-return image; `seen_through` the share of points a scanner could
see (its image has a return in their direction) lying in front of that return by more than a margin,
both ways where both scanners are known. Every transform maps source-local to target-local.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.align.memo import CloudMemo, PairMemo
from plotmosaic.config.freespace import FreeSpaceConfig


@dataclass(frozen=True, eq=False)
class Scanner:
    """One scan's nearest return per direction, cells of `step` radians in azimuth and elevation."""

    position: np.ndarray  # (3,) local coordinates
    step: float
    rows: int  # elevation cells
    nearest: np.ndarray  # (columns * rows,) range of the nearest return, inf where none


def _cells(d: np.ndarray, step: float, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """(range, flat cell index) of offsets `d` from a scanner."""
    r = np.linalg.norm(d, axis=1)
    az = np.arctan2(d[:, 1], d[:, 0]) + np.pi
    el = np.arcsin(np.clip(d[:, 2] / np.maximum(r, 1e-9), -1.0, 1.0)) + np.pi / 2
    return r, (az / step).astype(np.int64) * rows + (el / step).astype(np.int64)


def scanner(points: np.ndarray, position: np.ndarray, config: FreeSpaceConfig) -> Scanner:
    """The nearest-return image of a scan's `points` seen from `position` (both local)."""
    step = float(np.radians(config.resolution_deg))
    rows = int(np.pi / step) + 2
    columns = int(2 * np.pi / step) + 2
    nearest = np.full(columns * rows, np.inf)
    r, cell = _cells(points - position, step, rows)
    np.minimum.at(nearest, cell, r)
    return Scanner(
        position=np.asarray(position, dtype=float), step=step, rows=rows, nearest=nearest
    )


def _through(s: Scanner, points: np.ndarray, margin: float) -> tuple[int, int]:
    """(points lying where `s` saw through, points `s` could see) of `points` in its coordinates."""
    if len(points) == 0:
        return 0, 0
    r, cell = _cells(points - s.position, s.step, s.rows)
    near = s.nearest[cell]
    seen = np.isfinite(near)
    return int((seen & (r < near - margin)).sum()), int(seen.sum())


def seen_through(
    src_points: np.ndarray,
    tgt_points: np.ndarray,
    T: np.ndarray,
    src: Scanner | None,
    tgt: Scanner | None,
    margin: float,
    config: FreeSpaceConfig,
) -> float | None:
    """Share of the points either scanner could see that pose T puts where it saw through: source
    points in the target scanner's image, target points in the source scanner's; None when no
    scanner is known or too few points could be seen to tell."""
    through = seen = 0
    if tgt is not None:
        a, b = _through(tgt, src_points @ T[:3, :3].T + T[:3, 3], margin)
        through, seen = through + a, seen + b
    if src is not None:
        R, t = T[:3, :3], T[:3, 3]
        a, b = _through(src, (tgt_points - t) @ R, margin)  # target points in source coordinates
        through, seen = through + a, seen + b
    if seen < config.min_seen:
        return None
    return through / seen


def _scanner_of(cloud, config: FreeSpaceConfig, memo: CloudMemo) -> Scanner | None:
    if getattr(cloud, "viewpoint", None) is None:
        return None
    return memo.scanner.get(
        (config.resolution_deg,), lambda: scanner(cloud.points, cloud.viewpoint, config)
    )


@dataclass(frozen=True, eq=False)
class FreeSpace:
    """A pair's scanners, where known, and the test every pose of the pair is put to."""

    source: Scanner | None
    target: Scanner | None
    config: FreeSpaceConfig

    @classmethod
    def of_pair(cls, src, tgt, config: FreeSpaceConfig, memo: PairMemo) -> FreeSpace | None:
        """The pair's free space (None: switched off, or neither scanner known)."""
        if not config.enabled:
            return None
        a, b = _scanner_of(src, config, memo.source), _scanner_of(tgt, config, memo.target)
        return None if a is None and b is None else cls(source=a, target=b, config=config)

    def share(
        self, src_points: np.ndarray, tgt_points: np.ndarray, T: np.ndarray, screening: bool = False
    ) -> float | None:
        """`seen_through` at pose T, with the margin of a refined pose or of a screened start."""
        c = self.config
        margin = c.screen_margin_m if screening else c.margin_m
        return seen_through(src_points, tgt_points, T, self.source, self.target, margin, c)

    def beyond(self, share: float | None, screening: bool = False) -> bool:
        """Whether a seen-through `share` is more than a pose can have."""
        limit = self.config.screen_max_share if screening else self.config.max_share
        return share is not None and share > limit

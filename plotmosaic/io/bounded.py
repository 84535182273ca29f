"""Reading a scan for registration within a memory budget (`[read] max_points_in_memory`).

A scan of at most that many points is read whole (`io.las.read_cloud`). A bigger one streams in
chunk by chunk and keeps the first point, in file order, of each occupied cell of a grid far finer
than registration's, so its whole float64 cloud is never held. When the kept points would pass the
budget the cell doubles: the grids are nested, so each coarser cell still keeps the first of all its
points, as one pass at the coarser cell alone would.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.config.align import AlignConfig
from plotmosaic.config.merge import CHUNK_SIZE
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.errors import InputError
from plotmosaic.io import cells
from plotmosaic.io.cloud import PointCloud
from plotmosaic.io.las import file_format, iter_chunks, read_cloud, read_header_info


@dataclass(frozen=True, kw_only=True)
class Thinned:
    """A scan thinned on reading: the kept points and how."""

    cloud: PointCloud
    points_read: int
    origin: np.ndarray  # a corner of the grid's cells (inside the scan)
    first_cell: float  # m
    cell: float  # m, the final cell (first_cell doubled as often as the budget needed)


def over_budget(path: str | Path, reading: ReadingConfig) -> bool:
    """Whether reading the scan for registration thins it (its header counts more points than the budget)."""
    return read_header_info(path).point_count > reading.max_points_in_memory


def read_bounded(path: str | Path, reading: ReadingConfig, finest_voxel: float) -> PointCloud:
    """The scan's coordinates for registration: whole when within the budget, else thinned on
    reading to one point per cell of `reading.thinning_cell(finest_voxel)` or coarser (one line
    says so on stderr)."""
    if not over_budget(path, reading):
        return read_cloud(path, attributes=False)
    budget = reading.max_points_in_memory
    thinned = read_thinned(path, budget, reading.thinning_cell(finest_voxel))
    coarser = (
        f" (coarsened from {thinned.first_cell * 100:g} cm to stay within the budget)"
        if thinned.cell > thinned.first_cell
        else ""
    )
    print(
        f"note: {path}: {thinned.points_read:,} points, more than read.max_points_in_memory "
        f"({budget:,}): thinned on reading to {len(thinned.cloud):,} points, one per "
        f"{thinned.cell * 100:g} cm cell{coarser}",
        file=sys.stderr,
    )
    return thinned.cloud


def read_thinned(path: str | Path, max_points: int, cell: float) -> Thinned:
    """The first point (file order) of each occupied `cell` cube, streamed so that at most
    `max_points` float64 points (kept + one chunk) are held; the cell doubles when they would not fit."""
    path = Path(path)
    count = read_header_info(path).point_count
    chunk_size = max(1, min(CHUNK_SIZE, max_points // 8))
    kept = _FirstPerCell(cell, max_points - chunk_size, chunk_size)
    read = bad = 0
    crs = None
    for chunk in iter_chunks(path, chunk_size, attributes=False):
        read += len(chunk)
        crs = chunk.crs
        if not np.isfinite(chunk.xyz).all():  # the flat check is far cheaper than counting rows
            bad += int((~np.isfinite(chunk.xyz).all(axis=1)).sum())
        if not bad:  # else the scan is refused below, once every bad point is counted
            kept.add(chunk.xyz)
    if file_format(path) == "las" and read != count:  # E57 / PLY drop their invalid points
        raise InputError(f"{path}: truncated or overlong, read {read} of {count} points")
    if bad:
        raise InputError(f"{path}: {bad} points have NaN or infinite coordinates")
    if kept.n == 0:
        raise InputError(f"{path}: contains no valid points")
    return Thinned(
        cloud=PointCloud(kept.rows[: kept.n], {}, crs),
        points_read=read,
        origin=kept.origin,
        first_cell=cell,
        cell=kept.cell,
    )


def _first_of_each(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the distinct keys sorted, the index of each one's first occurrence), from an unstable sort
    and the least index of each run of equal keys: a few times faster than a stable sort (np.unique's
    return_index)."""
    order = np.argsort(keys)
    keys = keys[order]
    new = np.ones(len(keys), dtype=bool)
    np.not_equal(keys[1:], keys[:-1], out=new[1:])
    starts = np.flatnonzero(new)
    first = np.minimum.reduceat(order, starts) if len(starts) else starts
    return keys[starts], first


def _merged(sorted_keys: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Two sorted arrays of distinct keys as one (np.insert would sort the positions again)."""
    out = np.empty(len(sorted_keys) + len(new), dtype=np.int64)
    at = np.searchsorted(sorted_keys, new) + np.arange(len(new))
    old = np.ones(len(out), dtype=bool)
    old[at] = False
    out[at] = new
    out[old] = sorted_keys
    return out


def _member(keys: np.ndarray, sorted_keys: np.ndarray) -> np.ndarray:
    if not len(sorted_keys):
        return np.zeros(len(keys), dtype=bool)
    pos = np.minimum(np.searchsorted(sorted_keys, keys), len(sorted_keys) - 1)
    return sorted_keys[pos] == keys


class _FirstPerCell:
    """The first point (file order) of each occupied cell, kept in file order in at most `capacity`
    rows; the cell is `cell0 * 2**level`, cell indices are those of cell0 shifted by the level.
    Work arrays over the kept rows go `step` rows at a time."""

    def __init__(self, cell0: float, capacity: int, step: int):
        self.cell0 = cell0
        self.step = step
        self.level = 0
        self.origin: np.ndarray | None = None
        self.rows = np.empty((capacity, 3))  # pages are touched only as points are kept
        self.n = 0
        self.keys = np.empty(0, dtype=np.int64)  # the kept cells, sorted

    @property
    def cell(self) -> float:
        return self.cell0 * 2**self.level

    def _fine(self, xyz: np.ndarray) -> np.ndarray:
        # in float64 from an origin inside the scan: whole-metre UTM coordinates lose nothing
        local = xyz - self.origin
        local /= self.cell0
        return np.floor(local, out=local).astype(np.int64)

    def _fits(self, fine: np.ndarray) -> bool:
        return cells.fits(fine.min() >> self.level, fine.max() >> self.level)

    def _pack(self, fine: np.ndarray) -> np.ndarray:
        return cells.pack(fine >> self.level)

    def add(self, xyz: np.ndarray) -> None:
        if not len(xyz):
            return
        if self.origin is None:
            self.origin = (xyz.min(axis=0) + xyz.max(axis=0)) / 2
        fine = self._fine(xyz)
        while True:
            if self._fits(fine):
                keys, first = _first_of_each(self._pack(fine))
                new = ~_member(keys, self.keys)
                if self.n + int(new.sum()) <= len(self.rows):
                    break
            self._coarsen()
        keys, first = keys[new], first[new]
        self.rows[self.n : self.n + len(first)] = xyz[np.sort(first)]
        self.n += len(first)
        self.keys = _merged(self.keys, keys)

    def _coarsen(self) -> None:
        """Double the cell: keep the first kept point of each coarser cell."""
        self.level += 1
        self.keys = None  # made again below
        keys = np.empty(self.n, dtype=np.int64)
        for i in range(0, self.n, self.step):
            keys[i : i + self.step] = self._pack(
                self._fine(self.rows[i : min(i + self.step, self.n)])
            )
        self.keys, first = _first_of_each(keys)
        del keys
        first.sort()
        # in place, block by block: row first[j] >= j is read before any block writes over it
        for i in range(0, len(first), self.step):
            block = first[i : i + self.step]
            self.rows[i : i + len(block)] = self.rows[block]
        self.n = len(first)


def read_scan_points(path, reading: ReadingConfig, config: AlignConfig) -> PointCloud:
    """A scan's coordinates as registration with `config` reads them: within the budget `reading`,
    a scan over it thinned to a share of the finest voxel registration builds on it."""
    return read_bounded(path, reading, min(config.voxel, config.final_voxel))

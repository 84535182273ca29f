"""Spill files for thinning by tiles: points bucketed by tile beside the output, in stream order."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.config.merge import MergeConfig
from plotmosaic.stages.merge.plan import Source
from plotmosaic.stages.merge.records import (
    column_bounds,
    posed_record,
    read_records,
    stable_order,
    take_records,
    voxel_ijk,
)

# ---------------------------------------------------------------- thinning by tiles
#
# Which point wins a voxel: the first in stream order (sources in manifest order, points in file
# order). That rule is local to a voxel, so the cloud can be cut into tiles along voxel faces and
# each tile thinned alone: the kept set is the whole-cloud thinning, whatever the tiling or chunking.
# Points are bucketed by tile into raw spill files (in stream order) and each tile is thinned in
# memory with one sort; a tile over the memory budget is cut in two first (recursively), so memory is
# bounded by the budget, never by the input or the output.

# in-chunk thinning goes on for a source while it drops at least 20 % of the points
PRETHIN_WORTH = 0.8
_BYTES_OVERHEAD = 96  # per point while thinning a tile, beside two copies of its record: voxel indices, key, sort order


class Bucket:
    """One tile's spill file: raw output records in stream order, with their voxel-index bounds.
    An accumulator (each append grows the file, the count and the bounds), hence a plain class."""

    def __init__(self, path: Path):
        self.path = path
        self.count = 0
        self.lo = np.full(3, np.iinfo(np.int64).max)
        self.hi = np.full(3, np.iinfo(np.int64).min)

    def append(self, raw: np.ndarray, ijk: np.ndarray) -> None:
        with open(self.path, "ab") as f:
            f.write(np.ascontiguousarray(raw).data)
        self.count += len(raw)
        lo, hi = column_bounds(ijk)
        self.lo, self.hi = np.minimum(self.lo, lo), np.maximum(self.hi, hi)


def scatter(raw: np.ndarray, ijk: np.ndarray, labels: np.ndarray, bucket_of) -> None:
    """Append each group of points with the same (integer) label to `bucket_of(label)`, keeping their order."""
    lo, hi = labels.min(), labels.max()
    if lo == hi:  # the whole chunk in one tile: no sort
        bucket_of(lo).append(raw, ijk)
        return
    span_bits = int(hi - lo).bit_length()
    order = (
        stable_order((labels - lo).astype(np.int64), span_bits)
        if span_bits <= 62
        else np.argsort(labels, kind="stable")
    )
    ordered = labels[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    for a, b in zip(starts, [*starts[1:], len(order)]):
        index = order[a:b]
        bucket_of(ordered[a]).append(take_records(raw, index), ijk[index])


class TileSpill:
    """Output records bucketed by square xy tiles (`edge` voxels, anchored at the output offset)."""

    def __init__(self, folder: Path, step: int, edge: int):
        self.folder, self.step, self.edge = folder, step, edge
        self.buckets: dict[int, Bucket] = {}

    def add(self, raw: np.ndarray) -> None:
        if len(raw) == 0:
            return
        ijk = voxel_ijk(raw, self.step)
        cells = (ijk[:, :2] // self.edge + (1 << 31)).astype(np.uint64)  # output integers are int32
        scatter(raw, ijk, (cells[:, 0] << np.uint64(32)) | cells[:, 1], self._bucket)

    def _bucket(self, label) -> Bucket:
        label = int(label)
        if label not in self.buckets:
            self.buckets[label] = Bucket(self.folder / f"{label}.bin")
        return self.buckets[label]

    def tiles(self) -> list[tuple[tuple[int, int], Bucket]]:
        """(tile index (i, j), bucket) in label order (x, then y)."""
        return [
            (((k >> 32) - (1 << 31), (k & 0xFFFFFFFF) - (1 << 31)), self.buckets[k])
            for k in sorted(self.buckets)
        ]


def tile_points(config: MergeConfig, dtype: np.dtype, parallel: int) -> int:
    """Points one tile may hold so that `parallel` tiles in memory fit the budget."""
    per_point = 2 * dtype.itemsize + _BYTES_OVERHEAD
    return max(1, config.tile_memory_mb * 2**20 // (per_point * parallel))


def tile_name(origin: np.ndarray) -> str:
    return "tile_" + "_".join(f"{v:.3f}".rstrip("0").rstrip(".") for v in origin) + ".laz"


def bucket_sources(
    spill: TileSpill, sources: list[Source], header, config: MergeConfig, step: int | None, bar
) -> list[int]:
    """First pass: every chunk posed, cropped, thinned within itself (a point that is not the first of its
    voxel in its chunk cannot be the first in the cloud) and bucketed by tile. The points read per source."""
    points_in = []
    for source in sources:
        n_in = 0
        prethin = step is not None
        for chunk in read_records(source.path, config.chunk_size):
            record = posed_record(source, chunk, header, config.bbox, step if prethin else None)
            spill.add(record.array)
            # a fine voxel keeps nearly every point: then the in-chunk pass costs a sort and saves nothing
            prethin = prethin and len(record) < PRETHIN_WORTH * len(chunk)
            n_in += len(chunk)
            if bar is not None:
                bar.advance(len(chunk), source.id)
        points_in.append(n_in)
    return points_in

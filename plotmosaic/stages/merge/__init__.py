"""Merge posed scans into one LAS/LAZ 1.4 cloud, streaming chunk by chunk.

Memory stays bounded by the chunk size (with voxel thinning or --tiles, by the tile memory budget:
points are bucketed by tile into spill files beside the output, then each tile is thinned alone):
no scan, and no output, is ever held whole. Each chunk is posed in float64 straight from the file's stored
integers to the output's (one 4x4: input scaling, pose, output scaling), stored at 1 mm around
an offset rounded to 1 km, so UTM coordinates keep their millimetres. All other fields (intensity,
returns, classification, gps_time, RGB, user data, flags, unscaled extra dimensions such as
`label`) are carried over as stored; a field some input lacks is zero for its points.

Each source gets its own point_source_id: the scan's index in the manifest (0, 1, ...; a scan
left out with --skip-missing keeps its number free) and, after them, the ALS tiles. The table
id <-> number is written both into the file (VLR user "plotmosaic", record 1, JSON) and into a
sidecar `<out>.json` with the per-source counts, bounds, CRS and settings. Both are written
atomically: a failed or interrupted merge leaves no file and keeps an earlier output.

This module writes (stream, or tiles thinned one at a time); `job` and `plan` decide what is written,
`records` poses and thins point records, `tiles` spills them by tile, `progress` shows it."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np
from threadpoolctl import threadpool_limits

from plotmosaic.config.merge import SCALE, MergeConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import atomic_folder, atomic_output, temp_folder
from plotmosaic.lifetime import interrupts
from plotmosaic.manifest import Manifest
from plotmosaic.parallel import in_two_threads, threads
from plotmosaic.poses import Poses
from plotmosaic.stages.merge.job import MergeJob, plan_merge, sidecar_text, summary_of
from plotmosaic.stages.merge.plan import (
    TILE_INDEX,
    MergeSummary,
    Source,
    SourceCount,
    parse_bbox,
    plan_sources,
    read_source_table,
    sidecar_path,
    source_counts,
)
from plotmosaic.stages.merge.progress import points_bar
from plotmosaic.stages.merge.records import (
    count_out,
    first_in_voxel,
    posed_record,
    read_records,
    stable_order,
    take_records,
    voxel_ijk,
)
from plotmosaic.stages.merge.tiles import (
    Bucket,
    TileSpill,
    bucket_sources,
    scatter,
    tile_name,
    tile_points,
)

_SPLIT_SAMPLE = 65_536  # records sampled to choose where an over-budget tile is cut
_SPILL_READ = 1_000_000  # records read at once when an over-budget tile is re-bucketed


def _split(bucket: Bucket, dtype: np.dtype, step: int) -> list[Bucket]:
    """Cut an over-budget tile in two along voxel faces, at the median of a sample on its widest axis."""
    mapped = np.memmap(bucket.path, dtype=dtype, mode="r", shape=(bucket.count,))
    sample = voxel_ijk(np.array(mapped[:: max(1, bucket.count // _SPLIT_SAMPLE)]), step)
    del mapped
    extent = bucket.hi - bucket.lo
    spread = np.percentile(sample, 95, axis=0) - np.percentile(sample, 5, axis=0)
    score = np.where(extent > 0, spread, -1.0)
    if score.max() <= 0:  # the sample is one voxel wide: fall back on the bounds
        score = np.where(extent > 0, extent, -1)
    axis = int(np.argmax(score))
    # both halves non-empty
    cut = int(np.clip(np.median(sample[:, axis]), bucket.lo[axis] + 1, bucket.hi[axis]))
    halves = [Bucket(bucket.path.with_suffix(f".{k}.bin")) for k in (0, 1)]
    with open(bucket.path, "rb") as f:
        while len(raw := np.fromfile(f, dtype=dtype, count=_SPILL_READ)):
            ijk = voxel_ijk(raw, step)
            scatter(raw, ijk, (ijk[:, axis] >= cut).astype(np.int64), lambda k: halves[int(k)])
    bucket.path.unlink()
    return halves


def thinned_blocks(
    bucket: Bucket, dtype: np.dtype, step: int | None, max_points: int
) -> Iterator[np.ndarray]:
    """A tile's records, voxel-thinned when `step` is set, in blocks of at most `max_points`, in a
    fixed order (sub-tile by sub-tile, stream order within each); the spill files are removed as read."""
    stack = [bucket]
    while stack:
        b = stack.pop()
        if step is None:  # no thinning: stream the tile as it is
            with open(b.path, "rb") as f:
                while len(raw := np.fromfile(f, dtype=dtype, count=max_points)):
                    yield raw
        elif b.count <= max_points:
            raw = np.fromfile(b.path, dtype=dtype)
            yield take_records(raw, first_in_voxel(voxel_ijk(raw, step)))
        elif np.all(b.lo == b.hi):  # a single voxel: its first point
            yield np.fromfile(b.path, dtype=dtype, count=1)
        else:
            stack.extend(reversed(_split(b, dtype, step)))
            continue
        b.path.unlink()


def auto_tile_edge(
    mins: np.ndarray, maxs: np.ndarray, total: int, max_points: int, step: int
) -> int:
    """Tile edge (voxels) for a single output: about a quarter of the budget a tile at mean density."""
    if total <= max_points:
        return 1 << 40  # one tile
    area = max(float((maxs[0] - mins[0]) * (maxs[1] - mins[1])), 1e-6)
    edge_m = 0.5 * np.sqrt(area * max_points / total)
    return max(1, int(edge_m / SCALE) // step)


# ---------------------------------------------------------------- merging


def merge_scans(
    manifest: Manifest,
    poses: Poses,
    out: str | Path,
    config: MergeConfig | None = None,
    progress: bool = True,
    poses_path: str | Path | None = None,
) -> MergeSummary:
    """Write every posed scan (and optionally the ALS tiles) into one LAS/LAZ 1.4 file (or, with
    `tiles`, one LAZ per tile in the folder `out`), atomically."""
    config = config or MergeConfig()
    with interrupts.installed():
        return _merge_scans(manifest, poses, Path(out), config, progress, poses_path)


def _merge_scans(
    manifest: Manifest, poses: Poses, out: Path, config: MergeConfig, progress: bool, poses_path
) -> MergeSummary:
    job = plan_merge(manifest, poses, out, config, poses_path)
    try:
        # One BLAS thread: the 3x3 products are tiny per point, and a multi-threaded OpenBLAS on a
        # busy machine slows apply_transform down many times; the LAZ codec uses the cores instead.
        with threadpool_limits(1, user_api="blas"), points_bar(progress, job.total) as bar:
            if config.voxel is None and not config.tiles:
                summary = _write_stream(job, bar)
            else:
                summary = _write_thinned(job, bar)
    except OSError as exc:  # disk full, folder vanished...: a user problem, not a bug
        raise InputError(f"{out}: cannot write ({exc.strerror or exc})") from None
    return dataclasses.replace(summary, seconds=time.perf_counter() - job.start)


def _finish_file(job: MergeJob, writer: laspy.LasWriter, counts: list[SourceCount]) -> MergeSummary:
    """The summary of a written single file, and its sidecar written atomically."""
    summary = summary_of(job, counts, writer.header.mins, writer.header.maxs)
    with atomic_output(job.sidecar, force=True) as tmp_json:
        tmp_json.write_text(sidecar_text(job, summary))
    return summary


def _write_stream(job: MergeJob, bar) -> MergeSummary:
    """Plain merge into one file, no thinning."""
    out, header = job.out, job.header
    with atomic_output(out, force=True) as tmp:
        laz = out.suffix.lower() == ".laz"
        with laspy.open(tmp, mode="w", header=header, do_compress=laz) as writer:
            counts = _stream(writer, job.sources, header, job.config, bar)
        if writer.header.point_count == 0:
            raise InputError("no point left to write (check --bbox)")
        return _finish_file(job, writer, counts)


def _write_thinned(job: MergeJob, bar) -> MergeSummary:
    """Points spilled by tile beside the output, then each tile thinned alone: one file, or with
    `tiles` one LAZ per tile in a folder."""
    config, header = job.config, job.header
    with temp_folder(job.out, ".spill") as folder:
        step = int(round(config.voxel / SCALE)) if config.voxel else None
        dtype = header.point_format.dtype()
        parallel = min(2, threads()) if config.tiles else 1
        max_points = tile_points(config, dtype, parallel)
        if config.tiles:
            edge = int(round(config.tile_size / SCALE)) // (step or 1)
        else:
            edge = auto_tile_edge(job.mins, job.maxs, job.total, max_points, step or 1)
        spill = TileSpill(folder, step or 1, edge)
        points_in = bucket_sources(spill, job.sources, header, config, step, bar)
        if not spill.buckets:
            raise InputError("no point left to write (check --bbox)")
        if config.tiles:
            with atomic_folder(job.out, config.force) as tmp_dir:
                tiles, out_by_id = _write_tiles(
                    tmp_dir, spill, header, _ids(job), step, max_points, parallel
                )
                lo = np.min([t["min"] for t in tiles], axis=0)
                hi = np.max([t["max"] for t in tiles], axis=0)
                counts = _thinned_counts(job, points_in, out_by_id)
                summary = summary_of(job, counts, lo, hi, tiles)
                (tmp_dir / TILE_INDEX).write_text(sidecar_text(job, summary))
            return summary
        return _write_thinned_file(job, spill, points_in, dtype, step, max_points)


def _ids(job: MergeJob) -> int:
    """How many point_source_id values the output can hold (sources go by increasing id)."""
    return job.sources[-1].source_id + 1


def _thinned_counts(
    job: MergeJob, points_in: list[int], out_by_id: np.ndarray
) -> list[SourceCount]:
    return source_counts(job.sources, points_in, [out_by_id[s.source_id] for s in job.sources])


def _write_thinned_file(
    job: MergeJob, spill: TileSpill, points_in: list[int], dtype, step, max_points
) -> MergeSummary:
    out, header = job.out, job.header
    out_by_id = np.zeros(_ids(job), dtype=np.int64)
    with atomic_output(out, force=True) as tmp:
        laz = out.suffix.lower() == ".laz"
        with laspy.open(tmp, mode="w", header=header, do_compress=laz) as writer:
            for _, bucket in spill.tiles():
                _write_blocks(
                    writer, header, thinned_blocks(bucket, dtype, step, max_points), out_by_id
                )
        return _finish_file(job, writer, _thinned_counts(job, points_in, out_by_id))


def _stream(
    writer: laspy.LasWriter, sources: list[Source], header, config: MergeConfig, bar
) -> list[SourceCount]:
    """Plain merge: every chunk posed and written straight away, in stream order."""
    points_in, points_out = [], []
    for source in sources:
        n_in = n_out = 0
        for chunk in read_records(source.path, config.chunk_size):
            record = posed_record(source, chunk, header, config.bbox)
            write_chunk(writer, record)
            n_in += len(chunk)
            n_out += len(record)
            if bar is not None:
                bar.advance(len(chunk), source.id)
        points_in.append(n_in)
        points_out.append(n_out)
    return source_counts(sources, points_in, points_out)


def _write_tiles(
    folder: Path,
    spill: TileSpill,
    header,
    ids: int,
    step: int | None,
    max_points: int,
    parallel: int,
) -> tuple[list[dict], np.ndarray]:
    """One LAZ per tile, `parallel` tiles at a time (each with a single-threaded codec then); the
    tiles, and the points written per point_source_id."""
    edge_m = spill.edge * spill.step * SCALE
    backend = laspy.LazBackend.Lazrs if parallel > 1 else laspy.LazBackend.LazrsParallel
    dtype = header.point_format.dtype()

    def write(item) -> dict:
        (i, j), bucket = item
        origin = header.offsets[:2] + np.array([i, j]) * edge_m
        tile_out = np.zeros(ids, dtype=np.int64)
        path = folder / tile_name(origin)
        with laspy.open(
            path, mode="w", header=header, do_compress=True, laz_backend=backend
        ) as writer:
            _write_blocks(writer, header, thinned_blocks(bucket, dtype, step, max_points), tile_out)
        h = writer.header
        return {
            "file": path.name,
            "origin": [round(float(v), 3) for v in origin],
            "size": round(edge_m, 3),
            "points": int(h.point_count),
            "min": [round(float(v), 3) for v in h.mins],
            "max": [round(float(v), 3) for v in h.maxs],
            "_counts": tile_out,
        }

    items, tiles = spill.tiles(), []
    # by pairs, not one pool over all: Ctrl-C waits for two tiles at most
    for k in range(0, len(items), parallel):
        tiles += (
            in_two_threads(write, items[k : k + parallel]) if parallel > 1 else [write(items[k])]
        )
    out_by_id = np.zeros(ids, dtype=np.int64)
    for tile in tiles:
        out_by_id += tile.pop("_counts")
    return tiles, out_by_id


def _write_blocks(writer, header, blocks: Iterator[np.ndarray], counts: np.ndarray) -> None:
    """Thinned records written in their order, each counted by point_source_id into `counts`."""
    for block in blocks:
        counts += count_out(block, len(counts))
        record = laspy.ScaleAwarePointRecord(
            block, header.point_format, header.scales, header.offsets
        )
        write_chunk(writer, record)


def write_chunk(writer: laspy.LasWriter, record: laspy.ScaleAwarePointRecord) -> None:
    if len(record):
        writer.write_points(record)


__all__ = [
    "TILE_INDEX",
    "MergeSummary",
    "merge_scans",
    "first_in_voxel",
    "parse_bbox",
    "plan_sources",
    "posed_record",
    "read_records",
    "read_source_table",
    "sidecar_path",
    "stable_order",
]

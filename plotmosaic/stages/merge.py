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
atomically: a failed or interrupted merge leaves no file and keeps an earlier output."""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS
from pyproj.exceptions import CRSError
from threadpoolctl import threadpool_limits

from plotmosaic.config.merge import SCALE, MergeConfig, bbox_limits
from plotmosaic.errors import InputError, interrupts
from plotmosaic.io.atomic import (
    atomic_folder,
    atomic_output,
    check_writable,
    temp_folder,
    temp_name,
)
from plotmosaic.io.frame import apply_transform, translation
from plotmosaic.io.las import (
    STANDARD_ATTRIBUTES,
    HeaderInfo,
    corrupt_data,
    las_offsets,
    make_header,
    open_las,
    read_header_info,
)
from plotmosaic.manifest import Manifest
from plotmosaic.parallel import in_two_threads, threads
from plotmosaic.poses import Poses

VLR_USER_ID = "plotmosaic"
VLR_RECORD_ID = 1
MAX_SOURCE_ID = 65535  # point_source_id is a uint16
TILE_INDEX = "index.json"  # the index of a tiled output (--tiles), inside its folder


def parse_bbox(text: str) -> tuple[float, ...]:
    """`xmin,ymin,xmax,ymax[,zmin,zmax]` -> numbers (checked again by MergeConfig)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise InputError(
            f"--bbox {text!r}: expected numbers xmin,ymin,xmax,ymax[,zmin,zmax]"
        ) from None
    try:
        MergeConfig(bbox=values)
    except ValueError as exc:  # pydantic's ValidationError is a ValueError
        raise InputError(f"--bbox {text!r}: {_first_error(exc)}") from None
    return values


def _first_error(exc: Exception) -> str:
    errors = getattr(exc, "errors", None)
    if callable(errors):
        msg = errors()[0]["msg"]
        return msg.removeprefix("Value error, ")
    return str(exc)


@dataclass
class Source:
    """One input file with its pose into the output frame."""

    id: str
    kind: str
    path: Path
    source_id: int
    transform: np.ndarray
    info: HeaderInfo


@dataclass
class SourceCount:
    source_id: int
    id: str
    kind: str
    path: str
    points_in: int = 0
    points_out: int = 0


@dataclass
class MergeSummary:
    out: Path
    sidecar: Path
    sources: list[SourceCount]
    mins: np.ndarray
    maxs: np.ndarray
    crs: str | None  # WKT
    crs_name: str | None
    crs_source: str  # where the CRS came from, or why there is none
    voxel: float | None
    bbox: tuple[float, ...] | None
    seconds: float
    skipped: list[str] = field(
        default_factory=list
    )  # manifest scans without a pose (--skip-missing)
    ignored: list[str] = field(default_factory=list)  # posed scans not in the manifest
    tiles: list[dict] | None = (
        None  # with --tiles: one entry per written tile (file, origin, points, bounds)
    )

    @property
    def points_in(self) -> int:
        return sum(s.points_in for s in self.sources)

    @property
    def points_out(self) -> int:
        return sum(s.points_out for s in self.sources)

    @property
    def points_per_second(self) -> float:
        return self.points_in / self.seconds if self.seconds > 0 else float("nan")

    def to_dict(self) -> dict:
        return {
            "out": str(self.out),
            "points_in": self.points_in,
            "points_out": self.points_out,
            "sources": [vars(s) for s in self.sources],
            "bounds": {
                "min": [round(float(v), 3) for v in self.mins],
                "max": [round(float(v), 3) for v in self.maxs],
            },
            "crs": self.crs,
            "crs_name": self.crs_name,
            "crs_source": self.crs_source,
            "voxel": self.voxel,
            "bbox": list(self.bbox) if self.bbox else None,
            "skipped": self.skipped,
            "ignored": self.ignored,
            "seconds": round(self.seconds, 3),
            **({"tiles": self.tiles} if self.tiles is not None else {}),
        }


# ---------------------------------------------------------------- planning


def plan_sources(
    manifest: Manifest, poses: Poses, config: MergeConfig
) -> tuple[list[Source], list[str], list[str]]:
    """Sources to merge in output order, scans left out (no pose), and poses not in the manifest."""
    if poses.frame not in ("crs", "plot"):
        raise InputError(f"poses: unknown frame {poses.frame!r} (expected 'crs' or 'plot')")
    sources: list[Source] = []
    skipped: list[str] = []
    for index, scan in enumerate(manifest.scans):
        if scan.id not in poses.scans:
            if not config.skip_missing:
                raise InputError(
                    f"no pose for scan {scan.id!r} in the poses file (use --skip-missing to leave it out)"
                )
            skipped.append(scan.id)
            continue
        path = manifest.resolve(scan.path)
        sources.append(
            Source(
                scan.id,
                scan.kind.value,
                path,
                index,
                poses.transform(scan.id),
                read_header_info(path),
            )
        )
    if not sources:
        raise InputError("no scan of the manifest has a pose: nothing to merge")
    plots = {manifest.plot_of(s.id).id for s in sources}
    if poses.frame == "plot" and len(plots) > 1:
        raise InputError(
            f"poses are in per-plot frames but the scans come from {len(plots)} plots ({', '.join(sorted(plots))}); tie them to the ALS first"
        )
    if config.include_als:
        if not manifest.als:
            raise InputError("--include-als: the manifest has no [[als]] tiles")
        if poses.frame != "crs":
            raise InputError(
                "--include-als needs poses in the CRS frame (from tie-to-als), these are in the 'plot' frame"
            )
        for j, tile in enumerate(manifest.als):
            path = manifest.resolve(tile.path)
            sources.append(
                Source(
                    f"als:{tile.path.as_posix()}",
                    "als",
                    path,
                    len(manifest.scans) + j,
                    np.eye(4),
                    read_header_info(path),
                )
            )
    if sources[-1].source_id > MAX_SOURCE_ID:
        raise InputError(
            f"{sources[-1].source_id + 1} sources do not fit point_source_id (at most {MAX_SOURCE_ID + 1})"
        )
    known = {s.id for s in manifest.scans}
    ignored = sorted(sid for sid in poses.scans if sid not in known)
    return sources, skipped, ignored


def output_crs(manifest: Manifest, poses: Poses, sources: list[Source]) -> tuple[CRS | None, str]:
    """The CRS to write: the poses' own, else the (single) CRS of the merged plots, else none."""
    if poses.crs:
        try:
            return CRS.from_user_input(poses.crs), "poses file"
        except CRSError:
            raise InputError("poses: 'crs' is not a CRS pyproj understands") from None
    scan_ids = {s.id for s in manifest.scans}
    plots = {
        manifest.plot_of(s.id).id: manifest.plot_of(s.id).crs for s in sources if s.id in scan_ids
    }
    crss = {crs for crs in plots.values() if crs}
    if len(crss) > 1:
        raise InputError(
            f"plots {', '.join(sorted(plots))} have different CRSs and the poses give none"
        )
    if crss:
        named = ", ".join(pid for pid, crs in plots.items() if crs)
        return CRS.from_user_input(crss.pop()), f"manifest (plot {named})"
    return None, "none: neither the poses nor the manifest give one"


def output_bounds(sources: list[Source]) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the posed scans from their header boxes (8 corners each through the pose)."""
    corners = []
    for s in sources:
        if s.info.point_count == 0:
            continue
        lo, hi = s.info.mins, s.info.maxs
        box = np.array(
            [
                [(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]]
                for i in (0, 1)
                for j in (0, 1)
                for k in (0, 1)
            ]
        )
        corners.append(apply_transform(s.transform, box))
    if not corners:
        raise InputError("every input file is empty: nothing to merge")
    allc = np.vstack(corners)
    lo, hi = allc.min(axis=0), allc.max(axis=0)
    if np.max(hi - lo) > MAX_SPAN_M:
        raise InputError(_span_culprit([s for s in sources if s.info.point_count], corners))
    return lo, hi


# the output's 1 mm integers about a kilometre offset hold +-2,147 km: keep a margin below that
MAX_SPAN_M = 2_000_000.0


def _span_culprit(sources: list[Source], corners: list[np.ndarray]) -> str:
    """Why the merged extent is too wide to write: a file whose own points span that far (a stray
    point, not a pose), else the scan posed farthest from the others (its pose)."""
    limit = f"one merged file at 1 mm holds at most {MAX_SPAN_M / 1000:,.0f} km"
    for s in sources:
        span = float(np.max(s.info.maxs - s.info.mins))
        if span > MAX_SPAN_M:
            return (
                f"{s.path}: the file's own points span {span / 1000:,.0f} km (a stray point far "
                f"from the scan, or a damaged file); {limit}"
            )
    centres = np.array([c.mean(axis=0) for c in corners])
    far = np.linalg.norm(centres - np.median(centres, axis=0), axis=1)
    s = sources[int(np.argmax(far))]
    return (
        f"{s.path}: scan {s.id!r} is posed {far.max() / 1000:,.0f} km from the other scans "
        f"(is its pose right?); {limit}"
    )


def output_attributes(sources: list[Source]) -> list[str]:
    """Standard attributes present in at least one input (others are zero where missing)."""
    present = set().union(*(s.info.dimensions for s in sources))
    return [n for n in STANDARD_ATTRIBUTES if n in present and n != "point_source_id"]


def _adjusted_gps_time(sources: list[Source]) -> bool:
    """True when every input with gps_time stores adjusted standard GPS time."""
    flags = []
    for s in sources:
        if "gps_time" in s.info.dimensions:
            with open_las(s.path) as reader:
                flags.append(
                    reader.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD
                )
    return bool(flags) and all(flags)


def output_extra_dims(sources: list[Source]) -> dict[str, np.dtype]:
    """Unscaled single-value extra dimensions (e.g. the simulator's `label`) present in any input
    with one dtype everywhere; zero where an input lacks them. Others are dropped."""
    found: dict[str, set] = {}
    for s in sources:
        with open_las(s.path) as reader:
            for dim in reader.header.point_format.extra_dimensions:
                ok = not dim.is_scaled and dim.num_elements == 1
                found.setdefault(dim.name, set()).add(np.dtype(dim.dtype) if ok else None)
    return {
        name: dtypes.pop()
        for name, dtypes in found.items()
        if len(dtypes) == 1 and None not in dtypes
    }


def source_table(sources: list[Source]) -> list[dict]:
    return [
        {"source_id": s.source_id, "id": s.id, "kind": s.kind, "file": s.path.name} for s in sources
    ]


def build_header(sources: list[Source], crs: CRS | None, mins: np.ndarray) -> laspy.LasHeader:
    header = make_header(
        output_attributes(sources),
        output_extra_dims(sources),
        crs=crs,
        offsets=las_offsets(mins),
        scale=SCALE,
    )
    if _adjusted_gps_time(sources):
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    payload = json.dumps(
        {"version": 1, "sources": source_table(sources)}, separators=(",", ":")
    ).encode()
    if len(payload) > 65535:
        raise InputError(f"the source table of {len(sources)} sources does not fit a LAS VLR")
    header.vlrs.append(
        laspy.VLR(VLR_USER_ID, VLR_RECORD_ID, "point_source_id table (JSON)", payload)
    )
    return header


def read_source_table(path: str | Path) -> list[dict]:
    """The point_source_id table stored in a merged file."""
    with laspy.open(path) as reader:
        for vlr in reader.header.vlrs:
            if vlr.user_id == VLR_USER_ID and vlr.record_id == VLR_RECORD_ID:
                return json.loads(vlr.record_data)["sources"]
    raise InputError(f"{path}: no plotmosaic source table (not written by plotmosaic merge)")


# ---------------------------------------------------------------- thinning by tiles
#
# Which point wins a voxel: the first in stream order (sources in manifest order, points in file
# order). That rule is local to a voxel, so the cloud can be cut into tiles along voxel faces and
# each tile thinned alone: the kept set is the whole-cloud thinning, whatever the tiling or chunking.
# Points are bucketed by tile into raw spill files (in stream order) and each tile is thinned in
# memory with one sort; a tile over the memory budget is cut in two first (recursively), so memory is
# bounded by the budget, never by the input or the output.

_SPLIT_SAMPLE = 65_536  # records sampled to choose where an over-budget tile is cut
_SPILL_READ = 1_000_000  # records read at once when an over-budget tile is re-bucketed
_PRETHIN_WORTH = (
    0.8  # in-chunk thinning goes on for a source while it drops at least 20 % of the points
)
_BYTES_OVERHEAD = 96  # per point while thinning a tile, beside two copies of its record: voxel indices, key, sort order


def voxel_ijk(raw: np.ndarray, step: int) -> np.ndarray:
    """(N, 3) int64 voxel indices of output records (the voxel grid is anchored at the output offset)."""
    ijk = np.empty((len(raw), 3), dtype=np.int64)
    for axis, name in enumerate("XYZ"):
        ijk[:, axis] = np.floor_divide(raw[name], step)
    return ijk


def column_bounds(ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-column min and max of an (N, 3) array (column by column: axis=0 reductions are several times slower)."""
    return np.array([ijk[:, k].min() for k in range(3)]), np.array(
        [ijk[:, k].max() for k in range(3)]
    )


def take_records(raw: np.ndarray, index: np.ndarray) -> np.ndarray:
    """raw[index] for a structured point array, as whole rows of bytes (much faster than numpy's
    field-by-field gather of a structured dtype)."""
    raw = np.ascontiguousarray(raw)
    rows = raw.view(np.uint8).reshape(len(raw), raw.dtype.itemsize)
    return np.take(rows, index, axis=0).reshape(-1).view(raw.dtype)


def stable_order(keys: np.ndarray, key_bits: int) -> np.ndarray:
    """argsort(keys, kind="stable") for non-negative int64 keys below 2**key_bits: one plain sort of
    key and index packed together when they fit 63 bits (several times faster), else a stable argsort."""
    index_bits = max(1, int(len(keys) - 1).bit_length())
    if key_bits + index_bits > 63:
        return np.argsort(keys, kind="stable")
    packed = np.sort((keys << index_bits) | np.arange(len(keys), dtype=np.int64))
    return packed & ((1 << index_bits) - 1)


def first_in_voxel(ijk: np.ndarray) -> np.ndarray:
    """Ascending indices of the first row of each distinct voxel (one sort)."""
    if len(ijk) == 0:
        return np.empty(0, dtype=np.int64)
    lo, hi = column_bounds(ijk)
    bits = [int(v).bit_length() for v in hi - lo]
    if sum(bits) <= 62:  # pack the indices into one int64 key (always, but for far-flung outliers)
        key = (ijk[:, 0] - lo[0]) << (bits[1] + bits[2])
        key |= (ijk[:, 1] - lo[1]) << bits[2]
        key |= ijk[:, 2] - lo[2]
        order = stable_order(key, sum(bits))
        ordered = key[order]
        new = np.empty(len(order), dtype=bool)
        new[0], new[1:] = True, ordered[1:] != ordered[:-1]
    else:
        order = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))  # stable too
        ordered = ijk[order]
        new = np.empty(len(order), dtype=bool)
        new[0], new[1:] = True, np.any(ordered[1:] != ordered[:-1], axis=1)
    keep = np.zeros(len(order), dtype=bool)
    keep[order[new]] = True  # back in stream order without a second sort
    return np.flatnonzero(keep)


@dataclass
class Bucket:
    """One tile's spill file: raw output records in stream order, with their voxel-index bounds."""

    path: Path
    count: int = 0
    lo: np.ndarray = field(default_factory=lambda: np.full(3, np.iinfo(np.int64).max))
    hi: np.ndarray = field(default_factory=lambda: np.full(3, np.iinfo(np.int64).min))

    def append(self, raw: np.ndarray, ijk: np.ndarray) -> None:
        with open(self.path, "ab") as f:
            f.write(np.ascontiguousarray(raw).data)
        self.count += len(raw)
        lo, hi = column_bounds(ijk)
        self.lo, self.hi = np.minimum(self.lo, lo), np.maximum(self.hi, hi)


def _scatter(raw: np.ndarray, ijk: np.ndarray, labels: np.ndarray, bucket_of) -> None:
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
        _scatter(raw, ijk, (cells[:, 0] << np.uint64(32)) | cells[:, 1], self._bucket)

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
    cut = int(
        np.clip(np.median(sample[:, axis]), bucket.lo[axis] + 1, bucket.hi[axis])
    )  # both halves non-empty
    halves = [Bucket(bucket.path.with_suffix(f".{k}.bin")) for k in (0, 1)]
    with open(bucket.path, "rb") as f:
        while len(raw := np.fromfile(f, dtype=dtype, count=_SPILL_READ)):
            ijk = voxel_ijk(raw, step)
            _scatter(raw, ijk, (ijk[:, axis] >= cut).astype(np.int64), lambda k: halves[int(k)])
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


def tile_points(config: MergeConfig, dtype: np.dtype, parallel: int) -> int:
    """Points one tile may hold so that `parallel` tiles in memory fit the budget."""
    per_point = 2 * dtype.itemsize + _BYTES_OVERHEAD
    return max(1, config.tile_memory_mb * 2**20 // (per_point * parallel))


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


def sidecar_path(out: Path) -> Path:
    return out.with_name(out.name + ".json")


def _progress(enabled: bool, total: int):
    """A rich progress bar over points on stderr (nothing when disabled or not a terminal)."""
    if not enabled:
        return contextlib.nullcontext(None)
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    console = Console(stderr=True)
    if not console.is_terminal:
        return contextlib.nullcontext(None)
    bar = Progress(
        TextColumn("merge {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    )
    return _ProgressTask(bar, total)


class _ProgressTask:
    def __init__(self, bar, total: int):
        self.bar, self.total = bar, total

    def __enter__(self):
        self.bar.__enter__()
        self.task = self.bar.add_task("", total=self.total)
        return self

    def __exit__(self, *exc):
        return self.bar.__exit__(*exc)

    def advance(self, n: int, description: str) -> None:
        self.bar.update(self.task, advance=n, description=description)


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
    sidecar = _check_output(out, config)
    start = time.perf_counter()
    sources, skipped, ignored = plan_sources(manifest, poses, config)
    crs, crs_source = output_crs(manifest, poses, sources)
    for s in sources:  # ALS tiles are taken as they are: they must be in the output CRS
        if (
            s.kind == "als"
            and s.id.startswith("als:")
            and s.info.crs is not None
            and crs is not None
            and not s.info.crs.equals(crs, ignore_axis_order=True)
        ):
            raise InputError(
                f"{s.path}: ALS tile is in {s.info.crs.name}, the merged cloud in {crs.name}"
            )
    mins, maxs = output_bounds(sources)
    if config.bbox is not None:
        lo, hi = bbox_limits(config.bbox)
        if np.any(lo > maxs) or np.any(hi < mins):
            raise InputError(
                f"--bbox does not overlap the merged scans (x {mins[0]:.3f}..{maxs[0]:.3f}, y {mins[1]:.3f}..{maxs[1]:.3f}, z {mins[2]:.3f}..{maxs[2]:.3f})"
            )
    header = build_header(sources, crs, mins)
    counts = [SourceCount(s.source_id, s.id, s.kind, str(s.path)) for s in sources]
    total = sum(s.info.point_count for s in sources)

    def summary_of(lo, hi, tiles=None) -> MergeSummary:
        return MergeSummary(
            out,
            sidecar,
            counts,
            np.asarray(lo),
            np.asarray(hi),
            crs.to_wkt() if crs else None,
            crs.name if crs else None,
            crs_source,
            config.voxel,
            config.bbox,
            time.perf_counter() - start,
            skipped,
            ignored,
            tiles,
        )

    def write_sidecar(summary: MergeSummary) -> None:
        data = {
            "poses": str(poses_path) if poses_path else None,
            "frame": poses.frame,
            **summary.to_dict(),
        }
        with atomic_output(sidecar, force=True) as tmp_json:
            tmp_json.write_text(json.dumps(data, indent=1))

    try:
        # One BLAS thread: the 3x3 products are tiny per point, and a multi-threaded OpenBLAS on a
        # busy machine slows apply_transform down many times; the LAZ codec uses the cores instead.
        with threadpool_limits(1, user_api="blas"), _progress(progress, total) as bar:
            if config.voxel is None and not config.tiles:
                with atomic_output(out, force=True) as tmp:
                    with laspy.open(
                        tmp, mode="w", header=header, do_compress=out.suffix.lower() == ".laz"
                    ) as writer:
                        _stream(writer, sources, counts, header, config, bar)
                    if writer.header.point_count == 0:
                        raise InputError("no point left to write (check --bbox)")
                    summary = summary_of(writer.header.mins, writer.header.maxs)
                    write_sidecar(summary)
            else:
                with temp_folder(out, ".spill") as folder:
                    step = int(round(config.voxel / SCALE)) if config.voxel else None
                    dtype = header.point_format.dtype()
                    parallel = min(2, threads()) if config.tiles else 1
                    max_points = tile_points(config, dtype, parallel)
                    if config.tiles:
                        edge = int(round(config.tile_size / SCALE)) // (step or 1)
                    else:
                        edge = auto_tile_edge(mins, maxs, total, max_points, step or 1)
                    spill = TileSpill(folder, step or 1, edge)
                    _bucket(spill, sources, counts, header, config, step, bar)
                    if not spill.buckets:
                        raise InputError("no point left to write (check --bbox)")
                    if config.tiles:
                        with atomic_folder(out, config.force) as tmp_dir:
                            tiles = _write_tiles(
                                tmp_dir, spill, header, counts, step, max_points, parallel
                            )
                            summary = summary_of(
                                np.min([t["min"] for t in tiles], axis=0),
                                np.max([t["max"] for t in tiles], axis=0),
                                tiles,
                            )
                            data = {
                                "poses": str(poses_path) if poses_path else None,
                                "frame": poses.frame,
                                **summary.to_dict(),
                            }
                            (tmp_dir / TILE_INDEX).write_text(json.dumps(data, indent=1))
                    else:
                        with atomic_output(out, force=True) as tmp:
                            with laspy.open(
                                tmp,
                                mode="w",
                                header=header,
                                do_compress=out.suffix.lower() == ".laz",
                            ) as writer:
                                for _, bucket in spill.tiles():
                                    for block in thinned_blocks(bucket, dtype, step, max_points):
                                        _count_out(counts, block)
                                        write_chunk(
                                            writer,
                                            laspy.ScaleAwarePointRecord(
                                                block,
                                                header.point_format,
                                                header.scales,
                                                header.offsets,
                                            ),
                                        )
                            summary = summary_of(writer.header.mins, writer.header.maxs)
                            write_sidecar(summary)
    except OSError as exc:  # disk full, folder vanished...: a user problem, not a bug
        raise InputError(f"{out}: cannot write ({exc.strerror or exc})") from None
    summary.seconds = time.perf_counter() - start
    return summary


def _check_output(out: Path, config: MergeConfig) -> Path:
    """Refuse an output that cannot or must not be written; returns its sidecar (or tile index)."""
    if config.tiles:
        if out.exists() and not config.force:
            raise InputError(f"{out}: already exists (use --force to overwrite)")
        if out.exists() and not (out / TILE_INDEX).is_file():
            raise InputError(
                f"{out}: exists and is not a tile folder written by plotmosaic merge --tiles; not replacing it"
            )
        check_writable(temp_name(out), force=True)
        return out / TILE_INDEX
    if out.suffix.lower() not in (".las", ".laz"):
        raise InputError(f"{out}: output must end in .las or .laz")
    sidecar = sidecar_path(out)
    if not config.force:
        for path in (out, sidecar):
            if path.exists():
                raise InputError(f"{path}: already exists (use --force to overwrite)")
    check_writable(out, force=True)
    if not out.parent.is_dir():
        raise InputError(f"{out}: output folder {out.parent} is not a folder")
    return sidecar


def _stream(
    writer: laspy.LasWriter,
    sources: list[Source],
    counts: list[SourceCount],
    header,
    config: MergeConfig,
    bar,
) -> None:
    """Plain merge: every chunk posed and written straight away, in stream order."""
    for source, count in zip(sources, counts):
        for chunk in read_records(source.path, config.chunk_size):
            record = posed_record(source, chunk, header, config.bbox)
            write_chunk(writer, record)
            count.points_in += len(chunk)
            count.points_out += len(record)
            if bar is not None:
                bar.advance(len(chunk), source.id)


def _bucket(
    spill: TileSpill,
    sources: list[Source],
    counts: list[SourceCount],
    header,
    config: MergeConfig,
    step: int | None,
    bar,
) -> None:
    """First pass: every chunk posed, cropped, thinned within itself (a point that is not the first of its
    voxel in its chunk cannot be the first in the cloud) and bucketed by tile."""
    for source, count in zip(sources, counts):
        prethin = step is not None
        for chunk in read_records(source.path, config.chunk_size):
            record = posed_record(source, chunk, header, config.bbox, step if prethin else None)
            spill.add(record.array)
            # a fine voxel keeps nearly every point: then the in-chunk pass costs a sort and saves nothing
            prethin = prethin and len(record) < _PRETHIN_WORTH * len(chunk)
            count.points_in += len(chunk)
            if bar is not None:
                bar.advance(len(chunk), source.id)


def _count_out(counts: list[SourceCount], block: np.ndarray) -> None:
    per_id = np.bincount(block["point_source_id"], minlength=counts[-1].source_id + 1)
    for count in counts:
        count.points_out += int(per_id[count.source_id])


def _tile_name(origin: np.ndarray) -> str:
    return "tile_" + "_".join(f"{v:.3f}".rstrip("0").rstrip(".") for v in origin) + ".laz"


def _write_tiles(
    folder: Path, spill: TileSpill, header, counts, step: int | None, max_points: int, parallel: int
) -> list[dict]:
    """One LAZ per tile, `parallel` tiles at a time (each with a single-threaded codec then)."""
    edge_m = spill.edge * spill.step * SCALE
    backend = laspy.LazBackend.Lazrs if parallel > 1 else laspy.LazBackend.LazrsParallel
    dtype = header.point_format.dtype()

    def write(item) -> dict:
        (i, j), bucket = item
        origin = header.offsets[:2] + np.array([i, j]) * edge_m
        tile_counts = [SourceCount(c.source_id, c.id, c.kind, c.path) for c in counts]
        path = folder / _tile_name(origin)
        with laspy.open(
            path, mode="w", header=header, do_compress=True, laz_backend=backend
        ) as writer:
            for block in thinned_blocks(bucket, dtype, step, max_points):
                _count_out(tile_counts, block)
                write_chunk(
                    writer,
                    laspy.ScaleAwarePointRecord(
                        block, header.point_format, header.scales, header.offsets
                    ),
                )
        h = writer.header
        return {
            "file": path.name,
            "origin": [round(float(v), 3) for v in origin],
            "size": round(edge_m, 3),
            "points": int(h.point_count),
            "min": [round(float(v), 3) for v in h.mins],
            "max": [round(float(v), 3) for v in h.maxs],
            "_counts": [c.points_out for c in tile_counts],
        }

    items, tiles = spill.tiles(), []
    for k in range(
        0, len(items), parallel
    ):  # by pairs, not one pool over all: Ctrl-C waits for two tiles at most
        tiles += (
            in_two_threads(write, items[k : k + parallel]) if parallel > 1 else [write(items[k])]
        )
    for tile in tiles:
        for count, n in zip(counts, tile.pop("_counts")):
            count.points_out += n
    return tiles


def read_records(path: Path, chunk_size: int) -> Iterator[laspy.ScaleAwarePointRecord]:
    """The file's raw point records chunk by chunk (stored integers, all fields)."""
    with open_las(path) as reader, corrupt_data(path):
        yield from reader.chunk_iterator(chunk_size)


def integer_transform(
    pose: np.ndarray, in_scales, in_offsets, out_scales, out_offsets
) -> np.ndarray:
    """The pose as a map from a file's stored integers to the output's (float64, then rounded):
    unscale the input, apply the pose, rescale for the output, in one 4x4."""
    return (
        np.diag([*(1.0 / np.asarray(out_scales, dtype=np.float64)), 1.0])
        @ translation(-np.asarray(out_offsets, dtype=np.float64))
        @ np.asarray(pose, dtype=np.float64)
        @ translation(in_offsets)
        @ np.diag([*np.asarray(in_scales, dtype=np.float64), 1.0])
    )


def posed_record(
    source: Source,
    chunk: laspy.ScaleAwarePointRecord,
    header: laspy.LasHeader,
    bbox: tuple[float, ...] | None,
    thin: int | None = None,
) -> laspy.ScaleAwarePointRecord:
    """A chunk posed into the output, cropped, with its source id; with `thin` (a voxel edge in output
    integer units), only the first point of each voxel within the chunk.

    Works on the stored integers: one 4x4 maps input integers to output integers, so the
    other fields are copied as they are (the whole record at once when the point formats
    agree, field by field otherwise) instead of being unpacked and packed again.
    """
    M = integer_transform(
        source.transform, chunk.scales, chunk.offsets, header.scales, header.offsets
    )
    raw = chunk.array
    q = np.rint(apply_transform(M, np.column_stack([raw["X"], raw["Y"], raw["Z"]])))
    if len(q) and (q.min() < -(2**31) or q.max() > 2**31 - 1):
        raise InputError(
            f"{source.path}: posed points fall outside the output's coordinate range (is the pose right?)"
        )
    q = q.astype(np.int64)
    index = None
    if bbox is not None:
        lo, hi = bbox_limits(bbox)
        xyz = q * header.scales + header.offsets  # the coordinates as written
        index = np.flatnonzero(np.all((xyz >= lo) & (xyz <= hi), axis=1))
    if thin is not None:
        first = first_in_voxel(np.floor_divide(q if index is None else q[index], thin))
        index = first if index is None else index[first]
    if index is not None:
        raw, q = take_records(raw, index), q[index]
    if raw.dtype == header.point_format.dtype():
        record = laspy.ScaleAwarePointRecord(
            raw, header.point_format, header.scales, header.offsets
        )
    else:  # another point format (LAS 1.2 PF 3, no RGB, other extra bytes): copy the fields by name
        record = laspy.ScaleAwarePointRecord.zeros(len(raw), header=header)
        record.copy_fields_from(laspy.PackedPointRecord(raw, chunk.point_format))
    record.array["X"], record.array["Y"], record.array["Z"] = q[:, 0], q[:, 1], q[:, 2]
    record.array["point_source_id"] = source.source_id
    return record


def write_chunk(writer: laspy.LasWriter, record: laspy.ScaleAwarePointRecord) -> None:
    if len(record):
        writer.write_points(record)


interrupts_win = interrupts.installed  # the name tests/test_merge.py still calls

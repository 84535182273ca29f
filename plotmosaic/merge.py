"""Merge posed scans into one LAS/LAZ 1.4 cloud, streaming chunk by chunk.

Memory stays bounded by the chunk size (plus, with voxel thinning, 8 bytes per kept voxel):
no scan is ever held whole. Each chunk is posed in float64 straight from the file's stored
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
from pydantic import BaseModel, ConfigDict, Field, field_validator
from pyproj import CRS
from pyproj.exceptions import CRSError
from threadpoolctl import threadpool_limits

from plotmosaic.errors import InputError
from plotmosaic.io.atomic import atomic_output, check_writable
from plotmosaic.io.frame import apply_transform, translation
from plotmosaic.io.las import CHUNK_SIZE, STANDARD_ATTRIBUTES, HeaderInfo, las_offsets, make_header, read_header_info
from plotmosaic.io.las import open_las, short_error
from plotmosaic.manifest import Manifest
from plotmosaic.poses import Poses

SCALE = 0.001  # 1 mm
VLR_USER_ID = "plotmosaic"
VLR_RECORD_ID = 1
MAX_SOURCE_ID = 65535  # point_source_id is a uint16
_KEY_BITS = 21  # bits per voxel index in the packed int64 key: 2M voxels along each axis


class MergeConfig(BaseModel):
    """Options of `merge` (defaults = plain merge of every posed scan)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    voxel: float | None = Field(default=None, gt=0, description="voxel size (m) for thinning, rounded to whole mm")
    include_als: bool = False
    bbox: tuple[float, ...] | None = None  # xmin, ymin, xmax, ymax[, zmin, zmax] in output coordinates
    force: bool = False
    skip_missing: bool = False
    chunk_size: int = Field(default=CHUNK_SIZE, ge=1)

    @field_validator("voxel")
    @classmethod
    def _voxel_mm(cls, value: float | None) -> float | None:
        if value is not None and round(value / SCALE) < 1:
            raise ValueError("must be at least 0.001 (1 mm, the output resolution)")
        return value

    @field_validator("bbox")
    @classmethod
    def _bbox(cls, value: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if value is None:
            return None
        if len(value) not in (4, 6):
            raise ValueError("needs 4 or 6 numbers: xmin,ymin,xmax,ymax[,zmin,zmax]")
        if not all(np.isfinite(value)):
            raise ValueError("numbers must be finite")
        lo, hi = _bbox_limits(value)
        if np.any(lo >= hi):
            raise ValueError("each min must be smaller than its max")
        return tuple(float(v) for v in value)


def parse_bbox(text: str) -> tuple[float, ...]:
    """`xmin,ymin,xmax,ymax[,zmin,zmax]` -> numbers (checked again by MergeConfig)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--bbox {text!r}: expected numbers xmin,ymin,xmax,ymax[,zmin,zmax]") from None
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


def _bbox_limits(bbox: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    zlo, zhi = (bbox[4], bbox[5]) if len(bbox) == 6 else (-np.inf, np.inf)
    return np.array([bbox[0], bbox[1], zlo]), np.array([bbox[2], bbox[3], zhi])


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
    skipped: list[str] = field(default_factory=list)  # manifest scans without a pose (--skip-missing)
    ignored: list[str] = field(default_factory=list)  # posed scans not in the manifest

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
            "bounds": {"min": [round(float(v), 3) for v in self.mins], "max": [round(float(v), 3) for v in self.maxs]},
            "crs": self.crs,
            "crs_name": self.crs_name,
            "crs_source": self.crs_source,
            "voxel": self.voxel,
            "bbox": list(self.bbox) if self.bbox else None,
            "skipped": self.skipped,
            "ignored": self.ignored,
            "seconds": round(self.seconds, 3),
        }


# ---------------------------------------------------------------- planning


def plan_sources(manifest: Manifest, poses: Poses, config: MergeConfig) -> tuple[list[Source], list[str], list[str]]:
    """Sources to merge in output order, scans left out (no pose), and poses not in the manifest."""
    if poses.frame not in ("crs", "plot"):
        raise InputError(f"poses: unknown frame {poses.frame!r} (expected 'crs' or 'plot')")
    sources: list[Source] = []
    skipped: list[str] = []
    for index, scan in enumerate(manifest.scans):
        if scan.id not in poses.scans:
            if not config.skip_missing:
                raise InputError(f"no pose for scan {scan.id!r} in the poses file (use --skip-missing to leave it out)")
            skipped.append(scan.id)
            continue
        path = manifest.resolve(scan.path)
        sources.append(Source(scan.id, scan.kind.value, path, index, poses.transform(scan.id), read_header_info(path)))
    if not sources:
        raise InputError("no scan of the manifest has a pose: nothing to merge")
    plots = {manifest.plot_of(s.id).id for s in sources}
    if poses.frame == "plot" and len(plots) > 1:
        raise InputError(f"poses are in per-plot frames but the scans come from {len(plots)} plots ({', '.join(sorted(plots))}); tie them to the ALS first")
    if config.include_als:
        if not manifest.als:
            raise InputError("--include-als: the manifest has no [[als]] tiles")
        if poses.frame != "crs":
            raise InputError("--include-als needs poses in the CRS frame (from tie-to-als), these are in the 'plot' frame")
        for j, tile in enumerate(manifest.als):
            path = manifest.resolve(tile.path)
            sources.append(Source(f"als:{tile.path.as_posix()}", "als", path, len(manifest.scans) + j, np.eye(4), read_header_info(path)))
    if sources[-1].source_id > MAX_SOURCE_ID:
        raise InputError(f"{sources[-1].source_id + 1} sources do not fit point_source_id (at most {MAX_SOURCE_ID + 1})")
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
    plots = {manifest.plot_of(s.id).id: manifest.plot_of(s.id).crs for s in sources if s.id in scan_ids}
    crss = {crs for crs in plots.values() if crs}
    if len(crss) > 1:
        raise InputError(f"plots {', '.join(sorted(plots))} have different CRSs and the poses give none")
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
        box = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        corners.append(apply_transform(s.transform, box))
    if not corners:
        raise InputError("every input file is empty: nothing to merge")
    allc = np.vstack(corners)
    return allc.min(axis=0), allc.max(axis=0)


def output_attributes(sources: list[Source]) -> list[str]:
    """Standard attributes present in at least one input (others are zero where missing)."""
    present = set().union(*(s.info.dimensions for s in sources))
    return [n for n in STANDARD_ATTRIBUTES if n in present and n != "point_source_id"]


def _adjusted_gps_time(sources: list[Source]) -> bool:
    """True when every input with gps_time stores adjusted standard GPS time."""
    flags = []
    for s in sources:
        if "gps_time" in s.info.dimensions:
            with laspy.open(s.path) as reader:
                flags.append(reader.header.global_encoding.gps_time_type == laspy.header.GpsTimeType.STANDARD)
    return bool(flags) and all(flags)


def output_extra_dims(sources: list[Source]) -> dict[str, np.dtype]:
    """Unscaled single-value extra dimensions (e.g. the simulator's `label`) present in any input
    with one dtype everywhere; zero where an input lacks them. Others are dropped."""
    found: dict[str, set] = {}
    for s in sources:
        with laspy.open(s.path) as reader:
            for dim in reader.header.point_format.extra_dimensions:
                ok = not dim.is_scaled and dim.num_elements == 1
                found.setdefault(dim.name, set()).add(np.dtype(dim.dtype) if ok else None)
    return {name: dtypes.pop() for name, dtypes in found.items() if len(dtypes) == 1 and None not in dtypes}


def source_table(sources: list[Source]) -> list[dict]:
    return [{"source_id": s.source_id, "id": s.id, "kind": s.kind, "file": s.path.name} for s in sources]


def build_header(sources: list[Source], crs: CRS | None, mins: np.ndarray) -> laspy.LasHeader:
    header = make_header(output_attributes(sources), output_extra_dims(sources), crs=crs, offsets=las_offsets(mins), scale=SCALE)
    if _adjusted_gps_time(sources):
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
    payload = json.dumps({"version": 1, "sources": source_table(sources)}, separators=(",", ":")).encode()
    if len(payload) > 65535:
        raise InputError(f"the source table of {len(sources)} sources does not fit a LAS VLR")
    header.vlrs.append(laspy.VLR(VLR_USER_ID, VLR_RECORD_ID, "point_source_id table (JSON)", payload))
    return header


def read_source_table(path: str | Path) -> list[dict]:
    """The point_source_id table stored in a merged file."""
    with laspy.open(path) as reader:
        for vlr in reader.header.vlrs:
            if vlr.user_id == VLR_USER_ID and vlr.record_id == VLR_RECORD_ID:
                return json.loads(vlr.record_data)["sources"]
    raise InputError(f"{path}: no plotmosaic source table (not written by plotmosaic merge)")


# ---------------------------------------------------------------- thinning


class FirstInVoxel:
    """Streaming voxel thinning: keep the first point (in stream order) that falls in each voxel.

    Only the keys of the voxels seen so far are kept, as one sorted int64 array (8 bytes per
    output point), so memory is bounded by the output, never by the input. "First in stream
    order" depends only on the order of the points (sources in manifest order, points in file
    order), not on the chunk size. Voxels are counted on the written millimetre integers, so
    re-reading the file gives the same voxels.
    """

    def __init__(self, voxel: float):
        self.step = int(round(voxel / SCALE))  # voxel edge in output integer units (mm)
        self.keys = np.empty(0, dtype=np.int64)

    def voxel_keys(self, q: np.ndarray) -> np.ndarray:
        """int64 keys of the voxels of points given as output integers (N, 3)."""
        ijk = np.floor_divide(q, self.step) + (1 << (_KEY_BITS - 1))  # grid anchored at the output offset
        if len(ijk) and (ijk.min() < 0 or ijk.max() >= 1 << _KEY_BITS):
            span = (1 << (_KEY_BITS - 1)) * self.step * SCALE
            raise InputError(f"--voxel {self.step * SCALE:g}: the cloud reaches more than {span:,.0f} m from its offset along an axis")
        return (ijk[:, 0] << (2 * _KEY_BITS)) | (ijk[:, 1] << _KEY_BITS) | ijk[:, 2]

    def keep(self, q: np.ndarray) -> np.ndarray:
        """Mask of the points of this chunk (output integers) that are the first in their voxel."""
        keys = self.voxel_keys(q)
        unique, first = np.unique(keys, return_index=True)  # index of the first occurrence in the chunk
        pos = np.searchsorted(self.keys, unique)
        seen = np.zeros(len(unique), dtype=bool)
        inside = pos < len(self.keys)
        seen[inside] = self.keys[pos[inside]] == unique[inside]
        new = ~seen
        self.keys = np.insert(self.keys, pos[new], unique[new])  # linear merge, stays sorted
        mask = np.zeros(len(keys), dtype=bool)
        mask[first[new]] = True
        return mask


# ---------------------------------------------------------------- merging


def sidecar_path(out: Path) -> Path:
    return out.with_name(out.name + ".json")


def _progress(enabled: bool, total: int):
    """A rich progress bar over points on stderr (nothing when disabled or not a terminal)."""
    if not enabled:
        return contextlib.nullcontext(None)
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    console = Console(stderr=True)
    if not console.is_terminal:
        return contextlib.nullcontext(None)
    bar = Progress(TextColumn("merge {task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), console=console, transient=True)
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
    """Write every posed scan (and optionally the ALS tiles) into one LAS/LAZ 1.4 file, atomically."""
    config = config or MergeConfig()
    out = Path(out)
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

    start = time.perf_counter()
    sources, skipped, ignored = plan_sources(manifest, poses, config)
    crs, crs_source = output_crs(manifest, poses, sources)
    for s in sources:  # ALS tiles are taken as they are: they must be in the output CRS
        if s.kind == "als" and s.id.startswith("als:") and s.info.crs is not None and crs is not None and not s.info.crs.equals(crs, ignore_axis_order=True):
            raise InputError(f"{s.path}: ALS tile is in {s.info.crs.name}, the merged cloud in {crs.name}")
    mins, maxs = output_bounds(sources)
    if config.bbox is not None:
        lo, hi = _bbox_limits(config.bbox)
        if np.any(lo > maxs) or np.any(hi < mins):
            raise InputError(
                f"--bbox does not overlap the merged scans (x {mins[0]:.3f}..{maxs[0]:.3f}, y {mins[1]:.3f}..{maxs[1]:.3f}, z {mins[2]:.3f}..{maxs[2]:.3f})"
            )
    header = build_header(sources, crs, mins)
    counts = [SourceCount(s.source_id, s.id, s.kind, str(s.path)) for s in sources]
    total = sum(s.info.point_count for s in sources)
    try:
        # One BLAS thread: the 3x3 products are tiny per point, and a multi-threaded OpenBLAS on a
        # busy 2-core machine made apply_transform 20x slower; the LAZ codec uses the cores instead.
        with threadpool_limits(1, user_api="blas"), atomic_output(out, force=True) as tmp, _progress(progress, total) as bar:
            with laspy.open(tmp, mode="w", header=header, do_compress=out.suffix.lower() == ".laz") as writer:
                thin = FirstInVoxel(config.voxel) if config.voxel else None
                for source, count in zip(sources, counts):
                    for chunk in read_records(source.path, config.chunk_size):
                        record = posed_record(source, chunk, header, config.bbox, thin)
                        write_chunk(writer, record)
                        count.points_in += len(chunk)
                        count.points_out += len(record)
                        if bar is not None:
                            bar.advance(len(chunk), source.id)
            if writer.header.point_count == 0:
                raise InputError("no point left to write (check --bbox)")
            summary = MergeSummary(
                out, sidecar, counts, np.array(writer.header.mins), np.array(writer.header.maxs),
                crs.to_wkt() if crs else None, crs.name if crs else None,
                crs_source, config.voxel, config.bbox, time.perf_counter() - start, skipped, ignored,
            )
            sidecar_data = {"poses": str(poses_path) if poses_path else None, "frame": poses.frame, **summary.to_dict()}
            with atomic_output(sidecar, force=True) as tmp_json:
                tmp_json.write_text(json.dumps(sidecar_data, indent=1))
    except OSError as exc:  # disk full, folder vanished...: a user problem, not a bug
        raise InputError(f"{out}: cannot write ({exc.strerror or exc})") from None
    summary.seconds = time.perf_counter() - start
    return summary


def read_records(path: Path, chunk_size: int) -> Iterator[laspy.ScaleAwarePointRecord]:
    """The file's raw point records chunk by chunk (stored integers, all fields)."""
    with open_las(path) as reader:
        try:
            yield from reader.chunk_iterator(chunk_size)
        except Exception as exc:
            raise InputError(f"{path}: corrupt or truncated LAS/LAZ data ({short_error(exc)})") from None


def integer_transform(pose: np.ndarray, in_scales, in_offsets, out_scales, out_offsets) -> np.ndarray:
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
    source: Source, chunk: laspy.ScaleAwarePointRecord, header: laspy.LasHeader, bbox: tuple[float, ...] | None, thin: FirstInVoxel | None
) -> laspy.ScaleAwarePointRecord:
    """A chunk posed into the output, cropped and thinned, with its source id.

    Works on the stored integers: one 4x4 maps input integers to output integers, so the
    other fields are copied as they are (the whole record at once when the point formats
    agree, field by field otherwise) instead of being unpacked and packed again.
    """
    M = integer_transform(source.transform, chunk.scales, chunk.offsets, header.scales, header.offsets)
    raw = chunk.array
    q = np.rint(apply_transform(M, np.column_stack([raw["X"], raw["Y"], raw["Z"]])))
    if len(q) and (q.min() < -(2**31) or q.max() > 2**31 - 1):
        raise InputError(f"{source.path}: posed points fall outside the output's coordinate range (is the pose right?)")
    q = q.astype(np.int64)
    index = None
    if bbox is not None:
        lo, hi = _bbox_limits(bbox)
        xyz = q * header.scales + header.offsets  # the coordinates as written
        index = np.flatnonzero(np.all((xyz >= lo) & (xyz <= hi), axis=1))
    if thin is not None:
        index = np.flatnonzero(thin.keep(q)) if index is None else index[thin.keep(q[index])]
    if index is not None:
        raw, q = raw[index], q[index]
    if raw.dtype == header.point_format.dtype():
        record = laspy.ScaleAwarePointRecord(raw, header.point_format, header.scales, header.offsets)
    else:  # another point format (LAS 1.2 PF 3, no RGB, other extra bytes): copy the fields by name
        record = laspy.ScaleAwarePointRecord.zeros(len(raw), header=header)
        record.copy_fields_from(laspy.PackedPointRecord(raw, chunk.point_format))
    record.array["X"], record.array["Y"], record.array["Z"] = q[:, 0], q[:, 1], q[:, 2]
    record.array["point_source_id"] = source.source_id
    return record


def write_chunk(writer: laspy.LasWriter, record: laspy.ScaleAwarePointRecord) -> None:
    if len(record):
        writer.write_points(record)

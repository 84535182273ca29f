"""What a merge writes: its sources (one point_source_id each), CRS, bounds, attributes and header,
and the source table stored in the file and its sidecar."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS
from pyproj.exceptions import CRSError

from plotmosaic.config.merge import SCALE, MergeConfig
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import check_writable, temp_name
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import (
    STANDARD_ATTRIBUTES,
    HeaderInfo,
    las_offsets,
    make_header,
    open_las,
    read_header_info,
)
from plotmosaic.manifest import Manifest
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


@dataclass(frozen=True)
class Source:
    """One input file with its pose into the output frame."""

    id: str
    kind: str
    path: Path
    source_id: int
    transform: np.ndarray
    info: HeaderInfo


@dataclass(frozen=True)
class SourceCount:
    source_id: int
    id: str
    kind: str
    path: str
    points_in: int
    points_out: int


def source_counts(sources: list[Source], points_in, points_out) -> list[SourceCount]:
    """Each source's points read and written (`points_in`, `points_out`: one number per source)."""
    return [
        SourceCount(s.source_id, s.id, s.kind, str(s.path), int(n_in), int(n_out))
        for s, n_in, n_out in zip(sources, points_in, points_out, strict=True)
    ]


@dataclass(frozen=True)
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
    # manifest scans without a pose (--skip-missing)
    skipped: list[str] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)  # posed scans not in the manifest
    # with --tiles: one entry per written tile (file, origin, points, bounds)
    tiles: list[dict] | None = None

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
        path, T = manifest.resolve(scan.path), poses.transform(scan.id)
        sources.append(Source(scan.id, scan.kind.value, path, index, T, read_header_info(path)))
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
            info = read_header_info(path)
            source_id = len(manifest.scans) + j
            sources.append(
                Source(f"als:{tile.path.as_posix()}", "als", path, source_id, np.eye(4), info)
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


def sidecar_path(out: Path) -> Path:
    return out.with_name(out.name + ".json")


def check_output(out: Path, config: MergeConfig) -> Path:
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

"""LAS/LAZ 1.2-1.4 reading with laspy (lazrs backend); the reading entry points
(`read_header_info`, `iter_chunks`, `read_cloud`, `open_las`) also take E57 scans (io/e57.py, also
`FILE.e57#INDEX`) and PLY files (io/ply.py), dispatched on the suffix, so every caller reads them.
Writing is io/las_write.py and the in-memory types io/cloud.py; both are re-exported here.

Coordinates are always float64 in the file's own coordinate system; attributes are kept
as their LAS dtypes. Reading goes chunk by chunk so memory stays bounded by what is kept.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator
from functools import partial
from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS

from plotmosaic.config.merge import CHUNK_SIZE
from plotmosaic.errors import InputError, short_error
from plotmosaic.io import e57, ply
from plotmosaic.io.cloud import RGB, STANDARD_ATTRIBUTES, HeaderInfo, PointCloud
from plotmosaic.io.las_write import las_offsets, make_header, make_record, write_cloud
from plotmosaic.io.paths import check_input_file

__all__ = [
    "RGB",
    "STANDARD_ATTRIBUTES",
    "HeaderInfo",
    "PointCloud",
    "file_format",
    "iter_chunks",
    "las_offsets",
    "make_header",
    "make_record",
    "open_las",
    "read_cloud",
    "read_header_info",
    "write_cloud",
]

READ_SUFFIXES = (".las", ".laz", ".e57", ".ply")


def file_format(path: str | Path) -> str:
    """ "las", "e57" or "ply" from the suffix (an E57 reference path `FILE.e57#INDEX` is "e57")."""
    if e57.is_e57(path):
        return "e57"
    return "ply" if Path(path).suffix.lower() == ".ply" else "las"


def _check_file(path: Path) -> Path:
    path = Path(path)
    if file_format(path) == "e57":
        return path  # io/e57.py checks the file (and the scan a reference path names)
    check_input_file(path, "point-cloud file")
    if path.suffix.lower() not in READ_SUFFIXES:
        raise InputError(f"{path}: not a point-cloud file (expected .las, .laz, .e57 or .ply)")
    return path


# LAZ 1.4 (point formats 6-10) stores fields in separate layers: a coordinates-only read skips
# decompressing intensity, GPS time, etc. (a large share of a scan's read time); ignored otherwise
XYZ_ONLY = laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z


def open_las(path: Path, xyz_only: bool = False) -> laspy.LasReader:
    """A laspy reader; for E57/PLY a reader of the same shape (`header`, `chunk_iterator`)."""
    if file_format(path) != "las":
        return CloudRecordReader(Path(path))
    try:
        if xyz_only:
            return laspy.open(path, decompression_selection=XYZ_ONLY)
        return laspy.open(path)
    except Exception as exc:  # laspy raises several types for a bad signature/header
        raise InputError(f"{path}: not a readable LAS/LAZ file ({short_error(exc)})") from None


@contextlib.contextmanager
def corrupt_data(path: Path) -> Iterator[None]:
    """A codec error while reading points names the file as corrupt or truncated (exit 2)."""
    try:
        yield
    except InputError:
        raise
    except Exception as exc:
        raise InputError(
            f"{path}: corrupt or truncated LAS/LAZ data ({short_error(exc)})"
        ) from None


def _parse_crs(header: laspy.LasHeader) -> CRS | None:
    try:
        return header.parse_crs()
    except Exception:
        return None  # a damaged CRS VLR is not a reason to refuse the points


def read_header_info(path: str | Path) -> HeaderInfo:
    path = _check_file(Path(path))
    if file_format(path) != "las":
        return _other_header_info(path)
    with open_las(path) as reader:
        h = reader.header
        return HeaderInfo(
            path=path,
            point_count=int(h.point_count),
            point_format=int(h.point_format.id),
            version=str(h.version),
            box=(np.asarray(h.mins, dtype=np.float64), np.asarray(h.maxs, dtype=np.float64)),
            crs=_parse_crs(h),
            dimensions=tuple(h.point_format.dimension_names),
        )


def _wanted_attributes(header: laspy.LasHeader, attributes: bool | Iterable[str]) -> list[str]:
    present = set(header.point_format.dimension_names)
    if attributes is True:
        names = [n for n in STANDARD_ATTRIBUTES if n in present and n != "point_source_id"]
        names += list(header.point_format.extra_dimension_names)
        return names
    if attributes is False:
        return []
    return [n for n in attributes if n in present]


def iter_chunks(
    path: str | Path, chunk_size: int = CHUNK_SIZE, attributes: bool | Iterable[str] = True
) -> Iterator[PointCloud]:
    """Yield the file as PointCloud chunks of at most `chunk_size` points."""
    path = _check_file(Path(path))
    if file_format(path) != "las":  # E57 blocks at most 1M points: libE57's buffers are per field
        blocks = (
            e57.iter_e57_chunks(path, min(chunk_size, e57.CHUNK_SIZE), attributes)
            if file_format(path) == "e57"
            else ply.iter_ply_chunks(path, chunk_size, attributes)
        )
        for xyz, attrs in blocks:
            yield PointCloud(xyz, attrs)
        return
    with open_las(path, xyz_only=attributes is False) as reader:
        crs = _parse_crs(reader.header)
        names = _wanted_attributes(reader.header, attributes)
        with corrupt_data(path):
            for chunk in reader.chunk_iterator(chunk_size):
                xyz = np.column_stack(
                    [np.asarray(chunk.x), np.asarray(chunk.y), np.asarray(chunk.z)]
                )
                attrs = {n: np.array(chunk[n]) for n in names}
                yield PointCloud(xyz, attrs, crs)


def _las_records(path: Path, attributes: bool | Iterable[str], chunk_size: int = CHUNK_SIZE):
    """(count, raw point record, attribute names, header) per chunk of a LAS/LAZ file."""
    with open_las(path, xyz_only=attributes is False) as reader:
        names = _wanted_attributes(reader.header, attributes)
        with corrupt_data(path):
            for chunk in reader.chunk_iterator(chunk_size):
                yield len(chunk), chunk, names, reader.header


def read_cloud(
    path: str | Path, attributes: bool | Iterable[str] = True, min_points: int = 1
) -> PointCloud:
    """Read a whole point-cloud file as float64 xyz (+ attributes), validating it on the way."""
    path = _check_file(Path(path))
    if file_format(path) != "las":
        return _read_other(path, attributes, min_points)
    info = read_header_info(path)
    if info.point_count == 0:
        raise InputError(f"{path}: contains no points")
    xyz = np.empty((info.point_count, 3), dtype=np.float64)
    attrs: dict[str, np.ndarray] = {}
    n = 0
    for m, chunk, names, header in _las_records(path, attributes):
        if n + m > info.point_count:
            raise InputError(f"{path}: holds more points than its header says ({info.point_count})")
        # scaled straight into the output columns: laspy's x/y/z arrays and a column_stack would be
        # two extra passes over every point
        for i, raw in enumerate((chunk.X, chunk.Y, chunk.Z)):
            out = xyz[n : n + m, i]
            np.multiply(raw, header.scales[i], out=out)
            out += header.offsets[i]
        for name in names:
            values = np.asarray(chunk[name])
            if name not in attrs:
                attrs[name] = np.empty(info.point_count, dtype=values.dtype)
            attrs[name][n : n + m] = values
        n += m
    if n != info.point_count:
        raise InputError(f"{path}: truncated, read {n} of {info.point_count} points")
    if not np.isfinite(xyz).all():  # the flat check is far cheaper than counting bad rows
        bad = ~np.isfinite(xyz).all(axis=1)
        raise InputError(f"{path}: {int(bad.sum())} points have NaN or infinite coordinates")
    if n < min_points:
        raise InputError(f"{path}: only {n} points, at least {min_points} needed")
    return PointCloud(xyz, attrs, info.crs)


# ---------------------------------------------------------------- E57 / PLY

# Input scale of the LAS records made from E57/PLY points for merge (which works on stored
# integers): 0.1 mm, ten times finer than merge's output, so the extra rounding is negligible.
OTHER_SCALE = 1e-4
_OTHER_INFO: dict[tuple[str, int, int], HeaderInfo] = {}


def _read_other(path: Path, attributes: bool | Iterable[str], min_points: int) -> PointCloud:
    """E57 / PLY: the chunks copied into arrays of the record count, cut to the valid points."""
    count = (
        e57.resolve_scan(path)[1].point_count
        if file_format(path) == "e57"
        else ply.point_count(path)
    )
    xyz = np.empty((count, 3), dtype=np.float64)
    attrs: dict[str, np.ndarray] = {}
    n = 0
    for chunk in iter_chunks(path, attributes=attributes):
        m = len(chunk)
        if n + m > count:
            raise InputError(f"{path}: holds more points than its header says ({count})")
        xyz[n : n + m] = chunk.xyz
        for name, values in chunk.attrs.items():
            if name not in attrs:
                attrs[name] = np.empty(count, dtype=values.dtype)
            attrs[name][n : n + m] = values
        n += m
    if n == 0:
        raise InputError(f"{path}: contains no valid points")
    if n < count:  # invalid points dropped: copy, so the cut-off rows are freed
        xyz, attrs = xyz[:n].copy(), {k: v[:n].copy() for k, v in attrs.items()}
    if not np.isfinite(xyz).all():
        bad = ~np.isfinite(xyz).all(axis=1)
        raise InputError(f"{path}: {int(bad.sum())} points have NaN or infinite coordinates")
    if n < min_points:
        raise InputError(f"{path}: only {n} points, at least {min_points} needed")
    return PointCloud(xyz, attrs, None)


def _other_header_info(path: Path) -> HeaderInfo:
    """HeaderInfo of an E57 scan or a PLY file; bounds from the file (E57) or one streamed pass."""
    fmt = file_format(path)
    if fmt == "e57":
        file, scan = e57.resolve_scan(path)
        # cartesianBounds are in the scan frame by the standard, but some writers (pye57) store
        # them posed: trusted only where both frames agree (no pose, or identity)
        trusted = scan.pose is None or np.allclose(scan.pose, np.eye(4))
        bounds = scan.bounds if trusted else None
        count, names, version = scan.point_count, e57.attribute_names(scan), "E57"
        if count == 0:
            raise InputError(f"{file}: {scan.label}: contains no points")
    else:
        file = path
        count, names, bounds, version = (
            ply.point_count(path),
            ply.attribute_names(path),
            None,
            "PLY",
        )
    st = file.stat()
    memo = (str(path), st.st_mtime_ns, st.st_size)
    if memo in _OTHER_INFO:
        return _OTHER_INFO[memo]
    # a partial: pickles
    box = bounds if bounds is not None else partial(_streamed_bounds, str(path))
    info = HeaderInfo(path, count, -1, version, box, None, ("X", "Y", "Z", *names))
    _OTHER_INFO[memo] = info
    return info


def _streamed_bounds(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the valid points, from one pass over the file."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for chunk in iter_chunks(path, attributes=False):
        if len(chunk):
            lo, hi = np.minimum(lo, chunk.xyz.min(axis=0)), np.maximum(hi, chunk.xyz.max(axis=0))
    return (lo, hi) if np.isfinite(lo).all() else (np.zeros(3), np.zeros(3))


class CloudRecordReader:
    """An E57/PLY file seen as a laspy reader: a LAS 1.4 header and LAS point records per chunk."""

    def __init__(self, path: Path):
        self.path = path
        self.info = read_header_info(path)
        attrs = [n for n in self.info.dimensions if n not in ("X", "Y", "Z")]
        self.extra = {}
        # the extra attributes' dtypes, from one point
        for chunk in iter_chunks(path, chunk_size=1):
            self.extra = {
                n: v.dtype for n, v in chunk.attrs.items() if n not in STANDARD_ATTRIBUTES
            }
            break
        # nominal header (fields, extra dims); each chunk's records carry their own offsets
        self.header = make_header(attrs, self.extra, None, np.zeros(3), OTHER_SCALE)

    def __enter__(self) -> CloudRecordReader:
        return self

    def __exit__(self, *exc) -> None:
        return None

    def close(self) -> None:
        return None

    def chunk_iterator(self, chunk_size: int) -> Iterator[laspy.ScaleAwarePointRecord]:
        for chunk in iter_chunks(self.path, chunk_size):
            if not len(chunk):
                continue
            # offsets per chunk: stored bounds (cartesianBounds) need not hold the points
            header = make_header(
                chunk.attrs.keys(),
                self.extra,
                None,
                las_offsets(chunk.xyz.min(axis=0)),
                OTHER_SCALE,
            )
            yield make_record(header, chunk.xyz, chunk.attrs)

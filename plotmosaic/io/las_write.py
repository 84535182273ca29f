"""LAS/LAZ 1.4 writing with laspy: headers, point records and whole clouds (written atomically).

Records are also how merge and the E57/PLY readers hand points to laspy (io/las.py).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS

from plotmosaic.config.merge import CHUNK_SIZE
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import atomic_output
from plotmosaic.io.cloud import RGB, STANDARD_ATTRIBUTES, PointCloud


def las_offsets(mins: np.ndarray) -> np.ndarray:
    """Offsets rounded down to 1 km: int32 at 1 mm then spans +-2000 km around them."""
    return np.floor(np.asarray(mins, dtype=np.float64) / 1000.0) * 1000.0


def make_header(
    attribute_names: Iterable[str],
    extra_dims: dict[str, np.dtype] | None = None,
    crs: CRS | None = None,
    offsets: np.ndarray | None = None,
    scale: float = 0.001,
) -> laspy.LasHeader:
    """A LAS 1.4 header (PF 6, or 7 when RGB is present) for the given attributes."""
    names = set(attribute_names)
    point_format = 7 if all(c in names for c in RGB) else 6
    header = laspy.LasHeader(point_format=point_format, version="1.4")
    header.scales = np.array([scale, scale, scale])
    header.offsets = np.zeros(3) if offsets is None else np.asarray(offsets, dtype=np.float64)
    for name, dtype in (extra_dims or {}).items():
        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=np.dtype(dtype)))
    if crs is not None:
        header.add_crs(CRS.from_user_input(crs))
    return header


def make_record(
    header: laspy.LasHeader, xyz: np.ndarray, attrs: dict[str, np.ndarray]
) -> laspy.ScaleAwarePointRecord:
    """Points for `header` from float64 xyz and attribute arrays (unknown attributes are dropped)."""
    record = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=header)
    xyz = np.asarray(xyz, dtype=np.float64)
    span = np.abs(xyz - header.offsets).max(axis=0) / header.scales if len(xyz) else np.zeros(3)
    if np.any(span >= 2**31 - 1):
        raise InputError("coordinates do not fit the LAS integer range at this scale/offset")
    record.x, record.y, record.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    dims = set(header.point_format.dimension_names)
    for name, values in attrs.items():
        if name in dims:
            record[name] = values
    return record


def _extra_dims(cloud: PointCloud) -> dict[str, np.dtype]:
    return {n: v.dtype for n, v in cloud.attrs.items() if n not in STANDARD_ATTRIBUTES}


def write_cloud(
    path: str | Path,
    cloud: PointCloud,
    crs: CRS | None = None,
    scale: float = 0.001,
    force: bool = True,
    chunk_size: int = CHUNK_SIZE,
) -> Path:
    """Write a cloud as LAS/LAZ 1.4 (compression from the suffix), atomically."""
    path = Path(path)
    if path.suffix.lower() not in (".las", ".laz"):
        raise InputError(f"{path}: output must end in .las or .laz")
    if len(cloud) and not np.isfinite(cloud.xyz).all():
        raise InputError(f"{path}: refusing to write NaN or infinite coordinates")
    crs = crs if crs is not None else cloud.crs
    mins = cloud.xyz.min(axis=0) if len(cloud) else np.zeros(3)
    header = make_header(cloud.attrs.keys(), _extra_dims(cloud), crs, las_offsets(mins), scale)
    with atomic_output(path, force=force) as tmp:
        with laspy.open(
            tmp, mode="w", header=header, do_compress=path.suffix.lower() == ".laz"
        ) as writer:
            for start in range(0, len(cloud), chunk_size):
                part = slice(start, start + chunk_size)
                writer.write_points(
                    make_record(
                        header, cloud.xyz[part], {k: v[part] for k, v in cloud.attrs.items()}
                    )
                )
    return path

"""E57 (ASTM E2807) input with pye57's libE57Format bindings: scans, stored poses, chunked points.

Points are returned in the scan's own frame (the stored pose is *not* applied): registration
finds the poses, and the stored one is only offered as a prior (`stored_pose`), since many
exports store identity. Coordinates come out as float64 whatever the file stores (float,
double or scaled integers: libE57 converts), spherical scans are converted to cartesian,
and points flagged invalid (missing returns) are dropped. Intensity and colour are mapped to
the LAS names and ranges (uint16) that merge writes. The header (XML) side is io/e57_header.py.

A manifest names one scan of a multi-scan file as the reference path `FILE.e57#INDEX`
(`scan_ref`), so every reader of a path (`io.las.read_cloud`, `iter_chunks`, ...) gets it.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.errors import InputError, short_error
from plotmosaic.io.e57_header import (
    E57Scan,
    describe,
    field_range,
    libe57,
    limits,
    open_file,
    scan_nodes,
)

CHUNK_SIZE = 1_000_000
_REF = re.compile(r"^(?P<file>.*\.e57)#(?P<index>\d+)$", re.IGNORECASE)
_XYZ = ("cartesianX", "cartesianY", "cartesianZ")
_RAE = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
_RGB = {"colorRed": "red", "colorGreen": "green", "colorBlue": "blue"}
_NORMALS = {"nor:normalX": "normal_x", "nor:normalY": "normal_y", "nor:normalZ": "normal_z"}
_LAS_NAMES = {"intensity": "intensity", **_RGB, **_NORMALS}  # E57 field -> LAS attribute


def is_e57(path: str | Path) -> bool:
    return split_scan_ref(path)[0].suffix.lower() == ".e57"


def scan_ref(path: str | Path, index: int) -> Path:
    """The reference path naming scan `index` of an E57 file (what manifests resolve to)."""
    return Path(f"{Path(path)}#{int(index)}")


def split_scan_ref(path: str | Path) -> tuple[Path, int | None]:
    """(file, scan index) of a reference path; (path, None) for a plain path."""
    m = _REF.match(str(path))
    if m and not Path(path).exists():
        return Path(m["file"]), int(m["index"])
    return Path(path), None


def list_scans(path: str | Path) -> list[E57Scan]:
    """Every scan of an E57 file, from its XML section (no points read)."""
    path = Path(path)
    imf = open_file(path)
    try:
        scans = []
        for i, node in enumerate(scan_nodes(imf, path)):
            try:
                scans.append(describe(node, i))
            except Exception as exc:
                raise InputError(
                    f"{path}: scan {i}: unreadable header ({short_error(exc)})"
                ) from None
        return scans
    finally:
        imf.close()


def scan_list_text(scans: list[E57Scan]) -> str:
    return ", ".join(f"{s.index} {s.name!r}" if s.name else str(s.index) for s in scans)


def select_scan(
    path: str | Path, selector: int | str | None, scans: list[E57Scan] | None = None
) -> E57Scan:
    """The scan a manifest means: an index, a name or GUID, or (None) the only scan of the file."""
    path = Path(path)
    scans = list_scans(path) if scans is None else scans
    if not scans:
        raise InputError(f"{path}: holds no scans")
    if selector is None:
        if len(scans) > 1:
            listing = scan_list_text(scans)
            raise InputError(
                f"{path}: holds {len(scans)} scans, say which with `scan = INDEX or NAME` ({listing})"
            )
        return scans[0]
    if isinstance(selector, int):
        if not 0 <= selector < len(scans):
            raise InputError(
                f"{path}: no scan {selector} (0-based; the file holds {len(scans)}: {scan_list_text(scans)})"
            )
        return scans[selector]
    found = [s for s in scans if selector in (s.name, s.guid)]
    if len(found) != 1:
        why = "no" if not found else f"{len(found)} scans named"
        raise InputError(f"{path}: {why} scan {selector!r} (scans: {scan_list_text(scans)})")
    return found[0]


def resolve_scan(path: str | Path) -> tuple[Path, E57Scan]:
    """The file and the scan a path or reference path names (a plain path: the only scan)."""
    file, index = split_scan_ref(path)
    return file, select_scan(file, index)


def stored_pose(path: str | Path, scan: int | str | None = None) -> np.ndarray | None:
    """The scan's stored pose (4x4, scan frame -> file frame), None when the file stores none."""
    file, index = split_scan_ref(path)
    chosen = select_scan(file, index if scan is None else scan)
    if chosen.pose_problem:
        raise InputError(f"{file}: {chosen.label}: unusable stored pose ({chosen.pose_problem})")
    return chosen.pose


def _wanted(fields: tuple[str, ...], attributes: bool | Iterable[str]) -> list[str]:
    """E57 fields to read besides the coordinates, for the LAS attribute names asked for."""
    present = [f for f in _LAS_NAMES if f in fields]
    if attributes is True:
        return present
    if attributes is False:
        return []
    names = set(attributes)
    return [f for f in present if _LAS_NAMES[f] in names]


def attribute_names(scan: E57Scan) -> list[str]:
    """The LAS attribute names a read of this scan yields."""
    return [_LAS_NAMES[f] for f in _wanted(scan.fields, True)]


def _to_uint16(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Values mapped from [lo, hi] to the LAS range 0..65535; NaN (flagged invalid) becomes 0."""
    scaled = (np.asarray(values, dtype=np.float64) - lo) * (65535.0 / (hi - lo))
    return np.nan_to_num(np.clip(np.rint(scaled), 0, 65535), nan=0.0).astype(np.uint16)


@dataclass(frozen=True)
class _Fields:
    """What a read of one scan's points fetches, and how each field becomes a LAS value."""

    coords: tuple[str, str, str]  # _XYZ or _RAE
    state: str  # the invalid-state field of those coordinates (read when the scan has it)
    extra: list[str]  # intensity / colour / normal fields
    flags: dict[str, str]  # field -> its per-point "no value" flag (such values are written as 0)
    ranges: dict[str, tuple[float, float]]  # intensity / colour field -> what maps to 0..65535


def _fields(where: str, scan: E57Scan, node, proto, attributes: bool | Iterable[str]) -> _Fields:
    if all(f in scan.fields for f in _XYZ):
        coords, state = _XYZ, "cartesianInvalidState"
    elif all(f in scan.fields for f in _RAE):
        coords, state = _RAE, "sphericalInvalidState"
    else:
        raise InputError(
            f"{where}: neither cartesian nor spherical coordinates (fields: {', '.join(scan.fields)})"
        )
    extra = _wanted(scan.fields, attributes)
    flags = {
        f: flag
        for f, flag in (("intensity", "isIntensityInvalid"), ("colorRed", "isColorInvalid"))
        if f in extra and flag in scan.fields
    }
    if "colorRed" in flags:
        flags.update({"colorGreen": "isColorInvalid", "colorBlue": "isColorInvalid"})
    ranges = {}
    if "intensity" in extra:
        ranges["intensity"] = limits(
            node,
            "intensityLimits",
            "intensityMinimum",
            "intensityMaximum",
            field_range(proto, "intensity"),
        )
    for f in _RGB:
        if f in extra:
            ranges[f] = limits(
                node, "colorLimits", f"{f}Minimum", f"{f}Maximum", field_range(proto, f)
            )
    return _Fields(coords=coords, state=state, extra=extra, flags=flags, ranges=ranges)


def _buffers(fields: _Fields, scan: E57Scan, n: int) -> dict[str, np.ndarray]:
    """The arrays libE57 reads a block of `n` points into, one per field."""
    arrays = {f: np.empty(n, np.float64) for f in fields.coords}
    arrays.update({f: np.empty(n, np.float64) for f in fields.extra})
    if fields.state in scan.fields:
        arrays[fields.state] = np.empty(n, np.int8)
    for flag in set(fields.flags.values()):
        arrays[flag] = np.empty(n, np.int8)
    return arrays


def _block(
    fields: _Fields, arrays: dict[str, np.ndarray], got: int
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The valid points of the `got` just read: xyz (cartesian) and LAS attributes."""
    keep = slice(0, got)
    state = fields.state
    valid = arrays[state][keep] == 0 if state in arrays else np.ones(got, bool)
    c = [arrays[f][keep][valid] for f in fields.coords]
    # E57 spherical: azimuth from +x towards +y, elevation from the xy plane
    if fields.coords is _RAE:
        r, az, el = c
        c = [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    attrs = {}
    for f in fields.extra:
        v = arrays[f][keep][valid]
        if f in fields.flags:
            v = np.where(arrays[fields.flags[f]][keep][valid] != 0, np.nan, v)
        if f == "intensity":
            attrs["intensity"] = _to_uint16(v, *fields.ranges["intensity"])
        elif f in _RGB:
            attrs[_RGB[f]] = _to_uint16(v, *fields.ranges[f])
        else:
            attrs[_NORMALS[f]] = v.astype(np.float32)
    return np.column_stack(c), attrs


def iter_e57_chunks(
    path: str | Path, chunk_size: int = CHUNK_SIZE, attributes: bool | Iterable[str] = True
) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """Yield one scan's valid points as (xyz float64, attributes) blocks (scan frame), reading block by block."""
    lib = libe57()
    file, index = split_scan_ref(path)
    imf = open_file(file)
    try:
        nodes = scan_nodes(imf, file)
        scan = select_scan(file, index, [describe(n, i) for i, n in enumerate(nodes)])
        node = nodes[scan.index]
        where = f"{file}: {scan.label}"
        if scan.point_count == 0:
            raise InputError(f"{where}: contains no points")
        points = lib.CompressedVectorNode(node.get("points"))
        proto = lib.StructureNode(points.prototype())
        fields = _fields(where, scan, node, proto, attributes)
        n = max(1, min(chunk_size, scan.point_count))
        arrays = _buffers(fields, scan, n)
        buffers = lib.VectorSourceDestBuffer()
        for name, array in arrays.items():
            buffers.append(lib.SourceDestBuffer(imf, name, array, n, True, True))
        try:
            reader = points.reader(buffers)
        except Exception as exc:
            raise InputError(f"{where}: unreadable point data ({short_error(exc)})") from None
        try:
            while True:
                try:
                    got = reader.read()
                except Exception as exc:
                    raise InputError(
                        f"{where}: corrupt or truncated point data ({short_error(exc)})"
                    ) from None
                if got == 0:
                    break
                yield _block(fields, arrays, got)
        finally:
            reader.close()
    finally:
        imf.close()

"""E57 (ASTM E2807) input with pye57's libE57Format bindings: scans, stored poses, chunked points.

Points are returned in the scan's own frame (the stored pose is *not* applied): registration
finds the poses, and the stored one is only offered as a prior (`stored_pose`), since many
exports store identity. Coordinates come out as float64 whatever the file stores (float,
double or scaled integers: libE57 converts), spherical scans are converted to cartesian,
and points flagged invalid (missing returns) are dropped. Intensity and colour are mapped to
the LAS names and ranges (uint16) that merge writes.

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
from plotmosaic.io.paths import check_input_file

CHUNK_SIZE = 1_000_000
_REF = re.compile(r"^(?P<file>.*\.e57)#(?P<index>\d+)$", re.IGNORECASE)
_XYZ = ("cartesianX", "cartesianY", "cartesianZ")
_RAE = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
_RGB = {"colorRed": "red", "colorGreen": "green", "colorBlue": "blue"}
_NORMALS = {"nor:normalX": "normal_x", "nor:normalY": "normal_y", "nor:normalZ": "normal_z"}


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


@dataclass(frozen=True)
class E57Scan:
    """One scan of an E57 file, as its header describes it."""

    index: int
    name: str | None
    guid: str | None
    point_count: int
    fields: tuple[str, ...]
    pose: np.ndarray | None  # 4x4 scan -> file frame, None when the file stores none
    bounds: tuple[np.ndarray, np.ndarray] | None  # cartesianBounds (scan frame), when stored
    pose_problem: str | None = (
        None  # why a stored pose was unusable (an error only where the pose is used)
    )

    @property
    def label(self) -> str:
        return f"scan {self.index}" + (f" ({self.name!r})" if self.name else "")


def _libe57():
    from pye57 import libe57  # deferred: the C++ library loads only when an E57 file is read

    return libe57


def _open(path: Path):
    libe57 = _libe57()
    check_input_file(path, "E57 file")
    try:
        return libe57.ImageFile(str(path), "r")
    except Exception as exc:  # libE57 raises E57Exception (bad checksum, bad header, ...)
        raise InputError(f"{path}: not a readable E57 file ({short_error(exc)})") from None


def _number(node) -> float:
    """The value of an E57 numeric node (float, integer or scaled integer)."""
    libe57 = _libe57()
    for cast, getter in (
        (libe57.FloatNode, "value"),
        (libe57.ScaledIntegerNode, "scaledValue"),
        (libe57.IntegerNode, "value"),
    ):
        try:
            return float(getattr(cast(node), getter)())
        except Exception:
            continue
    raise ValueError(f"{node.pathName()}: not a number")


def _child(node, name: str):
    return node.get(name) if node.isDefined(name) else None


def _string(node, name: str) -> str | None:
    child = _child(node, name)
    return None if child is None else str(_libe57().StringNode(child).value())


def _pose(node) -> np.ndarray | None:
    """4x4 from the scan's pose (unit quaternion w, x, y, z + translation); None when absent."""
    pose = _child(node, "pose")
    if pose is None:
        return None
    pose = _libe57().StructureNode(pose)
    T = np.eye(4)
    rot = _child(pose, "rotation")
    if rot is not None:
        rot = _libe57().StructureNode(rot)
        w, x, y, z = (_number(rot.get(k)) for k in ("w", "x", "y", "z"))
        q = np.array([w, x, y, z])
        norm = np.linalg.norm(q)
        if not np.isfinite(norm) or abs(norm - 1.0) > 1e-3:
            raise ValueError(f"rotation quaternion is not a unit quaternion (norm {norm:.6g})")
        w, x, y, z = q / norm
        T[:3, :3] = [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    tr = _child(pose, "translation")
    if tr is not None:
        tr = _libe57().StructureNode(tr)
        T[:3, 3] = [_number(tr.get(k)) for k in ("x", "y", "z")]
    if not np.isfinite(T).all():
        raise ValueError("pose is not finite")
    return T


def _bounds(node) -> tuple[np.ndarray, np.ndarray] | None:
    b = _child(node, "cartesianBounds")
    if b is None:
        return None
    b = _libe57().StructureNode(b)
    try:
        lo = np.array([_number(b.get(f"{a}Minimum")) for a in "xyz"])
        hi = np.array([_number(b.get(f"{a}Maximum")) for a in "xyz"])
    except Exception:
        return None
    ok = np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()
    return (lo, hi) if ok else None


def _scan_nodes(imf, path: Path) -> list:
    libe57 = _libe57()
    root = imf.root()
    if not root.isDefined("data3D"):
        return []
    data3d = libe57.VectorNode(root.get("data3D"))
    return [libe57.StructureNode(data3d.get(i)) for i in range(data3d.childCount())]


def _describe(node, index: int) -> E57Scan:
    libe57 = _libe57()
    points = libe57.CompressedVectorNode(node.get("points"))
    proto = libe57.StructureNode(points.prototype())
    fields = tuple(proto.get(i).elementName() for i in range(proto.childCount()))
    try:
        pose, problem = _pose(node), None
    except Exception as exc:  # the points are still usable: registration does not need the pose
        pose, problem = None, short_error(exc)
    return E57Scan(
        index,
        _string(node, "name"),
        _string(node, "guid"),
        int(points.childCount()),
        fields,
        pose,
        _bounds(node),
        problem,
    )


def list_scans(path: str | Path) -> list[E57Scan]:
    """Every scan of an E57 file, from its XML section (no points read)."""
    path = Path(path)
    imf = _open(path)
    try:
        scans = []
        for i, node in enumerate(_scan_nodes(imf, path)):
            try:
                scans.append(_describe(node, i))
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
    las_names = {"intensity": "intensity", **_RGB, **_NORMALS}
    present = [f for f in las_names if f in fields]
    if attributes is True:
        return present
    if attributes is False:
        return []
    names = set(attributes)
    return [f for f in present if las_names[f] in names]


def attribute_names(scan: E57Scan) -> list[str]:
    """The LAS attribute names a read of this scan yields."""
    las_names = {"intensity": "intensity", **_RGB, **_NORMALS}
    return [las_names[f] for f in _wanted(scan.fields, True)]


def _limits(
    node, group: str, lo_name: str, hi_name: str, default: tuple[float, float]
) -> tuple[float, float]:
    g = _child(node, group)
    if g is not None:
        g = _libe57().StructureNode(g)
        try:
            lo, hi = _number(g.get(lo_name)), _number(g.get(hi_name))
            if np.isfinite(lo) and np.isfinite(hi) and hi > lo:
                return lo, hi
        except Exception:
            pass
    return default


def _field_range(proto, name: str) -> tuple[float, float]:
    """The value range a field's prototype declares (what the limits default to)."""
    libe57 = _libe57()
    node = proto.get(name)
    for cast, lo, hi in (
        (libe57.ScaledIntegerNode, "scaledMinimum", "scaledMaximum"),
        (libe57.IntegerNode, "minimum", "maximum"),
        (libe57.FloatNode, "minimum", "maximum"),
    ):
        try:
            n = cast(node)
            a, b = float(getattr(n, lo)()), float(getattr(n, hi)())
            if np.isfinite(a) and np.isfinite(b) and b > a:
                return a, b
        except Exception:
            continue
    return 0.0, 1.0


def _to_uint16(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Values mapped from [lo, hi] to the LAS range 0..65535; NaN (flagged invalid) becomes 0."""
    scaled = (np.asarray(values, dtype=np.float64) - lo) * (65535.0 / (hi - lo))
    return np.nan_to_num(np.clip(np.rint(scaled), 0, 65535), nan=0.0).astype(np.uint16)


def iter_e57_chunks(
    path: str | Path, chunk_size: int = CHUNK_SIZE, attributes: bool | Iterable[str] = True
) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """Yield one scan's valid points as (xyz float64, attributes) blocks (scan frame), reading block by block."""
    libe57 = _libe57()
    file, index = split_scan_ref(path)
    imf = _open(file)
    try:
        nodes = _scan_nodes(imf, file)
        scan = select_scan(file, index, [_describe(n, i) for i, n in enumerate(nodes)])
        node = nodes[scan.index]
        where = f"{file}: {scan.label}"
        if scan.point_count == 0:
            raise InputError(f"{where}: contains no points")
        points = libe57.CompressedVectorNode(node.get("points"))
        proto = libe57.StructureNode(points.prototype())
        if all(f in scan.fields for f in _XYZ):
            coords, state = _XYZ, "cartesianInvalidState"
        elif all(f in scan.fields for f in _RAE):
            coords, state = _RAE, "sphericalInvalidState"
        else:
            raise InputError(
                f"{where}: neither cartesian nor spherical coordinates (fields: {', '.join(scan.fields)})"
            )
        extra = _wanted(scan.fields, attributes)
        n = max(1, min(chunk_size, scan.point_count))
        arrays = {f: np.empty(n, np.float64) for f in coords}
        arrays.update({f: np.empty(n, np.float64) for f in extra})
        if state in scan.fields:
            arrays[state] = np.empty(n, np.int8)
        # per-point "no value" flags of intensity / colour: such values are written as 0
        flags = {
            f: flag
            for f, flag in (("intensity", "isIntensityInvalid"), ("colorRed", "isColorInvalid"))
            if f in extra and flag in scan.fields
        }
        if "colorRed" in flags:
            flags.update({"colorGreen": "isColorInvalid", "colorBlue": "isColorInvalid"})
        for flag in set(flags.values()):
            arrays[flag] = np.empty(n, np.int8)
        ilim = (
            _limits(
                node,
                "intensityLimits",
                "intensityMinimum",
                "intensityMaximum",
                _field_range(proto, "intensity"),
            )
            if "intensity" in extra
            else None
        )
        clim = {
            f: _limits(node, "colorLimits", f"{f}Minimum", f"{f}Maximum", _field_range(proto, f))
            for f in _RGB
            if f in extra
        }
        buffers = libe57.VectorSourceDestBuffer()
        for name, array in arrays.items():
            buffers.append(libe57.SourceDestBuffer(imf, name, array, n, True, True))
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
                keep = slice(0, got)
                valid = arrays[state][keep] == 0 if state in arrays else np.ones(got, bool)
                c = [arrays[f][keep][valid] for f in coords]
                if (
                    coords is _RAE
                ):  # E57 spherical: azimuth from +x towards +y, elevation from the xy plane
                    r, az, el = c
                    c = [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
                attrs = {}
                for f in extra:
                    v = arrays[f][keep][valid]
                    if f in flags:
                        v = np.where(arrays[flags[f]][keep][valid] != 0, np.nan, v)
                    if f == "intensity":
                        attrs["intensity"] = _to_uint16(v, *ilim)
                    elif f in _RGB:
                        attrs[_RGB[f]] = _to_uint16(v, *clim[f])
                    else:
                        attrs[_NORMALS[f]] = v.astype(np.float32)
                yield np.column_stack(c), attrs
        finally:
            reader.close()
    finally:
        imf.close()

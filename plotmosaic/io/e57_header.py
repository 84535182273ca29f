"""The XML section of an E57 file read with pye57's libE57Format bindings: the deferred library
load, numbers and strings of the tree, and each scan's description (`E57Scan`: fields, stored
pose, bounds) and value limits. No points are read here (io/e57.py reads them).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.errors import InputError, short_error
from plotmosaic.io.paths import check_input_file


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
    # why a stored pose was unusable (an error only where the pose is used)
    pose_problem: str | None = None

    @property
    def label(self) -> str:
        return f"scan {self.index}" + (f" ({self.name!r})" if self.name else "")


def libe57():
    from pye57 import libe57  # deferred: the C++ library loads only when an E57 file is read

    return libe57


def open_file(path: Path):
    lib = libe57()
    check_input_file(path, "E57 file")
    try:
        return lib.ImageFile(str(path), "r")
    except Exception as exc:  # libE57 raises E57Exception (bad checksum, bad header, ...)
        raise InputError(f"{path}: not a readable E57 file ({short_error(exc)})") from None


def number(node) -> float:
    """The value of an E57 numeric node (float, integer or scaled integer)."""
    lib = libe57()
    for cast, getter in (
        (lib.FloatNode, "value"),
        (lib.ScaledIntegerNode, "scaledValue"),
        (lib.IntegerNode, "value"),
    ):
        try:
            return float(getattr(cast(node), getter)())
        except Exception:
            continue
    raise ValueError(f"{node.pathName()}: not a number")


def child(node, name: str):
    return node.get(name) if node.isDefined(name) else None


def _string(node, name: str) -> str | None:
    found = child(node, name)
    return None if found is None else str(libe57().StringNode(found).value())


def _pose(node) -> np.ndarray | None:
    """4x4 from the scan's pose (unit quaternion w, x, y, z + translation); None when absent."""
    pose = child(node, "pose")
    if pose is None:
        return None
    pose = libe57().StructureNode(pose)
    T = np.eye(4)
    rot = child(pose, "rotation")
    if rot is not None:
        rot = libe57().StructureNode(rot)
        w, x, y, z = (number(rot.get(k)) for k in ("w", "x", "y", "z"))
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
    tr = child(pose, "translation")
    if tr is not None:
        tr = libe57().StructureNode(tr)
        T[:3, 3] = [number(tr.get(k)) for k in ("x", "y", "z")]
    if not np.isfinite(T).all():
        raise ValueError("pose is not finite")
    return T


def _bounds(node) -> tuple[np.ndarray, np.ndarray] | None:
    b = child(node, "cartesianBounds")
    if b is None:
        return None
    b = libe57().StructureNode(b)
    try:
        lo = np.array([number(b.get(f"{a}Minimum")) for a in "xyz"])
        hi = np.array([number(b.get(f"{a}Maximum")) for a in "xyz"])
    except Exception:
        return None
    ok = np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all()
    return (lo, hi) if ok else None


def scan_nodes(imf, path: Path) -> list:
    lib = libe57()
    root = imf.root()
    if not root.isDefined("data3D"):
        return []
    data3d = lib.VectorNode(root.get("data3D"))
    return [lib.StructureNode(data3d.get(i)) for i in range(data3d.childCount())]


def describe(node, index: int) -> E57Scan:
    lib = libe57()
    points = lib.CompressedVectorNode(node.get("points"))
    proto = lib.StructureNode(points.prototype())
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


def limits(
    node, group: str, lo_name: str, hi_name: str, default: tuple[float, float]
) -> tuple[float, float]:
    g = child(node, group)
    if g is not None:
        g = libe57().StructureNode(g)
        try:
            lo, hi = number(g.get(lo_name)), number(g.get(hi_name))
            if np.isfinite(lo) and np.isfinite(hi) and hi > lo:
                return lo, hi
        except Exception:
            pass
    return default


def field_range(proto, name: str) -> tuple[float, float]:
    """The value range a field's prototype declares (what the limits default to)."""
    lib = libe57()
    node = proto.get(name)
    for cast, lo, hi in (
        (lib.ScaledIntegerNode, "scaledMinimum", "scaledMaximum"),
        (lib.IntegerNode, "minimum", "maximum"),
        (lib.FloatNode, "minimum", "maximum"),
    ):
        try:
            n = cast(node)
            a, b = float(getattr(n, lo)()), float(getattr(n, hi)())
            if np.isfinite(a) and np.isfinite(b) and b > a:
                return a, b
        except Exception:
            continue
    return 0.0, 1.0

"""PLY input (ASCII and binary) with plyfile: the `vertex` element as float64 xyz plus attributes.

plyfile keeps every property with its own dtype (float64 coordinates and intensity included)
and memory-maps binary files, so they are handed out in chunks with bounded memory. Open3D's
legacy reader drops intensity and other properties (its tensor reader keeps them, but loads the
whole file). ASCII files are parsed whole (plyfile has no streaming ASCII parser): prefer binary
for big clouds.

Mapping: x/y/z -> xyz (float64); intensity / scalar_intensity -> LAS `intensity` (uint16; the raw
values are kept as `intensity_raw` when that is lossy); red/green/blue (also r/g/b,
diffuse_*) -> LAS uint16 colour; nx/ny/nz -> normal_x/y/z; every other scalar property is kept
as an extra attribute under its own name and dtype.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyParseError

from plotmosaic.errors import InputError, short_error
from plotmosaic.io.paths import check_input_file

CHUNK_SIZE = 2_000_000
_INTENSITY = ("intensity", "scalar_intensity", "scalar_Intensity", "Intensity")
_COLOUR = {
    "red": ("red", "r", "diffuse_red"),
    "green": ("green", "g", "diffuse_green"),
    "blue": ("blue", "b", "diffuse_blue"),
}
_NORMALS = {"nx": "normal_x", "ny": "normal_y", "nz": "normal_z"}


def _vertices(path: Path):
    """The vertex element's structured array (memory-mapped for binary files)."""
    check_input_file(path, "PLY file")
    try:
        data = PlyData.read(str(path), mmap="r")
        vertex = data["vertex"]
        array = vertex.data
    except KeyError:
        raise InputError(f"{path}: PLY file without a 'vertex' element") from None
    except Exception as exc:  # plyfile raises PlyParseError, ValueError, ... for bad headers/bodies
        raise InputError(f"{path}: not a readable PLY file ({short_error(exc)})") from None
    names = array.dtype.names or ()
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise InputError(
            f"{path}: PLY vertices lack {', '.join(missing)} (properties: {', '.join(names)})"
        )
    return array


def _vertex_header(path: Path) -> tuple[int, np.dtype]:
    """(vertex count, vertex dtype) from the header alone: an ASCII body is not parsed for them."""
    try:
        with open(path, "rb") as f:
            # plyfile 1.x; the header parser PlyData.read itself uses
            header = PlyData._parse_header(f)
        vertex = header["vertex"]
        return int(vertex.count), np.dtype(vertex.dtype())
    except (AttributeError, TypeError):  # a plyfile without that helper: read the file
        array = _vertices(path)
        return len(array), array.dtype
    except (OSError, KeyError, ValueError, PlyParseError):
        array = _vertices(path)  # raises the one-line error naming the file
        return len(array), array.dtype


def _pick(names: tuple[str, ...], options: Iterable[str]) -> str | None:
    return next((n for n in options if n in names), None)


def _layout(dtype: np.dtype) -> dict[str, str]:
    """PLY property -> attribute name for every scalar property besides x/y/z."""
    names = tuple(n for n in dtype.names if dtype[n].kind in "iuf" and dtype[n].shape == ())
    out: dict[str, str] = {}
    if (i := _pick(names, _INTENSITY)) is not None:
        out[i] = "intensity"
    colour = {las: _pick(names, opts) for las, opts in _COLOUR.items()}
    if all(colour.values()):
        out.update({ply: las for las, ply in colour.items()})
    out.update({p: n for p, n in _NORMALS.items() if p in names})
    for n in names:
        if n not in out and n not in ("x", "y", "z") and n not in out.values():
            out[n] = n
    return out


def _to_uint16(
    values: np.ndarray, full_range: tuple[float, float] | None
) -> tuple[np.ndarray, bool]:
    """LAS uint16 values and whether that was exact (uint8 is stretched by 257, floats by their range)."""
    dt = values.dtype
    if dt == np.uint16:
        return values.astype(np.uint16), True
    if dt == np.uint8:
        return values.astype(np.uint16) * np.uint16(257), True
    lo, hi = full_range if full_range is not None else (0.0, 1.0)
    if np.issubdtype(dt, np.floating) and lo >= 0.0 and hi <= 1.0:
        lo, hi = 0.0, 1.0  # normalised values
    elif lo >= 0 and hi <= 65535 and np.issubdtype(dt, np.integer):
        return values.astype(np.uint16), True
    span = hi - lo if hi > lo else 1.0
    scaled = (values.astype(np.float64) - lo) * (65535.0 / span)
    return np.clip(np.rint(scaled), 0, 65535).astype(np.uint16), False


def attribute_names(path: str | Path) -> list[str]:
    """The attribute names a read of this file yields (for headers)."""
    dtype = _vertex_header(Path(path))[1]
    layout = _layout(dtype)
    names = list(layout.values())
    i = next((p for p, a in layout.items() if a == "intensity"), None)
    if i is not None and dtype[i] not in (np.uint16, np.uint8):
        names.append("intensity_raw")
    return names


def point_count(path: str | Path) -> int:
    """The vertex count the header gives."""
    return _vertex_header(Path(path))[0]


def iter_ply_chunks(
    path: str | Path, chunk_size: int = CHUNK_SIZE, attributes: bool | Iterable[str] = True
) -> Iterator[tuple[np.ndarray, dict[str, np.ndarray]]]:
    """Yield the vertices as (xyz float64, attributes) blocks of at most `chunk_size` points."""
    path = Path(path)
    array = _vertices(path)
    if len(array) == 0:
        raise InputError(f"{path}: contains no points")
    layout = _layout(array.dtype)
    if attributes is False:
        layout = {}
    elif attributes is not True:
        wanted = set(attributes)
        layout = {
            p: a
            for p, a in layout.items()
            if a in wanted or (a == "intensity" and "intensity_raw" in wanted)
        }
    ranges = {}
    for ply, las in layout.items():  # one whole-column pass, so every chunk maps values alike
        if las in ("intensity", "red", "green", "blue") and array.dtype[ply] not in (
            np.uint8,
            np.uint16,
        ):
            col = np.asarray(array[ply])
            ranges[ply] = (float(np.nanmin(col)), float(np.nanmax(col)))
    try:
        for start in range(0, len(array), chunk_size):
            part = array[start : start + chunk_size]
            xyz = np.column_stack([np.asarray(part[c], dtype=np.float64) for c in "xyz"])
            attrs: dict[str, np.ndarray] = {}
            for ply, las in layout.items():
                values = np.array(part[ply])
                if las in ("intensity", "red", "green", "blue"):
                    attrs[las], exact = _to_uint16(values, ranges.get(ply))
                    if las == "intensity" and not exact:
                        attrs["intensity_raw"] = values
                else:
                    attrs[las] = values
            yield xyz, attrs
    except InputError:
        raise
    except Exception as exc:  # a truncated binary body surfaces when the map is read
        raise InputError(f"{path}: corrupt or truncated PLY data ({short_error(exc)})") from None

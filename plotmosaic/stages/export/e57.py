"""One E57 file holding every scan in its own frame with its pose (pye57's writer).

Each scan's pose block is the unit quaternion (w, x, y, z) and translation of the pose merge
applies, so a reader that applies E57 poses (CloudCompare, Cyclone, RiSCAN, pye57) gets the merged
cloud. E57 stores a scan's points as float32 here (pye57 writes single precision): a scan whose own
coordinates lie more than 500 m from the origin is stored about its centre rounded to 1 km, that
shift folded into its pose, so its points keep sub-millimetre precision; scans in their scanner's
frame (the usual case) are stored as they are, with the pose unchanged.

Memory stays bounded: a scan is streamed chunk by chunk into memory-mapped spill files beside the
output, which pye57 writes from in its own blocks. Intensity is written as stored, LAS 16-bit
colour as 8-bit (the high byte).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from plotmosaic.config.merge import CHUNK_SIZE
from plotmosaic.io.atomic import atomic_output, temp_folder
from plotmosaic.io.frame import translation
from plotmosaic.io.las import RGB, iter_chunks
from plotmosaic.stages.export.plan import Advance, ExportPlan
from plotmosaic.stages.merge.plan import Source

LOCAL_ORIGIN_STEP = 1000.0  # m: a scan is stored about its centre rounded to this


@dataclass(frozen=True, kw_only=True)
class E57Pose:
    """A scan's pose as E57 writes it, and the shift of its stored points."""

    quaternion: np.ndarray  # w, x, y, z
    translation: np.ndarray
    origin: np.ndarray  # subtracted from the scan's coordinates before they are stored


def e57_pose(source: Source) -> E57Pose:
    centre = (source.info.mins + source.info.maxs) / 2
    origin = np.round(centre / LOCAL_ORIGIN_STEP) * LOCAL_ORIGIN_STEP
    T = np.asarray(source.transform, dtype=np.float64) @ translation(origin)
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat()
    q = np.array([w, x, y, z])
    return E57Pose(quaternion=q if w >= 0 else -q, translation=T[:3, 3].copy(), origin=origin)


def _spill(
    source: Source, origin: np.ndarray, folder: Path, advance: Advance | None
) -> dict[str, np.ndarray]:
    """The scan's fields as pye57 names them, in memory-mapped files (the valid points only)."""
    n = source.info.point_count
    names = [a for a in ("intensity", *RGB) if a in source.info.dimensions]
    colour = all(c in names for c in RGB)
    fields = {"cartesianX": "f8", "cartesianY": "f8", "cartesianZ": "f8"}
    if "intensity" in names:
        fields["intensity"] = "f4"
    if colour:
        fields |= {"colorRed": "u1", "colorGreen": "u1", "colorBlue": "u1"}
    maps = {
        f: np.lib.format.open_memmap(folder / f"{f}.npy", mode="w+", dtype=t, shape=(max(n, 1),))
        for f, t in fields.items()
    }
    m = 0
    for chunk in iter_chunks(source.path, CHUNK_SIZE, attributes=names):
        k, xyz = len(chunk), chunk.xyz - origin
        for axis, f in enumerate(("cartesianX", "cartesianY", "cartesianZ")):
            maps[f][m : m + k] = xyz[:, axis]
        if "intensity" in fields:
            maps["intensity"][m : m + k] = chunk.attrs["intensity"]
        if colour:
            for c, f in zip(RGB, ("colorRed", "colorGreen", "colorBlue")):
                maps[f][m : m + k] = np.asarray(chunk.attrs[c], dtype=np.uint16) >> 8
        m += k
        if advance is not None:
            advance(k, source.id)
    return {f: a[:m] for f, a in maps.items()}


def write_e57(plan: ExportPlan, out: Path, advance: Advance | None = None) -> list[tuple[str, int]]:
    """Every scan of the plan into one E57 at `out` (atomically); (scan id, points) written."""
    import pye57  # deferred: the C++ library loads only when an E57 is written

    written = []
    with atomic_output(out, force=True) as tmp, temp_folder(out, ".spill") as folder:
        e57 = pye57.E57(str(tmp), mode="w")
        try:
            for s in plan.scans:
                pose = e57_pose(s)
                data = _spill(s, pose.origin, folder, advance)
                if len(data["cartesianX"]):
                    e57.write_scan_raw(
                        data, name=s.id, rotation=pose.quaternion, translation=pose.translation
                    )
                written.append((s.id, len(data["cartesianX"])))
                del data
                for f in folder.iterdir():
                    f.unlink()
        finally:
            e57.close()
    return written

"""A PDAL pipeline (JSON) that does what `merge` does: each scan read, posed with its matrix, given
its point_source_id, then all of them merged into one LAS 1.4 (or COPC) file with merge's scale,
offset, point format and CRS.

Stages, in order: per source `readers.las` (`readers.ply`) -> `filters.transformation` (the pose,
16 numbers row-major, float64 in full) -> `filters.assign` (PointSourceId); then `filters.merge`
-> `writers.las` (or `writers.copc` for a `.copc.laz` cloud). Every stage has a tag and names its
inputs. An E57 scan has no PDAL reader that picks one scan as merge reads it: it is refused.
"""

from __future__ import annotations

import json
from pathlib import Path

from plotmosaic.errors import InputError
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.las import file_format
from plotmosaic.stages.export.plan import ExportPlan
from plotmosaic.stages.merge.plan import Source, build_header, output_bounds

READERS = {"las": "readers.las", "ply": "readers.ply"}


def is_copc(path: Path) -> bool:
    return path.name.lower().endswith(".copc.laz")


def _reader(source: Source) -> dict:
    fmt = file_format(source.path)
    if fmt not in READERS:
        raise InputError(
            f"{source.path}: scan {source.id!r} is in an E57 file, which no PDAL reader reads scan "
            "by scan as merge does; export --to e57 or merge it instead"
        )
    return {
        "type": READERS[fmt],
        "filename": str(source.path.resolve()),
        "tag": f"read_{source.source_id}",
    }


def matrix_option(T) -> str:
    """filters.transformation's `matrix`: 16 numbers, row-major, in their shortest exact form."""
    return " ".join(repr(float(v)) for v in T.reshape(-1))


def pipeline(plan: ExportPlan, cloud: Path) -> dict:
    """The pipeline writing `cloud` from the plan's sources."""
    header = build_header(list(plan.sources), plan.crs, output_bounds(list(plan.sources))[0])
    stages: list[dict] = []
    for s in plan.sources:
        stages += [
            _reader(s),
            {
                "type": "filters.transformation",
                "matrix": matrix_option(s.transform),
                "inputs": [f"read_{s.source_id}"],
                "tag": f"pose_{s.source_id}",
            },
            {
                "type": "filters.assign",
                "value": f"PointSourceId = {s.source_id}",
                "inputs": [f"pose_{s.source_id}"],
                "tag": f"source_{s.source_id}",
            },
        ]
    stages.append(
        {
            "type": "filters.merge",
            "inputs": [f"source_{s.source_id}" for s in plan.sources],
            "tag": "merged",
        }
    )
    writer = {
        "type": "writers.copc" if is_copc(cloud) else "writers.las",
        "filename": str(cloud.absolute()),
        "inputs": ["merged"],
        "tag": "write",
        **{f"scale_{a}": float(v) for a, v in zip("xyz", header.scales)},
        **{f"offset_{a}": float(v) for a, v in zip("xyz", header.offsets)},
        "extra_dims": "all",
    }
    if not is_copc(cloud):
        writer |= {"minor_version": 4, "dataformat_id": int(header.point_format.id)}
    if plan.crs is not None:
        writer["a_srs"] = plan.crs.to_wkt()
    return {"pipeline": [*stages, writer]}


def write_pipeline(plan: ExportPlan, out: Path, cloud: Path) -> Path:
    return write_text_atomic(out, json.dumps(pipeline(plan, cloud), indent=1) + "\n")

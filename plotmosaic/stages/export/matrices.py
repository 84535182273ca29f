"""Per-scan 4x4 matrices as text, in CloudCompare's convention.

One file `<scan id>.txt` per scan: 4 rows of 4 numbers, row-major, mapping the scan file's own
coordinates (as stored, before any shift a viewer applies) to the output frame, p_out = M @ p_scan
with points as columns [x, y, z, 1]; the last row is 0 0 0 1. It is the pose `merge` applies.
Numbers are float64 written in their shortest exact form (Python's repr), so a georeferenced
translation keeps every digit. `matrices.json` names the frame, CRS and the file of each scan.
"""

from __future__ import annotations

import json
from pathlib import Path

from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.matrix import matrix_text
from plotmosaic.stages.export.plan import ExportPlan

INDEX = "matrices.json"
CONVENTION = (
    "4x4, row-major, 4 rows of 4 numbers; maps the scan file's own coordinates to the output "
    "frame: p_out = M @ [x, y, z, 1]^T (CloudCompare's convention; apply to global coordinates)"
)


def matrix_file(scan_id: str) -> str:
    return f"{scan_id}.txt"


def output_names(plan: ExportPlan) -> tuple[str, ...]:
    """Every name `write_matrices` writes into its folder."""
    return (*(matrix_file(s.id) for s in plan.scans), INDEX)


def write_matrices(plan: ExportPlan, folder: Path) -> list[Path]:
    """One matrix file per scan and the index, each written atomically; the files written."""
    folder.mkdir(parents=True, exist_ok=True)
    written = [
        write_text_atomic(folder / matrix_file(s.id), matrix_text(s.transform)) for s in plan.scans
    ]
    index = {
        "convention": CONVENTION,
        "frame": plan.frame,
        "crs": plan.crs.to_wkt() if plan.crs else None,
        "crs_name": plan.crs.name if plan.crs else None,
        "poses": str(plan.poses_path) if plan.poses_path else None,
        "scans": [
            {"id": s.id, "source_id": s.source_id, "file": str(s.path), "matrix": matrix_file(s.id)}
            for s in plan.scans
        ],
        "skipped": list(plan.skipped),
    }
    written.append(write_text_atomic(folder / INDEX, json.dumps(index, indent=1)))
    return written

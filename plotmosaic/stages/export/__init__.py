"""Exports of posed scans for other tools, from the same inputs as `merge` (manifest + poses):

- `matrices`: one 4x4 text matrix per scan (CloudCompare's convention) and an index;
- `pdal`: a PDAL pipeline that reads, poses and merges the scans as merge does;
- `e57`: one E57 file with every scan in its own frame and its pose;
- `copc`: the merged cloud as COPC (an octree of LAZ chunks for streaming viewers).

Each writes atomically; what it may write and what it reads are checked by the command first.
"""

from plotmosaic.stages.export.copc import write_copc
from plotmosaic.stages.export.e57 import write_e57
from plotmosaic.stages.export.matrices import output_names, write_matrices
from plotmosaic.stages.export.pdal import write_pipeline
from plotmosaic.stages.export.plan import ExportPlan, plan_export, points_progress

FORMATS = ("matrices", "pdal", "e57", "copc")

__all__ = [
    "FORMATS",
    "ExportPlan",
    "output_names",
    "plan_export",
    "points_progress",
    "write_copc",
    "write_e57",
    "write_matrices",
    "write_pipeline",
]

"""Point-cloud input/output: LAS/LAZ (also E57 scans and PLY files on input), local frames, atomic writes."""

from plotmosaic.io.atomic import atomic_output
from plotmosaic.io.frame import Frame
from plotmosaic.io.las import (
    PointCloud,
    file_format,
    iter_chunks,
    read_cloud,
    read_header_info,
    write_cloud,
)

__all__ = [
    "Frame",
    "PointCloud",
    "atomic_output",
    "file_format",
    "iter_chunks",
    "read_cloud",
    "read_header_info",
    "write_cloud",
]

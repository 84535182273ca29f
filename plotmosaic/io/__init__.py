"""Point-cloud input/output: LAS/LAZ, local frames, atomic writes."""

from plotmosaic.io.atomic import atomic_output
from plotmosaic.io.frame import Frame
from plotmosaic.io.las import PointCloud, iter_chunks, read_cloud, read_crs, read_header_info, write_cloud

__all__ = [
    "Frame",
    "PointCloud",
    "atomic_output",
    "iter_chunks",
    "read_cloud",
    "read_crs",
    "read_header_info",
    "write_cloud",
]

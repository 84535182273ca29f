"""Point-cloud input/output: LAS/LAZ (also E57 scans and PLY files on input), local frames, atomic writes."""

from plotmosaic.io.frame import Frame
from plotmosaic.io.las import PointCloud, iter_chunks, read_cloud, write_cloud

__all__ = ["Frame", "PointCloud", "iter_chunks", "read_cloud", "write_cloud"]

"""Global coarse alignment: any heading, tens of metres, no GNSS.

  1. several vertical hypotheses per cloud (ground normals, stem normals, a robust ground fit,
     z-up when airborne or already near vertical: levelling.py), each carried into the search
     (clouds.py),
  2. generators, under every vertical pair: heading searched exhaustively and the horizontal shift
     by masked FFT correlation of forest rasters (raster.py); stem maps matched as point patterns
     (stems.py); FPFH matches with a 4-DoF vote and a 6-DoF RANSAC (fpfh.py); when the first
     vertical pair has not settled, fine height-slice occupancy correlated over heading x shift
     (slices.py: sparse ground views the 1 m rasters miss),
  3. the vertical offset of raster and stem hypotheses from the ground (clouds.py),
  4. screen every hypothesis with a short ICP, refine the best of each generator and the best
     overall with a quick robust ICP, and keep the best by how many non-flat points (stems,
     branches, crowns: flat ground matches anywhere) find a partner; the gap to the best distinct
     runner-up is the confidence (verify.py).

stage.py puts them in order. Every transform here maps source-local to target-local coordinates
(see PreparedCloud.frame).
"""

from plotmosaic.align.coarse.stage import CoarseResult, coarse_align
from plotmosaic.config.coarse import CoarseConfig

__all__ = ["CoarseConfig", "CoarseResult", "coarse_align"]

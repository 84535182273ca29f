"""Place each scan of a big plot on the ALS first, so that only neighbours are registered to each other.

Without approximate positions a plot of N scans would need N(N-1)/2 pairs. Registering each scan
to the ALS tile instead is N pairs (the coarse stage finds a scan in a whole tile): the verified
poses give positions for the neighbour selection (graph/pairs.py) and each pair's prior for the
coarse stage. These scan -> ALS runs are ordinary pairs: same pairwise path, same pair and
prepared-cloud caches. A scan that cannot be placed is simply paired with every other scan.
"""

from __future__ import annotations

import numpy as np

from plotmosaic.graph.jobs import JobSettings, PairJob, ScanFile, pair_job
from plotmosaic.io.frame import inverse
from plotmosaic.manifest import Manifest, Plot

ALS_ID = "ALS"


def placement_jobs(manifest: Manifest, plot: Plot, settings: JobSettings) -> list[PairJob]:
    """One scan -> ALS job per scan of the plot (the first ALS tile; none when the manifest has no ALS).

    `settings.prepare`: the settings the scans are prepared with (register-plot's), so the same
    prepared clouds serve the placement and the pairs."""
    if not manifest.als:
        return []
    tile = manifest.als[0]
    als = ScanFile(ALS_ID, str(manifest.resolve(tile.path)), "als", tile.k)
    return [pair_job(settings, ScanFile.of(manifest, scan), als) for scan in plot.scans]


def placed_poses(
    jobs: list[PairJob], records: dict[str, dict], min_confidence: float = 0.0
) -> dict[str, np.ndarray]:
    """scan id -> its pose in the ALS CRS (scan file -> ALS file coordinates): verified pairs at least this sure."""
    out = {}
    for j in jobs:
        r = records.get(j.key, {})
        if r.get("status") == "ok" and (
            r.get("confidence") is None or r["confidence"] >= min_confidence
        ):
            out[j.source] = np.asarray(r["transform"], dtype=np.float64)
    return out


def prior(poses: dict[str, np.ndarray], source: str, target: str) -> tuple | None:
    """source file -> target file from two placed scans (rows of a 4x4), or None when either is not placed."""
    if source not in poses or target not in poses:
        return None
    T = inverse(poses[target]) @ poses[source]
    return tuple(tuple(float(v) for v in row) for row in T)


def sure_placements(
    jobs: list[PairJob], records: dict[str, dict], min_confidence: float
) -> set[str]:
    """Scans placed on the ALS at least this surely: a pair of two of them starts from its prior
    and is verified first (jobs.with_stored_poses), the global search only when that fails."""
    return {
        j.source
        for j in jobs
        if (r := records.get(j.key, {})).get("status") == "ok"
        and (r.get("confidence") is not None and r["confidence"] >= min_confidence)
    }

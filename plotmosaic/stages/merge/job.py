"""What one merge will do, decided before its first point is written, and what it reports."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS

from plotmosaic.config.merge import MergeConfig, bbox_limits
from plotmosaic.errors import InputError
from plotmosaic.manifest import Manifest
from plotmosaic.poses import Poses
from plotmosaic.stages.merge.plan import (
    MergeSummary,
    Source,
    SourceCount,
    build_header,
    check_output,
    output_bounds,
    output_crs,
    plan_sources,
)


@dataclass(frozen=True, kw_only=True)
class MergeJob:
    """Everything decided before the first point is written."""

    out: Path
    sidecar: Path
    config: MergeConfig
    sources: list[Source]
    skipped: list[str]
    ignored: list[str]
    crs: CRS | None
    crs_source: str
    mins: np.ndarray
    maxs: np.ndarray
    header: laspy.LasHeader
    total: int
    frame: str
    poses_path: str | None
    start: float


def plan_merge(
    manifest: Manifest, poses: Poses, out: Path, config: MergeConfig, poses_path
) -> MergeJob:
    """The output checked, its sources, CRS, bounds and header; bad input is found here."""
    sidecar = check_output(out, config)
    start = time.perf_counter()
    sources, skipped, ignored = plan_sources(manifest, poses, config)
    crs, crs_source = output_crs(manifest, poses, sources)
    for s in sources:  # ALS tiles are taken as they are: they must be in the output CRS
        if (
            s.kind == "als"
            and s.id.startswith("als:")
            and s.info.crs is not None
            and crs is not None
            and not s.info.crs.equals(crs, ignore_axis_order=True)
        ):
            raise InputError(
                f"{s.path}: ALS tile is in {s.info.crs.name}, the merged cloud in {crs.name}"
            )
    mins, maxs = output_bounds(sources)
    if config.bbox is not None:
        lo, hi = bbox_limits(config.bbox)
        if np.any(lo > maxs) or np.any(hi < mins):
            raise InputError(
                f"--bbox does not overlap the merged scans (x {mins[0]:.3f}..{maxs[0]:.3f}, y {mins[1]:.3f}..{maxs[1]:.3f}, z {mins[2]:.3f}..{maxs[2]:.3f})"
            )
    return MergeJob(
        out=out,
        sidecar=sidecar,
        config=config,
        sources=sources,
        skipped=skipped,
        ignored=ignored,
        crs=crs,
        crs_source=crs_source,
        mins=mins,
        maxs=maxs,
        header=build_header(sources, crs, mins),
        total=sum(s.info.point_count for s in sources),
        frame=poses.frame,
        poses_path=str(poses_path) if poses_path else None,
        start=start,
    )


def summary_of(job: MergeJob, counts: list[SourceCount], lo, hi, tiles=None) -> MergeSummary:
    """The merge's summary once written: points per source, output bounds `lo`..`hi`, and the
    tiles if any."""
    crs = job.crs
    return MergeSummary(
        job.out,
        job.sidecar,
        counts,
        np.asarray(lo),
        np.asarray(hi),
        crs.to_wkt() if crs else None,
        crs.name if crs else None,
        job.crs_source,
        job.config.voxel,
        job.config.bbox,
        time.perf_counter() - job.start,
        job.skipped,
        job.ignored,
        tiles,
    )


def sidecar_text(job: MergeJob, summary: MergeSummary) -> str:
    """The sidecar `<out>.json` (or a tile folder's index): poses used and the summary."""
    data = {"poses": job.poses_path, "frame": job.frame, **summary.to_dict()}
    return json.dumps(data, indent=1)

"""tie-to-als: anchor each plot to the ALS and optimise the whole region with the ALS frame fixed.

Per plot: merge its scans with the register-plot poses (voxel-thinned) into one plot cloud, crop
the ALS around it (by approximate CRS positions when the manifest has them, else the whole tile,
where the coarse stage has to find the plot), register plot -> ALS with ForestAlign (TLS K=3 vs
ALS K=2). Each result becomes an edge between the plot's reference scan and an "ALS" node, in one
graph with each plot's scans as register-plot placed them (its poses and sigmas as edges to the
reference). The region is solved in a local frame (ALS CRS minus a recorded offset), and poses are
written in the ALS CRS.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.register import TieConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.cache import PairCache
from plotmosaic.graph.compute import compute_pairs
from plotmosaic.graph.executor import Workers
from plotmosaic.graph.jobs import JobSettings, PairJob, ScanFile, pair_job, prepare_jobs_for
from plotmosaic.graph.posegraph import Solution, graph_from_json, graph_to_json
from plotmosaic.graph.prepared import points_reader, prepare_held
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import Frame, translation
from plotmosaic.io.las import PointCloud, write_cloud
from plotmosaic.manifest import Manifest, Plot, load_manifest
from plotmosaic.poses import Poses, ScanPose, load_poses
from plotmosaic.report.runs import write_tie_report
from plotmosaic.stages.tie_to_als.anchor_fit import fit_anchors
from plotmosaic.stages.tie_to_als.clouds import LAS_SCALE, as_stored, crop_als, load_als, plot_cloud
from plotmosaic.stages.tie_to_als.solve import (
    ALS_NODE,
    Anchor,
    Tied,
    _anchor_dict,
    _plot_reference,
    anchor_of,
    georeferenced_sigmas,
    region_graph,
    solve_region,
)

__all__ = ["Anchor", "as_stored", "plot_cloud", "tie_to_als"]


@dataclass(frozen=True)
class TieResult:
    out: Path
    poses: Poses
    graph: nx.Graph
    anchors: list[Anchor]
    solution: Solution
    offset: np.ndarray
    unplaced: list[str] = field(default_factory=list)
    computed: int = 0
    seconds: float = 0.0


@dataclass(frozen=True, kw_only=True)
class TieRun:
    """One tie-to-als run: the register-plot poses it ties, the ALS it ties them to, where to."""

    manifest: Manifest
    config: TieConfig
    poses: Poses
    poses_path: Path
    G_plot: nx.Graph | None  # register-plot's graph (the scans' files, for the report)
    out: Path
    als: PointCloud
    crs: object
    als_frame: Frame  # the region is solved in ALS CRS - offset
    prepared_scans: dict[str, Path]  # scan id -> register-plot's prepared cloud
    seed: int


def _start(
    manifest: str | Path | Manifest,
    poses_path: str | Path,
    out: str | Path,
    config: TieConfig | None,
    seed: int,
) -> TieRun:
    """The inputs loaded and checked (register-plot poses, one ALS tile with a CRS), OUT made."""
    config = config or TieConfig()
    manifest = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    poses_path, out = Path(poses_path), Path(out)
    poses = load_poses(poses_path)
    if poses.frame != "plot":
        raise InputError(
            f"{poses_path}: expected register-plot poses (frame 'plot'), got frame {poses.frame!r}"
        )
    graph_path = poses_path.parent / "graph.json"
    G_plot = graph_from_json(json.loads(graph_path.read_text())) if graph_path.is_file() else None
    out.mkdir(parents=True, exist_ok=True)
    if any(s.id == ALS_NODE for s in manifest.scans):
        raise InputError(
            f"{manifest.source}: scan id {ALS_NODE!r} is reserved for the ALS frame in tie-to-als; rename the scan"
        )
    als, crs = load_als(manifest)
    if crs is None:
        raise InputError(
            f"{manifest.resolve(manifest.als[0].path)}: the ALS tile has no CRS; cannot georeference"
        )
    # register-plot's prepared clouds (voxel grids of every scan): no scan is read again to build the plots
    recorded = poses.extra.get("prepared") or {}
    prepared_scans = {
        sid: poses_path.parent / "prepared" / Path(name).name for sid, name in recorded.items()
    }
    return TieRun(
        manifest=manifest,
        config=config,
        poses=poses,
        poses_path=poses_path,
        G_plot=G_plot,
        out=out,
        als=als,
        crs=crs,
        als_frame=Frame.around(als.xyz),
        prepared_scans=prepared_scans,
        seed=seed,
    )


def _plot_job(run: TieRun, plot: Plot, cache: PairCache) -> tuple[PairJob, str]:
    """(the pair plot cloud -> ALS crop, how the ALS was cropped): both clouds written as outputs,
    and prepared from the points in memory (exactly what the files hold) unless the pair is cached."""
    cloud = plot_cloud(run.manifest, plot, run.poses, run.config, run.prepared_scans)
    crop, how = crop_als(run.als, plot, cloud, run.config.buffer)
    src = write_cloud(run.out / "plots" / f"{plot.id}.laz", cloud, scale=LAS_SCALE)
    tgt = write_cloud(run.out / "plots" / f"{plot.id}_als.laz", crop, crs=run.crs, scale=LAS_SCALE)
    # a merged plot may pass for one scan about the reference scanner (align/viewpoint.py); its only
    # partner is the ALS, which has no scanner, so the final ICP's side test never runs on it
    kind, k, als_k = plot.reference.kind.value, plot.reference.k, run.manifest.als[0].k
    settings = JobSettings(run.config.align, run.seed, str(run.out / "prepared"), run.config.read)
    job = pair_job(
        settings, ScanFile(plot.id, str(src), kind, k), ScanFile(ALS_NODE, str(tgt), "als", als_k)
    )
    if not cache.path(job.key).is_file():  # a cached result needs neither cloud prepared
        for pj, points in zip(prepare_jobs_for(job), (as_stored(cloud), as_stored(crop))):
            prepare_held(pj, points)
    return job, how


def _tie_plots(run: TieRun, workers: Workers) -> Tied:
    """Each plot with a placed scan registered to the ALS; its pair runs (and is cached) like any."""
    jobs: dict[str, tuple[PairJob, str]] = {}  # plot id -> (its job, how the ALS was cropped)
    refs = {}
    cache = PairCache(run.out / "pairs")
    for plot in run.manifest.plots:
        if any(s.id in run.poses.scans for s in plot.scans):
            refs[plot.id] = _plot_reference(plot, run.poses, run.G_plot)
            jobs[plot.id] = _plot_job(run, plot, cache)
    jobs_list = [job for job, _ in jobs.values()]
    records, computed = compute_pairs(jobs_list, cache, workers)
    fits = fit_anchors(jobs_list, records, run.config)
    anchors = {}
    for plot in run.manifest.plots:
        if plot.id not in jobs:
            why = "no scan of this plot was placed by register-plot"
            anchors[plot.id] = Anchor(plot.id, "", "failed", error=why)
            continue
        job, how = jobs[plot.id]
        anchors[plot.id] = anchor_of(
            plot.id, refs[plot.id], how, records[job.key], fits.get(plot.id)
        )
    return Tied(
        jobs=jobs_list, records=records, computed=computed, anchors=anchors, refs=refs, fits=fits
    )


def _write(run: TieRun, G: nx.Graph, sol: Solution, tied: Tied, start: float) -> TieResult:
    """poses.json (ALS CRS), graph.json and the report written; the run's result."""
    E = translation(run.als_frame.offset)
    sigmas = {**sol.sigmas, **georeferenced_sigmas(run.poses, tied)}
    scans = {}
    for name, X in sol.poses.items():
        if name == ALS_NODE:
            continue
        scans[name] = ScanPose(E @ X, G.nodes[name].get("plot"), sigmas[name])
    unplaced = sorted(s.id for s in run.manifest.scans if s.id not in scans)
    extra = {
        "offset": [float(v) for v in run.als_frame.offset],
        "unplaced": unplaced,
        "anchors": {a.plot: _anchor_dict(a) for a in tied.anchors.values()},
    }
    result_poses = Poses(scans, frame="crs", crs=run.crs.to_wkt(), extra=extra)
    write_text_atomic(run.out / "graph.json", json.dumps(graph_to_json(G)))
    result_poses.save(run.out / "poses.json")
    entries = {
        str(run.manifest.resolve(s.path)): run.prepared_scans[s.id]
        for s in run.manifest.scans
        if s.id in run.prepared_scans
    }
    anchors = list(tied.anchors.values())
    offset = run.als_frame.offset
    seconds = time.perf_counter() - start  # the report shows the work before it
    result = TieResult(
        run.out, result_poses, G, anchors, sol, offset, unplaced, tied.computed, seconds
    )
    write_tie_report(
        result,
        run.manifest,
        run.als,
        run.config,
        run.seed,
        reader=points_reader(entries, run.config.read, run.config.align),
        earlier=run.poses,
        earlier_report=run.poses_path.parent / "report.html",
    )
    return dataclasses.replace(result, seconds=time.perf_counter() - start)


def tie_to_als(
    manifest: str | Path | Manifest,
    poses_path: str | Path,
    out: str | Path,
    config: TieConfig | None = None,
    seed: int = 0,
    workers: Workers = Workers(),
) -> TieResult:
    """Tie register-plot's plots (`poses_path`) to the manifest's ALS tile into `out`: poses.json in
    the ALS CRS, graph.json, the plot clouds and the report. Raises InputError for bad inputs and
    RegistrationFailed when no plot can be registered to the ALS."""
    start = time.perf_counter()
    run = _start(manifest, poses_path, out, config, seed)
    tied = _tie_plots(run, workers)  # plot cloud -> ALS crop, each
    G = region_graph(run.manifest, run.poses, run.G_plot, run.als_frame, tied)
    sol = solve_region(G, run.config)  # the region, with the ALS node fixed
    return _write(run, G, sol, tied, start)

"""Write: a register-plot run's poses, pose graph and report into its output folder."""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx

from plotmosaic.graph.jobs import prepare_jobs_for
from plotmosaic.graph.posegraph import graph_to_json
from plotmosaic.graph.prepared import entry, points_reader
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.poses import Poses
from plotmosaic.report.runs import write_register_report
from plotmosaic.stages.register_plot.pairs import Pairs, Run
from plotmosaic.stages.register_plot.place import Priors
from plotmosaic.stages.register_plot.solve import PlotResult, Solved


@dataclass(frozen=True)
class RegisterResult:
    out: Path
    poses: Poses
    graph: nx.Graph
    plots: list[PlotResult]
    pairs: int
    computed: int  # pairs registered in this run (the rest came from the cache)
    failed: list[dict] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def unplaced(self) -> list[str]:
        return [s for p in self.plots for s in p.unplaced]


def _extra(run: Run, priors: Priors, pairs: Pairs, solved: Solved) -> dict:
    """What poses.json holds beside the poses: each plot's reference, unplaced and dropped scans,
    the ALS placements, and each scan's prepared cloud under OUT/prepared (tie-to-als reuses them)."""
    results = solved.plots
    extra = {
        "plots": {
            r.plot: {
                "reference": r.reference,
                "unplaced": r.unplaced,
                "dropped": r.solution.dropped,
            }
            for r in results
        },
        "unplaced": [s for r in results for s in r.unplaced],
    }
    if priors.placement:  # scan -> ALS step of big plots without positions: which scans it placed
        extra["placement"] = {
            j.source: "ok"
            if j.source in priors.placed
            else priors.placement_records[j.key].get("error")
            for j in priors.placement
        }
    by_path = {str(run.manifest.resolve(s.path)): s.id for s in run.manifest.scans}
    extra["prepared"] = {}
    for job in pairs.jobs:
        for pj in prepare_jobs_for(job):
            extra["prepared"][by_path[pj.path]] = entry(pj.folder, pj.key).name
    return extra


def write(run: Run, priors: Priors, pairs: Pairs, solved: Solved, start: float) -> RegisterResult:
    """graph.json, poses.json and the report written; the run's result (its seconds since `start`)."""
    extra = _extra(run, priors, pairs, solved)
    poses = Poses(solved.scans, frame="plot", crs=None, extra=extra)
    G = solved.graph
    failed = G.graph["failed"]
    write_text_atomic(run.out / "graph.json", json.dumps(graph_to_json(G)))
    poses.save(run.out / "poses.json")
    result = RegisterResult(
        run.out,
        poses,
        G,
        solved.plots,
        len(pairs.jobs),
        pairs.computed,
        failed,
        time.perf_counter() - start,  # the report shows the work before it
    )
    # the pictures use the prepared (voxel-thinned) points: no scan is read a second time
    by_path = {str(run.manifest.resolve(s.path)): s.id for s in run.manifest.scans}
    entries = {
        p: run.out / "prepared" / extra["prepared"][sid]
        for p, sid in by_path.items()
        if sid in extra["prepared"]
    }
    reader = points_reader(entries, run.config.read, run.config.align)
    write_register_report(result, run.manifest, run.config, run.seed, reader=reader)
    return dataclasses.replace(result, seconds=time.perf_counter() - start)

"""register-plot: candidate pairs -> cached parallel align -> pose graph per plot -> poses, graph, report.

A region manifest is done plot by plot: each plot gets its own frame (its reference scan's file
coordinates); tie-to-als then places the plots in the ALS CRS.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np
from pydantic import BaseModel, Field

from plotmosaic.align.config import AlignConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.cache import PairCache, pair_key
from plotmosaic.graph.executor import PairJob, run_pairs
from plotmosaic.graph.pairs import candidate_pairs
from plotmosaic.graph.posegraph import PoseGraphConfig, Solution, build_graph, graph_to_json, optimise
from plotmosaic.graph import report as rep
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.las import read_cloud, read_header_info
from plotmosaic.manifest import Manifest, Plot, load_manifest
from plotmosaic.poses import Poses, ScanPose

# Figures of a pair result kept on the graph edge (the full result stays in DIR/pairs/).
EDGE_FIELDS = ("source", "target", "key", "status", "error", "transform", "information", "fitness", "inlier_rmse",
               "overlap", "confidence", "sigma", "seconds")


def _graph_align_config() -> AlignConfig:
    # unsure pairs still become edges: the pose graph keeps one only when a loop confirms it
    return AlignConfig(min_confidence=0.0)


class RegisterConfig(BaseModel):
    align: AlignConfig = Field(default_factory=_graph_align_config)
    graph: PoseGraphConfig = Field(default_factory=PoseGraphConfig)
    max_distance: float | None = Field(60.0, gt=0)  # with approximate positions: farther pairs are not tried
    report_points: int = 20_000  # per scan in the pictures


@dataclass
class PlotResult:
    plot: str
    reference: str
    solution: Solution
    scans: list[str]

    @property
    def unplaced(self) -> list[str]:
        return self.solution.unplaced


@dataclass
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


def plan_jobs(manifest: Manifest, config: RegisterConfig, seed: int) -> list[PairJob]:
    config_json = config.align.model_dump_json()
    jobs = []
    for plot in manifest.plots:
        for source, target in candidate_pairs(plot, config.max_distance):
            sp, tp = manifest.resolve(source.path), manifest.resolve(target.path)
            key = pair_key(sp, tp, source.kind.value, target.kind.value, source.k, target.k, config_json, seed)
            jobs.append(PairJob(key, source.id, target.id, str(sp), str(tp), source.kind.value, target.kind.value,
                                source.k, target.k, config_json, seed))
    return jobs


def compute_pairs(jobs: list[PairJob], cache: PairCache, executor: str = "local", n_jobs: int | None = None,
                  scheduler: str | None = None, force: bool = False, progress: bool = True,
                  on_result: Callable[[dict], None] | None = None) -> tuple[dict[str, dict], int]:
    """Records for every job, from the cache where present; returns (records by key, number computed)."""
    records = {} if force else {job.key: r for job in jobs if (r := cache.get(job.key)) is not None}
    todo = [job for job in jobs if job.key not in records]
    computed = 0

    def keep(record: dict) -> None:
        nonlocal computed
        computed += 1
        if record.get("status") == "ok" or record.pop("cacheable", False):
            cache.put(record["key"], record)
        records[record["key"]] = record
        if on_result is not None:
            on_result(record)

    run_pairs(todo, keep, executor, n_jobs, scheduler, progress)
    return records, computed


def _choose_reference(G: nx.Graph, plot: Plot) -> str:
    """The manifest's reference, unless it has no successful pair: then the best-connected scan."""
    ref = plot.reference.id
    if G.degree(ref) > 0 or G.number_of_edges() == 0:
        return ref
    biggest = max(nx.connected_components(G), key=len)
    return max(sorted(biggest), key=lambda n: G.degree(n, weight="weight"))


def register_plot(manifest: str | Path | Manifest, out: str | Path, jobs: int | None = None, executor: str = "local",
                  scheduler: str | None = None, config: RegisterConfig | None = None, seed: int = 0,
                  force: bool = False, progress: bool = True,
                  on_result: Callable[[dict], None] | None = None) -> RegisterResult:
    start = time.perf_counter()
    config = config or RegisterConfig()
    manifest = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    cache = PairCache(out / "pairs")
    job_list = plan_jobs(manifest, config, seed)
    records, computed = compute_pairs(job_list, cache, executor, jobs, scheduler, force, progress, on_result)

    nodes = {}
    for plot in manifest.plots:
        for scan in plot.scans:
            path = manifest.resolve(scan.path)
            nodes[scan.id] = {"plot": plot.id, "kind": scan.kind.value, "path": str(path),
                              "points": read_header_info(path).point_count}
    edges = [{k: records[j.key].get(k) for k in EDGE_FIELDS} for j in job_list]
    G = build_graph(nodes, edges)
    failed = G.graph["failed"]

    results, scans = [], {}
    for plot in manifest.plots:
        sub = G.subgraph([s.id for s in plot.scans])
        ref = _choose_reference(sub, plot)
        sol = optimise(sub, ref, config.graph)
        results.append(PlotResult(plot.id, ref, sol, [s.id for s in plot.scans]))
        for name, T in sol.poses.items():
            scans[name] = ScanPose(T, plot.id, sol.sigmas[name])
    extra = {
        "plots": {r.plot: {"reference": r.reference, "unplaced": r.unplaced, "dropped": r.solution.dropped} for r in results},
        "unplaced": [s for r in results for s in r.unplaced],
    }
    poses = Poses(scans, frame="plot", crs=None, extra=extra)
    result = RegisterResult(out, poses, G, results, len(job_list), computed, failed, 0.0)

    write_text_atomic(out / "graph.json", json.dumps(graph_to_json(G)))
    poses.save(out / "poses.json")
    result.seconds = time.perf_counter() - start
    write_register_report(result, manifest, config, seed)
    result.seconds = time.perf_counter() - start
    return result


def _read_xyz(path: Path) -> np.ndarray:
    return read_cloud(path, attributes=False).xyz


# the report (report.md + report.html) is H-report's: plotmosaic/graph/report.py
from plotmosaic.graph.report import write_register_report  # noqa: E402

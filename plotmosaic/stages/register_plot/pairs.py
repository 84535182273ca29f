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

from plotmosaic.config.register import (
    RegisterConfig,
)
from plotmosaic.config.scale import PlacedPriors, SignatureConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.cache import PairCache, pair_key
from plotmosaic.graph.executor import PairJob, prepare_jobs_for, run_pairs, with_stored_poses
from plotmosaic.graph.pairs import (
    candidate_pairs,
    manifest_positions,
    neighbour_pairs,
    reach_distance,
)
from plotmosaic.graph.placement import placed_poses, placement_jobs, prior, sure_placements
from plotmosaic.graph.posegraph import (
    Solution,
    add_edges,
    build_graph,
    graph_to_json,
    optimise,
)
from plotmosaic.graph.prepared import (
    PrepareJob,
    entry,
    points_reader,
    prepared_key,
    run_prepare_job,
)
from plotmosaic.graph.signature import (
    SignatureJob,
    from_record,
    grow_candidates,
    ranked_partners,
    run_signature_job,
    signature_pairs,
    similarity,
)
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import translation
from plotmosaic.io.las import read_header_info
from plotmosaic.manifest import Manifest, Plot, Scan, load_manifest
from plotmosaic.poses import Poses, ScanPose
from plotmosaic.report.runs import write_register_report

# Figures of a pair result kept on the graph edge (the full result stays in DIR/pairs/).
EDGE_FIELDS = (
    "source",
    "target",
    "key",
    "status",
    "error",
    "transform",
    "information",
    "fitness",
    "inlier_rmse",
    "overlap",
    "confidence",
    "sigma",
    "seconds",
)


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


def _pair_job(
    manifest: Manifest,
    source: Scan,
    target: Scan,
    config_json: str,
    seed: int,
    prepared: str | None,
    placed: dict[str, np.ndarray],
) -> PairJob:
    sp, tp = manifest.resolve(source.path), manifest.resolve(target.path)
    key = pair_key(
        sp, tp, source.kind.value, target.kind.value, source.k, target.k, config_json, seed
    )
    return PairJob(
        key,
        source.id,
        target.id,
        str(sp),
        str(tp),
        source.kind.value,
        target.kind.value,
        source.k,
        target.k,
        config_json,
        seed,
        prepared,
        prior(placed, source.id, target.id),
    )


def plan_jobs(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    prepared: str | Path | None = None,
    placed: dict[str, np.ndarray] | None = None,
    linked: dict[str, list[tuple[str, str]]] | None = None,
) -> list[PairJob]:
    """The pair jobs of every plot; `prepared`: the prepared-cloud cache folder (DIR/prepared);
    `placed`: scan poses from the ALS step (positions for the pair selection, priors for the coarse stage);
    `linked`: plot id -> pairs of scans whose signatures match (pairs for scans without a position)."""
    config_json = config.align.model_dump_json()
    prepared = None if prepared is None else str(prepared)
    placed = placed or {}
    linked = linked or {}
    reach = _priors(config).reach
    jobs = []
    for plot in manifest.plots:
        positions = {s.id: placed[s.id][:3, 3] for s in plot.scans if s.id in placed} or None
        for source, target in candidate_pairs(
            plot, config.max_distance, positions, config.pairs, linked.get(plot.id), reach
        ):
            jobs.append(_pair_job(manifest, source, target, config_json, seed, prepared, placed))
    return jobs


def _signature_config(config: RegisterConfig) -> SignatureConfig:
    return getattr(config, "signature", None) or SignatureConfig()


def _priors(config: RegisterConfig) -> PlacedPriors:
    return getattr(config, "placed_priors", None) or PlacedPriors()


def _degrees(job_list: list[PairJob]) -> dict[str, int]:
    degree: dict[str, int] = {}
    for j in job_list:
        degree[j.source] = degree.get(j.source, 0) + 1
        degree[j.target] = degree.get(j.target, 0) + 1
    return degree


def graph_poses(
    manifest: Manifest,
    config: RegisterConfig,
    job_list: list[PairJob],
    records: dict[str, dict],
    anchors: dict[str, list[dict]],
) -> dict[str, np.ndarray]:
    """scan id -> its pose in its plot's frame, from the pose graph of the pairs so far (and the ALS
    anchors): what the verified pairs place, after the graph's own outlier checks."""
    edges = [{k: records[j.key].get(k) for k in EDGE_FIELDS} for j in job_list if j.key in records]
    G = build_graph({s.id: {} for s in manifest.scans}, edges)
    poses: dict[str, np.ndarray] = {}
    for plot in manifest.plots:
        poses.update(solve_plot(G, plot, anchors.get(plot.id, []), config)[1].poses)
    return poses


def position_jobs(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    prepared: str | Path,
    poses: dict[str, np.ndarray],
    job_list: list[PairJob],
) -> list[PairJob]:
    """Neighbour pairs of a big plot's scans that the pose graph places (graph_poses), not tried yet:
    at most `reach` x the scan spacing apart, their prior from the graph and verified first (a chain
    of verified pairs is as good a prior as two ALS placements), at most `max_per_scan` pairs a scan."""
    reach = _priors(config).reach
    config_json = config.align.model_dump_json()
    tried = {frozenset((j.source, j.target)) for j in job_list}
    degree = _degrees(job_list)
    cap = config.pairs.max_per_scan
    out = []
    for plot in manifest.plots:
        if len(plot.scans) <= config.pairs.all_pairs_up_to:
            continue  # every pair is tried already
        ids = [s.id for s in plot.scans if s.id in poses]
        if len(ids) < 2:
            continue
        xy = np.array([poses[i][:2, 3] for i in ids])
        far = reach_distance(xy, reach, config.max_distance)
        by_id = {s.id: s for s in plot.scans}
        order = {s.id: k for k, s in enumerate(plot.scans)}
        for i, j in neighbour_pairs(xy, config.pairs.neighbours, cap, far):
            a, b = ids[i], ids[j]
            if frozenset((a, b)) in tried or max(degree.get(a, 0), degree.get(b, 0)) >= cap:
                continue
            target, source = sorted((a, b), key=order.get)  # the later scan is the source
            out.append(
                _pair_job(
                    manifest, by_id[source], by_id[target], config_json, seed, str(prepared), poses
                )
            )
            tried.add(frozenset((a, b)))
            degree[a] = degree.get(a, 0) + 1
            degree[b] = degree.get(b, 0) + 1
    return with_stored_poses(out, set(poses))


def match_signatures(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    out: Path,
    placed: dict[str, np.ndarray],
    executor: str = "local",
    n_jobs: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> tuple[dict[str, list[tuple[str, str]]], dict[str, list[str]]]:
    """Big plots where some scan has no position: every scan's stem-map signature (graph/signature.py).

    Returns (plot id -> linked scan pairs, scan id -> other scans of its plot ranked by signature).
    The scans are prepared here, into the cache their pairs load from (each still read once)."""
    sig = _signature_config(config)
    if not sig.enabled:
        return {}, {}
    plots = [
        p
        for p in manifest.plots
        if len(p.scans) > config.pairs.all_pairs_up_to
        and manifest_positions(p) is None
        and not all(s.id in placed for s in p.scans)
    ]
    if not plots:
        return {}, {}
    settings = config.align.model_dump_json()
    folder = str(out / "prepared")
    jobs = {}
    for plot in plots:
        for scan in plot.scans:
            path = str(manifest.resolve(scan.path))
            key = prepared_key(path, scan.kind.value, scan.k, settings, seed)
            jobs[scan.id] = SignatureJob(
                key,
                scan.id,
                path,
                scan.kind.value,
                scan.k,
                settings,
                seed,
                folder,
                sig.model_dump_json(),
            )
    records = run_pairs(
        list(jobs.values()),
        None,
        executor,
        n_jobs,
        scheduler,
        progress,
        worker=run_signature_job,
        label="scan signatures",
    )
    by_key = {r["key"]: r for r in records}
    linked, ranks = {}, {}
    for plot in plots:
        ids = [s.id for s in plot.scans]
        sigs = [from_record(by_key.get(jobs[i].key, {})) for i in ids]
        scores = similarity(sigs, sig)
        # with ALS placements a scan needs one verified partner: the graph places it, and its
        # neighbours follow by position (position_jobs), not by further, costlier signature guesses
        partners = sig.placed_partners if sum(i in placed for i in ids) >= 3 else sig.partners
        pairs = signature_pairs(scores, len(ids), partners, config.pairs.max_per_scan)
        linked[plot.id] = [(ids[i], ids[j]) for i, j in pairs]
        for i, row in enumerate(ranked_partners(scores, len(ids))):
            ranks[ids[i]] = [ids[j] for j in row]
    return linked, ranks


def grow_jobs(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    prepared: str | Path,
    placed: dict[str, np.ndarray],
    ranks: dict[str, list[str]],
    job_list: list[PairJob],
    records: dict[str, dict],
    anchored: set[str] | None = None,
) -> list[PairJob]:
    """Pairs to add where a plot's verified pairs leave it in pieces: the next signature-ranked partners.

    `anchored`: scans held by an ALS anchor (one piece with each other through the plot's ALS node)."""
    sig = _signature_config(config)
    config_json = config.align.model_dump_json()
    tried = {frozenset((j.source, j.target)) for j in job_list}
    degree = _degrees(job_list)
    G = nx.Graph()
    for j in job_list:
        if records.get(j.key, {}).get("status") == "ok":
            G.add_edge(j.source, j.target)
    out = []
    for plot in manifest.plots:
        ids = [s.id for s in plot.scans]
        if not any(i in ranks for i in ids):
            continue
        sub = G.subgraph(ids).copy()
        sub.add_nodes_from(ids)
        sub.add_edges_from((i, anchor_id(plot)) for i in ids if i in (anchored or ()))
        comps = [set(c) - {anchor_id(plot)} for c in nx.connected_components(sub)]
        by_id = {s.id: s for s in plot.scans}
        order = {s.id: k for k, s in enumerate(plot.scans)}
        for a, b in grow_candidates(
            ranks, tried, comps, degree, sig.grow_per_scan, config.pairs.max_per_scan
        ):
            target, source = sorted((a, b), key=order.get)  # the later scan is the source
            out.append(
                _pair_job(
                    manifest, by_id[source], by_id[target], config_json, seed, str(prepared), placed
                )
            )
    return out


def place_scans(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    out: Path,
    executor: str = "local",
    n_jobs: int | None = None,
    scheduler: str | None = None,
    force: bool = False,
    progress: bool = True,
) -> tuple[dict[str, np.ndarray], list[PairJob], dict[str, dict]]:
    """Scans of big plots without positions registered to the ALS tile (N pairs instead of N(N-1)/2)."""
    if not config.place_on_als:
        return {}, [], {}
    jobs = []
    for plot in manifest.plots:
        if len(plot.scans) > config.pairs.all_pairs_up_to and manifest_positions(plot) is None:
            jobs += placement_jobs(
                manifest,
                plot,
                config.placement.model_dump_json(),
                seed,
                str(out / "prepared"),
                config.align.model_dump_json(),
            )
    if not jobs:
        return {}, [], {}
    records, _ = compute_pairs(
        jobs, PairCache(out / "placement"), executor, n_jobs, scheduler, force, progress
    )
    return placed_poses(jobs, records, config.placement_min_confidence), jobs, records


def prepare_scans(
    jobs: list[PairJob],
    executor: str = "local",
    n_jobs: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> dict[str, dict]:
    """Read and prepare every scan these pairs need, once each, into their prepared-cloud cache.

    Returns the failed preparations by prepared key (their pairs are not run)."""
    unique: dict[str, PrepareJob] = {}
    for job in jobs:
        if job.prepared:
            for pj in prepare_jobs_for(job):
                unique.setdefault(pj.key, pj)
    return _prepare(list(unique.values()), executor, n_jobs, scheduler, progress)


def _prepare(
    jobs: list[PrepareJob], executor: str, n_jobs: int | None, scheduler: str | None, progress: bool
) -> dict[str, dict]:
    """Run the prepare jobs whose cache entry is missing; the failed records by prepared key."""
    todo = [pj for pj in jobs if not entry(pj.folder, pj.key).is_file()]
    # entries already on disk are checked when loaded (a damaged one is prepared again there)
    records = run_pairs(
        todo,
        None,
        executor,
        n_jobs,
        scheduler,
        progress,
        worker=run_prepare_job,
        label="preparing scans",
    )
    return {r["key"]: r for r in records if r.get("status") != "ok"}


def prepare_every_scan(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    folder: Path,
    executor: str = "local",
    n_jobs: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> None:
    """Read and prepare every scan of the manifest before any pair runs (into the cache the pairs
    load from): a scan that cannot be read stops the run here, named, instead of leaving it unplaced."""
    settings = config.align.model_dump_json()
    jobs = {}
    for plot in manifest.plots:
        for scan in plot.scans:
            path = str(manifest.resolve(scan.path))
            key = prepared_key(path, scan.kind.value, scan.k, settings, seed)
            jobs[key] = PrepareJob(
                key, scan.id, path, scan.kind.value, scan.k, settings, seed, str(folder)
            )
    for key, record in _prepare(list(jobs.values()), executor, n_jobs, scheduler, progress).items():
        pj = jobs[key]
        cause = str(record.get("error", "")).removeprefix("InputError: ")
        cause = cause.removeprefix(f"{pj.path}: ")
        raise InputError(f"{pj.path}: scan {pj.scan!r} cannot be used ({cause})")


def compute_pairs(
    jobs: list[PairJob],
    cache: PairCache,
    executor: str = "local",
    n_jobs: int | None = None,
    scheduler: str | None = None,
    force: bool = False,
    progress: bool = True,
    on_result: Callable[[dict], None] | None = None,
) -> tuple[dict[str, dict], int]:
    """Records for every job, from the cache where present; returns (records by key, number computed).

    Scans are prepared first (one job per scan), then the pairs load them from the cache."""
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

    failed = prepare_scans(todo, executor, n_jobs, scheduler, progress)
    runnable = []
    for job in todo:
        bad = (
            [failed[pj.key] for pj in prepare_jobs_for(job) if pj.key in failed]
            if job.prepared
            else []
        )
        if (
            bad
        ):  # the scan itself cannot be used: its error, not a registration failure (not cached)
            keep(
                {
                    "source": job.source,
                    "target": job.target,
                    "key": job.key,
                    "status": "failed",
                    "error": f"scan {bad[0]['scan']}: {bad[0].get('error')}",
                    "cacheable": False,
                }
            )
        else:
            runnable.append(job)
    run_pairs(runnable, keep, executor, n_jobs, scheduler, progress)
    return records, computed


def anchor_id(plot: Plot) -> str:
    """The ALS node of a plot's pose graph (never a scan: ids with '@' are not written to poses)."""
    return f"ALS@{plot.id}"


def als_anchor_edges(
    plot: Plot, placement: list[PairJob], records: dict[str, dict], placed: set[str]
) -> list[dict]:
    """Edges scan -> the plot's ALS node from its kept ALS placements, in a local ALS frame (the ALS
    file coordinates less the placements' mean position, rounded to 1 m: UTM-sized translations
    would make the ALS node's rotation ill-conditioned)."""
    ids = {s.id for s in plot.scans}
    use = [j for j in placement if j.source in ids and j.source in placed]
    if not use:
        return []
    Ts = [np.asarray(records[j.key]["transform"], dtype=float) for j in use]
    shift = translation(-np.round(np.mean([T[:3, 3] for T in Ts], axis=0)))
    out = []
    for j, T in zip(use, Ts, strict=True):
        e = {k: records[j.key].get(k) for k in EDGE_FIELDS}
        e.update(source=j.source, target=anchor_id(plot), transform=shift @ T)
        out.append(e)
    return out


def solve_plot(
    G: nx.Graph, plot: Plot, anchors: list[dict], config: RegisterConfig
) -> tuple[str, Solution]:
    """(reference, solution) of one plot: its scans' subgraph, plus the ALS node when there are anchors.

    The ALS node and its edges live only in the solve; what the solve marks on the scan-to-scan
    edges (dropped, residuals) is written back to G, and the ALS node is no pose of the result."""
    ids = [s.id for s in plot.scans]
    sub = G.subgraph(ids)
    ref = _choose_reference(sub, plot)
    if not anchors:
        return ref, optimise(sub, ref, config.graph)
    H = add_edges(sub.copy(), anchors)
    sol = optimise(H, ref, config.graph)
    for u, v in sub.edges():
        G.edges[u, v].update(H.edges[u, v])
    node = anchor_id(plot)
    sol.poses.pop(node, None)
    sol.sigmas.pop(node, None)
    sol.unplaced = [n for n in sol.unplaced if n != node]
    return ref, sol


def _choose_reference(G: nx.Graph, plot: Plot) -> str:
    """The manifest's reference, unless it has no successful pair: then the best-connected scan."""
    ref = plot.reference.id
    if G.degree(ref) > 0 or G.number_of_edges() == 0:
        return ref
    biggest = max(nx.connected_components(G), key=len)
    return max(sorted(biggest), key=lambda n: G.degree(n, weight="weight"))


def register_plot(
    manifest: str | Path | Manifest,
    out: str | Path,
    jobs: int | None = None,
    executor: str = "local",
    scheduler: str | None = None,
    config: RegisterConfig | None = None,
    seed: int = 0,
    force: bool = False,
    progress: bool = True,
    on_result: Callable[[dict], None] | None = None,
) -> RegisterResult:
    start = time.perf_counter()
    config = config or RegisterConfig()
    manifest = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    cache = PairCache(out / "pairs")
    prepare_every_scan(
        manifest, config, seed, out / "prepared", executor, jobs, scheduler, progress
    )
    placed, placement, placement_records = place_scans(
        manifest, config, seed, out, executor, jobs, scheduler, force, progress
    )
    # poses stored in the scan files (E57 `use_pose = true`) are priors like the ALS step's, one
    # plot at a time so that frames never mix within a plot; the pairwise judge verifies them
    stored = manifest.stored_poses()
    verify_first: set[str] = set()  # scans whose prior is checked before any search
    for plot in manifest.plots:
        if not any(s.id in placed for s in plot.scans):
            placed.update({s.id: stored[s.id] for s in plot.scans if s.id in stored})
            verify_first |= {s.id for s in plot.scans if s.id in stored}
    priors = _priors(config)
    if (
        priors.verify_first
    ):  # two sure ALS placements: their relative pose is as good as a stored one
        verify_first |= sure_placements(placement, placement_records, priors.min_confidence)
    linked, ranks = match_signatures(
        manifest, config, seed, out, placed, executor, jobs, scheduler, progress
    )
    job_list = with_stored_poses(
        plan_jobs(manifest, config, seed, out / "prepared", placed, linked), verify_first
    )
    records, computed = compute_pairs(
        job_list, cache, executor, jobs, scheduler, force, progress, on_result
    )
    from_als = set(placed) - set(stored)  # the ALS step's placements (not stored E57 poses)
    anchors = {
        plot.id: als_anchor_edges(plot, placement, placement_records, from_als)
        if config.als_anchors
        else []
        for plot in manifest.plots
    }
    # the plan grows in bounded rounds: neighbour pairs of the scans the verified graph places
    # (priors verified first), else, where a plot is still in pieces, the next signature partners
    grows = _signature_config(config).grow_rounds if ranks else 0
    positions = priors.position_rounds
    while True:
        more = []
        if positions:
            poses = graph_poses(manifest, config, job_list, records, anchors)
            more = position_jobs(manifest, config, seed, out / "prepared", poses, job_list)
            positions -= bool(more)
        if not more and grows:
            grows -= 1
            anchored = from_als if config.als_anchors else set()
            more = with_stored_poses(
                grow_jobs(
                    manifest,
                    config,
                    seed,
                    out / "prepared",
                    placed,
                    ranks,
                    job_list,
                    records,
                    anchored,
                ),
                verify_first,
            )
        if not more:
            break
        job_list += more
        extra_records, extra_computed = compute_pairs(
            more, cache, executor, jobs, scheduler, force, progress, on_result
        )
        records.update(extra_records)
        computed += extra_computed

    nodes = {}
    for plot in manifest.plots:
        for scan in plot.scans:
            path = manifest.resolve(scan.path)
            nodes[scan.id] = {
                "plot": plot.id,
                "kind": scan.kind.value,
                "path": str(path),
                "points": read_header_info(path).point_count,
            }
    edges = [{k: records[j.key].get(k) for k in EDGE_FIELDS} for j in job_list]
    G = build_graph(nodes, edges)
    failed = G.graph["failed"]

    results, scans = [], {}
    for plot in manifest.plots:
        ref, sol = solve_plot(G, plot, anchors[plot.id], config)
        results.append(PlotResult(plot.id, ref, sol, [s.id for s in plot.scans]))
        for name, T in sol.poses.items():
            scans[name] = ScanPose(T, plot.id, sol.sigmas[name])
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
    if placement:  # scan -> ALS step of big plots without positions: which scans it placed
        extra["placement"] = {
            j.source: "ok" if j.source in placed else placement_records[j.key].get("error")
            for j in placement
        }
    by_path = {str(manifest.resolve(s.path)): s.id for s in manifest.scans}
    extra[
        "prepared"
    ] = {}  # scan id -> its prepared cloud under OUT/prepared (tie-to-als reuses them)
    for job in job_list:
        for pj in prepare_jobs_for(job):
            extra["prepared"][by_path[pj.path]] = entry(pj.folder, pj.key).name
    poses = Poses(scans, frame="plot", crs=None, extra=extra)
    result = RegisterResult(out, poses, G, results, len(job_list), computed, failed, 0.0)

    write_text_atomic(out / "graph.json", json.dumps(graph_to_json(G)))
    poses.save(out / "poses.json")
    result.seconds = time.perf_counter() - start
    # the pictures use the prepared (voxel-thinned) points: no scan is read a second time
    entries = {
        p: out / "prepared" / extra["prepared"][sid]
        for p, sid in by_path.items()
        if sid in extra["prepared"]
    }
    write_register_report(result, manifest, config, seed, reader=points_reader(entries))
    result.seconds = time.perf_counter() - start
    return result

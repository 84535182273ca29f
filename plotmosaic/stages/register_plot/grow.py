"""Grow: the plan's pairs beyond its spanning tree from the poses the tree implies, then more pairs in
bounded rounds, where the verified pairs so far place scans or leave a plot in pieces."""

from __future__ import annotations

from collections import Counter

import networkx as nx
import numpy as np

from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.jobs import JobSettings, PairJob, ScanFile, pair_job, with_stored_poses
from plotmosaic.graph.pairs import neighbour_pairs, reach_distance, spanning_first
from plotmosaic.graph.placement import prior
from plotmosaic.graph.posegraph import build_graph
from plotmosaic.graph.signature import grow_candidates
from plotmosaic.manifest import Manifest, Plot
from plotmosaic.stages.register_plot.pairs import Pairs, Run, anchor_id, run_jobs
from plotmosaic.stages.register_plot.place import Priors
from plotmosaic.stages.register_plot.solve import solve_plot


def _degrees(job_list: list[PairJob]) -> Counter[str]:
    return Counter(scan for j in job_list for scan in (j.source, j.target))


def plot_pair(
    settings: JobSettings,
    manifest: Manifest,
    plot: Plot,
    pair: tuple[str, str],
    placed: dict[str, np.ndarray],
) -> PairJob:
    """The job of two scans of `plot`, the later of them in the plot as the source, its prior from
    the `placed` poses."""
    by_id = {s.id: s for s in plot.scans}
    order = {s.id: k for k, s in enumerate(plot.scans)}
    target, source = sorted(pair, key=order.get)
    sides = ScanFile.of(manifest, by_id[source]), ScanFile.of(manifest, by_id[target])
    return pair_job(settings, *sides, prior(placed, source, target))


def graph_poses(
    manifest: Manifest, config: RegisterConfig, pairs: Pairs, anchors: dict[str, list[dict]]
) -> dict[str, np.ndarray]:
    """scan id -> its pose in its plot's frame, from the pose graph of the pairs and maps so far
    (and the ALS anchors): what the verified edges place, after the graph's own outlier checks."""
    G = build_graph({s.id: {} for s in manifest.scans}, pairs.edges())
    poses: dict[str, np.ndarray] = {}
    for plot in manifest.plots:
        poses.update(solve_plot(G, plot, anchors.get(plot.id, []), config)[1].poses)
    return poses


def position_jobs(
    manifest: Manifest,
    config: RegisterConfig,
    settings: JobSettings,
    poses: dict[str, np.ndarray],
    job_list: list[PairJob],
) -> list[PairJob]:
    """Neighbour pairs of a big plot's scans that the pose graph places (graph_poses), not tried yet:
    at most `reach` x the scan spacing apart, their prior from the graph and verified first (a chain
    of verified pairs is as good a prior as two ALS placements), at most `max_per_scan` pairs a scan."""
    reach = config.placed_priors.reach
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
        for i, j in neighbour_pairs(xy, config.pairs.neighbours, cap, far):
            a, b = ids[i], ids[j]
            if frozenset((a, b)) in tried or max(degree[a], degree[b]) >= cap:
                continue
            out.append(plot_pair(settings, manifest, plot, (a, b), poses))
            tried.add(frozenset((a, b)))
            degree.update((a, b))
    return with_stored_poses(out, set(poses))


def grow_jobs(
    manifest: Manifest,
    config: RegisterConfig,
    settings: JobSettings,
    placed: dict[str, np.ndarray],
    ranks: dict[str, list[str]],
    pairs: Pairs,
    anchored: set[str] | None = None,
) -> list[PairJob]:
    """Pairs to add where a plot's verified `pairs` leave it in pieces: the next signature-ranked
    partners. `anchored`: scans held by an ALS anchor (one piece with each other through the plot's
    ALS node)."""
    sig = config.signature
    tried = {frozenset((j.source, j.target)) for j in pairs.jobs}
    degree = _degrees(pairs.jobs)
    G = nx.Graph()
    for j in pairs.jobs:
        if pairs.records.get(j.key, {}).get("status") == "ok":
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
        for pair in grow_candidates(
            ranks, tried, comps, degree, sig.grow_per_scan, config.pairs.max_per_scan
        ):
            out.append(plot_pair(settings, manifest, plot, pair, placed))
    return out


def _signature_round(
    run: Run, priors: Priors, ranks: dict[str, list[str]], pairs: Pairs
) -> list[PairJob]:
    """The next signature-ranked partners where a plot is still in pieces."""
    anchored = priors.from_als if run.config.als_anchors else set()
    jobs = grow_jobs(run.manifest, run.config, run.settings, priors.placed, ranks, pairs, anchored)
    return with_stored_poses(jobs, priors.verify_first)


def from_graph(
    jobs: list[PairJob], poses: dict[str, np.ndarray], only: frozenset[str] = frozenset()
) -> list[PairJob]:
    """Jobs between scans the graph places, their prior the pose it implies, verified first (and
    only verified between two scans the ALS placed: their maps will do what a search could)."""
    placed = [j for j in jobs if j.source in poses and j.target in poses]
    rebased = [pair_job(j.settings, *j.sides, prior(poses, j.source, j.target)) for j in placed]
    return with_stored_poses(with_stored_poses(rebased, set(only), start="only"), set(poses))


def joining(jobs: list[PairJob], poses: dict[str, np.ndarray], pairs: Pairs) -> list[PairJob]:
    """Jobs, in their order, that join what the graph leaves apart (the placed scans are one piece;
    the others are joined by their verified pairs), one job for each join, as a spanning tree."""
    placed = sorted(poses)
    joined = list(zip(placed, placed[1:]))
    joined += [
        (j.source, j.target)
        for j in pairs.jobs
        if pairs.records.get(j.key, {}).get("status") == "ok"
        and j.source not in poses
        and j.target not in poses
    ]
    picked = spanning_first([(j.source, j.target) for j in jobs], joined)
    return [jobs[k] for k in picked]


def next_round(
    deferred: list[PairJob],
    poses: dict[str, np.ndarray],
    pairs: Pairs,
    only: frozenset[str] = frozenset(),
    verify_first: set[str] | frozenset[str] = frozenset(),
) -> list[PairJob]:
    """The deferred jobs to run now: those between scans the graph places, from its poses
    (`from_graph`), and beside them one job for each join of what it leaves apart (`joining`, as the
    tree's jobs): a pair between placed scans cannot place another, so the joins need not wait."""
    loops = from_graph(deferred, poses, only)
    running = {(j.source, j.target) for j in loops}
    rest = [j for j in deferred if (j.source, j.target) not in running]
    return loops + with_stored_poses(joining(rest, poses, pairs), verify_first)


def close_loops(run: Run, priors: Priors, deferred: list[PairJob], pairs: Pairs) -> Pairs:
    """The planned pairs beyond the spanning tree (`deferred`, plain jobs), in rounds: each pair
    between scans the verified graph places starts from the pose the graph implies and is verified
    from there (the fine ICP and the judge), the global search only when that fails; where the tree
    left scans apart, one pair for each join runs as the tree's did, then the loop pairs it makes.
    Pairs inside a piece the graph never places are not run (they could place nothing)."""
    only = frozenset(priors.from_als) if run.config.maps.enabled else frozenset()
    while deferred:
        poses = graph_poses(run.manifest, run.config, pairs, priors.anchors)
        ready = next_round(deferred, poses, pairs, only, priors.verify_first)
        if not ready:
            return pairs
        running = {(j.source, j.target) for j in ready}
        deferred = [j for j in deferred if (j.source, j.target) not in running]
        pairs = run_jobs(run, ready, pairs)
    return pairs


def grow(run: Run, priors: Priors, ranks: dict[str, list[str]], pairs: Pairs) -> Pairs:
    """The plan grown in bounded rounds: neighbour pairs of the scans the verified graph places
    (priors verified first), else, where a plot is still in pieces, the next signature partners."""
    grows = run.config.signature.grow_rounds if ranks else 0
    positions = run.config.placed_priors.position_rounds
    while True:
        more = []
        if positions:
            poses = graph_poses(run.manifest, run.config, pairs, priors.anchors)
            more = position_jobs(run.manifest, run.config, run.settings, poses, pairs.jobs)
            positions -= bool(more)
        if not more and grows:
            grows -= 1
            more = _signature_round(run, priors, ranks, pairs)
        if not more:
            return pairs
        pairs = run_jobs(run, more, pairs)

"""Plan: the pair jobs of every plot, by position, by signature where scans have no position; a
spanning tree of them runs first (grow.close_loops runs the rest from the poses the tree implies)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.executor import Workers, run_pairs
from plotmosaic.graph.jobs import (
    JobSettings,
    PairJob,
    ScanFile,
    pair_job,
    prepare_job,
    with_stored_poses,
)
from plotmosaic.graph.pairs import candidate_pairs, manifest_positions, spanning_first
from plotmosaic.graph.placement import prior
from plotmosaic.graph.signature import (
    SignatureJob,
    from_record,
    ranked_partners,
    run_signature_job,
    signature_pairs,
    similarity,
)
from plotmosaic.manifest import Manifest
from plotmosaic.stages.register_plot.pairs import Run, pair_settings
from plotmosaic.stages.register_plot.place import Priors


@dataclass(frozen=True, kw_only=True)
class Plan:
    """The first pair jobs (a spanning tree of the planned pairs), the rest (`deferred`, plain jobs:
    their priors come from the tree's poses), and the signature ranks the grow rounds draw from."""

    jobs: list[PairJob]
    deferred: list[PairJob]
    ranks: dict[str, list[str]]  # scan id -> other scans of its plot ranked by signature


def plan_jobs(
    manifest: Manifest,
    config: RegisterConfig,
    settings: JobSettings,
    placed: dict[str, np.ndarray] | None = None,
    linked: dict[str, list[tuple[str, str]]] | None = None,
) -> list[PairJob]:
    """The pair jobs of every plot (`settings`: what they share, pairs.pair_settings);
    `placed`: scan poses from the ALS step (positions for the pair selection, priors for the coarse stage);
    `linked`: plot id -> pairs of scans whose signatures match (pairs for scans without a position)."""
    placed = placed or {}
    linked = linked or {}
    reach = config.placed_priors.reach
    jobs = []
    for plot in manifest.plots:
        positions = {s.id: placed[s.id][:3, 3] for s in plot.scans if s.id in placed} or None
        for source, target in candidate_pairs(
            plot, config.max_distance, positions, config.pairs, linked.get(plot.id), reach
        ):
            sides = ScanFile.of(manifest, source), ScanFile.of(manifest, target)
            jobs.append(pair_job(settings, *sides, prior(placed, source.id, target.id)))
    return jobs


def _signature_jobs(
    manifest: Manifest, config: RegisterConfig, seed: int, out: Path, plots: list
) -> dict[str, SignatureJob]:
    """scan id -> its signature job, for every scan of these plots."""
    settings = pair_settings(config, seed, out / "prepared")
    jobs = {}
    for plot in plots:
        for scan in plot.scans:
            pj = prepare_job(settings, ScanFile.of(manifest, scan))
            jobs[scan.id] = SignatureJob.of(pj, config.signature)
    return jobs


def match_signatures(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    out: Path,
    placed: dict[str, np.ndarray],
    workers: Workers = Workers(),
) -> tuple[dict[str, list[tuple[str, str]]], dict[str, list[str]]]:
    """Big plots where some scan has no position: every scan's stem-map signature (graph/signature.py).

    Returns (plot id -> linked scan pairs, scan id -> other scans of its plot ranked by signature).
    The scans are prepared here, into the cache their pairs load from (each still read once)."""
    sig = config.signature
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
    jobs = _signature_jobs(manifest, config, seed, out, plots)
    records = run_pairs(
        list(jobs.values()), workers, worker=run_signature_job, label="scan signatures"
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


def tree_first(
    manifest: Manifest,
    jobs: list[PairJob],
    placed: dict[str, np.ndarray],
    verify_first: set[str],
    verify_only: frozenset[str] = frozenset(),
) -> tuple[list[PairJob], list[PairJob]]:
    """(first, deferred): a spanning forest of each plot's planned pairs, verified priors first, then
    the nearest scans (ALS placements or stored poses, else the manifest's positions), else in the
    plan's order (a small plot without positions: a star around its first scan); the other pairs,
    plain and in that order, start from the poses the tree implies. A pair of two `verify_first`
    scans is verified at its prior before any search; of two `verify_only` scans (placed on the ALS),
    verified there and never searched (a search finds no more than its maps will)."""
    approx = {}
    for plot in manifest.plots:
        approx.update(manifest_positions(plot) or {})
    xyz = {i: T[:3, 3] for i, T in placed.items()}
    marked = with_stored_poses(with_stored_poses(jobs, verify_first), verify_only, start="only")

    def rank(k: int) -> tuple[bool, float]:
        a, b = jobs[k].source, jobs[k].target
        d = np.inf  # positions of a plot's scans are compared within one source (one frame)
        for where in (xyz, approx):
            if a in where and b in where:
                d = np.linalg.norm(np.subtract(where[a], where[b]))
                break
        return marked[k].start == "prior", float(d)

    order = sorted(range(len(jobs)), key=rank)
    tree = {order[k] for k in spanning_first([(jobs[i].source, jobs[i].target) for i in order])}
    return [marked[i] for i in order if i in tree], [jobs[i] for i in order if i not in tree]


def plan(run: Run, priors: Priors) -> Plan:
    """The pair jobs: candidate pairs by position, signature links where there is none; a spanning
    tree of them first."""
    linked, ranks = match_signatures(
        run.manifest, run.config, run.seed, run.out, priors.placed, run.workers
    )
    jobs = plan_jobs(run.manifest, run.config, run.settings, priors.placed, linked)
    only = frozenset(priors.from_als) if run.config.maps.enabled else frozenset()
    first, deferred = tree_first(run.manifest, jobs, priors.placed, priors.verify_first, only)
    return Plan(jobs=first, deferred=deferred, ranks=ranks)

"""Pair jobs run through a pair cache: their scans prepared first (one job per scan), then the pairs
not cached yet (register-plot's steps and tie-to-als alike)."""

from __future__ import annotations

from collections.abc import Callable

from plotmosaic.graph.cache import PairCache
from plotmosaic.graph.executor import Workers, run_pairs
from plotmosaic.graph.jobs import PairJob, failed_pair, prepare_jobs_for
from plotmosaic.graph.prepared import PrepareJob, entry, run_prepare_job

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
    "via",
)


def prepare_scans(jobs: list[PairJob], workers: Workers = Workers()) -> dict[str, dict]:
    """Read and prepare every scan these pairs need, once each, into their prepared-cloud cache.

    Returns the failed preparations by prepared key (their pairs are not run)."""
    unique: dict[str, PrepareJob] = {}
    for job in jobs:
        if job.prepared:
            for pj in prepare_jobs_for(job):
                unique.setdefault(pj.key, pj)
    return run_prepare_jobs(list(unique.values()), workers)


def run_prepare_jobs(jobs: list[PrepareJob], workers: Workers) -> dict[str, dict]:
    """Run the prepare jobs whose cache entry is missing; the failed records by prepared key."""
    todo = [pj for pj in jobs if not entry(pj.folder, pj.key).is_file()]
    # entries already on disk are checked when loaded (a damaged one is prepared again there)
    records = run_pairs(todo, workers, worker=run_prepare_job, label="preparing scans")
    return {r["key"]: r for r in records if r.get("status") != "ok"}


def compute_pairs(
    jobs: list[PairJob],
    cache: PairCache,
    workers: Workers = Workers(),
    force: bool = False,
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

    failed = prepare_scans(todo, workers)
    runnable = []
    for job in todo:
        bad = (
            [failed[pj.key] for pj in prepare_jobs_for(job) if pj.key in failed]
            if job.prepared
            else []
        )
        # the scan itself cannot be used: its error, not a registration failure (not cached)
        if bad:
            keep(failed_pair(job, f"scan {bad[0]['scan']}: {bad[0].get('error')}"))
        else:
            runnable.append(job)
    run_pairs(runnable, workers, keep)
    return records, computed

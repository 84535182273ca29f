"""What every register-plot step shares: the run's settings, pair jobs, preparing scans, running pairs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plotmosaic.config.reading import ReadingConfig
from plotmosaic.config.register import RegisterConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.cache import PairCache, pair_key
from plotmosaic.graph.executor import PairJob, Workers, prepare_jobs_for, run_pairs, with_reading
from plotmosaic.graph.placement import prior
from plotmosaic.graph.prepared import PrepareJob, entry, prepared_key, run_prepare_job
from plotmosaic.manifest import Manifest, Plot, Scan, load_manifest

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


@dataclass(frozen=True, kw_only=True)
class Run:
    """One register-plot run: what it registers, where to, with which settings and workers."""

    manifest: Manifest
    config: RegisterConfig
    out: Path
    cache: PairCache
    seed: int
    workers: Workers
    force: bool
    on_result: Callable[[dict], None] | None

    @property
    def prepared(self) -> Path:
        """The prepared-cloud cache every step loads scans from."""
        return self.out / "prepared"


@dataclass(frozen=True, kw_only=True)
class Pairs:
    """The pair jobs run so far, their records by key, and how many were computed (not cached);
    `maps`: the edges of the latest map placements (stages/register_plot/maps.py)."""

    jobs: list[PairJob]
    records: dict[str, dict]
    computed: int
    maps: tuple[dict, ...] = ()

    def edges(self) -> list[dict]:
        """Every pair that ran as an edge record (failed ones too: the graph keeps them apart),
        then the map edges."""
        pairs = [
            {k: self.records[j.key].get(k) for k in EDGE_FIELDS}
            for j in self.jobs
            if j.key in self.records
        ]
        return pairs + list(self.maps)


def start_run(
    manifest: str | Path | Manifest,
    out: str | Path,
    config: RegisterConfig | None,
    *,
    seed: int,
    workers: Workers,
    force: bool,
    on_result: Callable[[dict], None] | None,
) -> Run:
    """The run's manifest and settings loaded, its output folder checked (a file there is refused)."""
    config = config or RegisterConfig()
    manifest = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a folder")
    return Run(
        manifest=manifest,
        config=config,
        out=out,
        cache=PairCache(out / "pairs"),
        seed=seed,
        workers=workers,
        force=force,
        on_result=on_result,
    )


def run_jobs(run: Run, jobs: list[PairJob], so_far: Pairs | None = None) -> Pairs:
    """`so_far` and these jobs, run through the run's pair cache."""
    records, computed = compute_pairs(jobs, run.cache, run.workers, run.force, run.on_result)
    if so_far is None:
        return Pairs(jobs=list(jobs), records=records, computed=computed)
    return Pairs(
        jobs=[*so_far.jobs, *jobs],
        records={**so_far.records, **records},
        computed=so_far.computed + computed,
        maps=so_far.maps,
    )


def _pair_job(
    manifest: Manifest,
    source: Scan,
    target: Scan,
    config_json: str,
    seed: int,
    prepared: str | None,
    placed: dict[str, np.ndarray],
    reading: ReadingConfig | None = None,
) -> PairJob:
    """The pair's job, its scans read within `reading` (None: the default budget)."""
    sp, tp = manifest.resolve(source.path), manifest.resolve(target.path)
    key = pair_key(
        sp, tp, source.kind.value, target.kind.value, source.k, target.k, config_json, seed
    )
    job = PairJob(
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
    return with_reading([job], reading or ReadingConfig())[0]


def anchor_id(plot: Plot) -> str:
    """The ALS node of a plot's pose graph (never a scan: ids with '@' are not written to poses)."""
    return f"ALS@{plot.id}"


def prepare_scans(jobs: list[PairJob], workers: Workers = Workers()) -> dict[str, dict]:
    """Read and prepare every scan these pairs need, once each, into their prepared-cloud cache.

    Returns the failed preparations by prepared key (their pairs are not run)."""
    unique: dict[str, PrepareJob] = {}
    for job in jobs:
        if job.prepared:
            for pj in prepare_jobs_for(job):
                unique.setdefault(pj.key, pj)
    return _prepare(list(unique.values()), workers)


def _prepare(jobs: list[PrepareJob], workers: Workers) -> dict[str, dict]:
    """Run the prepare jobs whose cache entry is missing; the failed records by prepared key."""
    todo = [pj for pj in jobs if not entry(pj.folder, pj.key).is_file()]
    # entries already on disk are checked when loaded (a damaged one is prepared again there)
    records = run_pairs(todo, workers, worker=run_prepare_job, label="preparing scans")
    return {r["key"]: r for r in records if r.get("status") != "ok"}


def prepare_every_scan(
    manifest: Manifest,
    config: RegisterConfig,
    seed: int,
    folder: Path,
    workers: Workers = Workers(),
) -> None:
    """Read and prepare every scan of the manifest before any pair runs (into the cache the pairs
    load from): a scan that cannot be read stops the run here, named, instead of leaving it unplaced."""
    settings = config.align.model_dump_json()
    jobs = {}
    for plot in manifest.plots:
        for scan in plot.scans:
            path = str(manifest.resolve(scan.path))
            kind = scan.kind.value
            key = prepared_key(path, kind, scan.k, settings, seed, config.read)
            jobs[key] = PrepareJob(
                key, scan.id, path, kind, scan.k, settings, seed, str(folder), reading=config.read
            )
    for key, record in _prepare(list(jobs.values()), workers).items():
        pj = jobs[key]
        cause = str(record.get("error", "")).removeprefix("InputError: ")
        cause = cause.removeprefix(f"{pj.path}: ")
        raise InputError(f"{pj.path}: scan {pj.scan!r} cannot be used ({cause})")


def prepare(run: Run) -> None:
    """Every scan of the run prepared before any pair (a scan that cannot be read stops it, named)."""
    prepare_every_scan(run.manifest, run.config, run.seed, run.prepared, run.workers)


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
    run_pairs(runnable, workers, keep)
    return records, computed

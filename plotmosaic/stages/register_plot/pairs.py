"""What every register-plot step shares: the run's settings, its pair jobs, preparing scans, running pairs."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from plotmosaic.config.register import RegisterConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.cache import PairCache
from plotmosaic.graph.compute import EDGE_FIELDS, compute_pairs, run_prepare_jobs
from plotmosaic.graph.executor import Workers
from plotmosaic.graph.jobs import JobSettings, PairJob, ScanFile, prepare_job
from plotmosaic.manifest import Manifest, Plot, load_manifest


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

    @property
    def settings(self) -> JobSettings:
        """What the run's scan-to-scan pair jobs share."""
        return pair_settings(self.config, self.seed, self.prepared)


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


def pair_settings(config: RegisterConfig, seed: int, prepared: str | Path | None) -> JobSettings:
    """What every scan-to-scan pair job of a run shares (`prepared`: DIR/prepared, None: in the worker)."""
    return JobSettings(config.align, seed, None if prepared is None else str(prepared), config.read)


def anchor_id(plot: Plot) -> str:
    """The ALS node of a plot's pose graph (never a scan: ids with '@' are not written to poses)."""
    return f"ALS@{plot.id}"


def prepare(run: Run) -> None:
    """Every scan of the run read and prepared before any pair runs (into the cache the pairs load
    from): a scan that cannot be read stops the run here, named, instead of leaving it unplaced."""
    jobs = {}
    for scan in run.manifest.scans:
        pj = prepare_job(run.settings, ScanFile.of(run.manifest, scan))
        jobs[pj.key] = pj
    for key, record in run_prepare_jobs(list(jobs.values()), run.workers).items():
        pj = jobs[key]
        cause = str(record.get("error", "")).removeprefix("InputError: ")
        cause = cause.removeprefix(f"{pj.path}: ")
        raise InputError(f"{pj.path}: scan {pj.scan!r} cannot be used ({cause})")

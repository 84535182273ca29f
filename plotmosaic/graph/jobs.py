"""A pair job, made in one place: `pair_job` computes its key once, from all that determines its result.

Stages ask for a job and never rewrite one: a job started otherwise (a verified pose, a new prior)
is asked for again. The job carries its settings as typed objects; they pickle to any worker
process or Dask machine as they are.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field

from plotmosaic import __version__
from plotmosaic.config.align import AlignConfig
from plotmosaic.config.reading import ReadingConfig
from plotmosaic.errors import InputError
from plotmosaic.graph.cache import file_hash, settings_json
from plotmosaic.graph.prepared import PrepareJob, prepared_key
from plotmosaic.io.bounded import over_budget
from plotmosaic.manifest import Manifest, Scan


@dataclass(frozen=True)
class ScanFile:
    """One side of a pair: the scan's id, file, kind and levels."""

    id: str
    path: str
    kind: str
    levels: int | None

    @classmethod
    def of(cls, manifest: Manifest, scan: Scan) -> ScanFile:
        return cls(scan.id, str(manifest.resolve(scan.path)), scan.kind.value, scan.k)


@dataclass(frozen=True)
class JobSettings:
    """What the pair jobs of a step share: the align settings, the seed, the prepared-cloud folder
    (DIR/prepared; None: prepared in the worker), the reading budget, and the settings the scans
    are prepared with when not `config` (the ALS placement registers with its own)."""

    config: AlignConfig
    seed: int
    prepared: str | None = None
    reading: ReadingConfig = field(default_factory=ReadingConfig)
    prepare: AlignConfig | None = None


@dataclass(frozen=True)
class PairJob:
    """Everything a worker needs to register one pair (plain data: pickles to any process or
    machine); made by `pair_job`, with its key."""

    key: str
    source: str  # scan ids
    target: str
    source_path: str
    target_path: str
    source_kind: str
    target_kind: str
    levels_source: int | None
    levels_target: int | None
    config: AlignConfig
    seed: int
    # DIR/prepared: the prepared-cloud cache shared by every pair and run
    prepared: str | None = None
    init: tuple | None = None  # 4x4 rows, source file -> target file: a prior for the coarse stage
    prepare: AlignConfig | None = None  # settings the scans are prepared with, when not `config`
    start: str = "prior"  # how `init` is used (align Start): "stored" (poses stored in the scan
    # files, E57 use_pose, sure placements, the graph's: verified first, the search skipped when
    # it holds), "only" (two ALS placements: verified, refused when it does not hold)
    reading: ReadingConfig = field(default_factory=ReadingConfig, kw_only=True)

    @property
    def sides(self) -> tuple[ScanFile, ScanFile]:
        return (
            ScanFile(self.source, self.source_path, self.source_kind, self.levels_source),
            ScanFile(self.target, self.target_path, self.target_kind, self.levels_target),
        )

    @property
    def settings(self) -> JobSettings:
        return JobSettings(self.config, self.seed, self.prepared, self.reading, self.prepare)


def pair_job(
    settings: JobSettings,
    source: ScanFile,
    target: ScanFile,
    init: tuple | None = None,
    start: str = "prior",
) -> PairJob:
    """The job registering `source` onto `target`, from `init` as `start` says (a prior: "prior")."""
    return PairJob(
        job_key(settings, source, target, init, start),
        source.id,
        target.id,
        source.path,
        target.path,
        source.kind,
        target.kind,
        source.levels,
        target.levels,
        settings.config,
        settings.seed,
        settings.prepared,
        init,
        settings.prepare,
        start,
        reading=settings.reading,
    )


def job_key(
    settings: JobSettings, source: ScanFile, target: ScanFile, init: tuple | None, start: str
) -> str:
    """The pair cache's key of a job: both files' contents, kinds and levels, the align settings,
    the seed and the version; then the reading budget when it thins either scan, and the verified
    pose when the job starts from one (a result found otherwise is another pair result). A plain
    prior is no part of it."""
    parts = {
        "source": file_hash(source.path),
        "target": file_hash(target.path),
        "kinds": [source.kind, target.kind],
        "levels": [source.levels, target.levels],
        "config": json.loads(settings_json(settings.config)),
        "seed": settings.seed,
        "version": __version__,
    }
    key = hashlib.sha256(json.dumps(parts, sort_keys=True).encode()).hexdigest()[:32]
    if _thins(source.path, settings.reading) or _thins(target.path, settings.reading):
        budget = hashlib.sha256(settings_json(settings.reading).encode()).hexdigest()[:12]
        key = f"{key}-read-{budget}"
    if start != "prior":
        pose = hashlib.sha256(json.dumps(init).encode()).hexdigest()[:12]
        tag = "stored" if start == "stored" else f"stored-{start}"
        key = f"{key}-{tag}-{pose}"
    return key


def _thins(path: str, reading: ReadingConfig) -> bool:
    try:
        return over_budget(path, reading)
    except InputError:  # unreadable: its prepare job fails and names it, the pair is not run
        return False


def with_stored_poses(
    jobs: list[PairJob], scans: set[str] | frozenset[str], start: str = "stored"
) -> list[PairJob]:
    """The jobs, those whose two scans' priors are verified poses (`Manifest.stored_poses`, sure
    placements, the graph's) asked for again, verified first as `start` says; a job marked already
    keeps its mark."""
    return [
        pair_job(job.settings, *job.sides, job.init, start)
        if job.init is not None and job.start == "prior" and {job.source, job.target} <= scans
        else job
        for job in jobs
    ]


def failed_pair(job: PairJob, error: str) -> dict:
    """The record of a pair that could not be registered for a reason outside the pair (a scan
    that cannot be used, a lost worker): not cached, the next run tries again."""
    record = {"source": job.source, "target": job.target, "key": job.key, "status": "failed"}
    return {**record, "error": error, "cacheable": False}


def prepare_job(settings: JobSettings, scan: ScanFile, folder: str | None = None) -> PrepareJob:
    """The scan's prepare job, into `folder` (else the settings' prepared-cloud folder): each scan
    is prepared once with the run's seed, whatever its role."""
    config = settings.prepare or settings.config
    key = prepared_key(scan.path, scan.kind, scan.levels, config, settings.seed, settings.reading)
    return PrepareJob(
        key,
        scan.id,
        scan.path,
        scan.kind,
        scan.levels,
        config,
        settings.seed,
        folder or settings.prepared,
        reading=settings.reading,
    )


def prepare_jobs_for(job: PairJob, folder: str | None = None) -> tuple[PrepareJob, PrepareJob]:
    """The two scans' prepare jobs (in `folder`, else the job's prepared-cloud folder)."""
    source, target = job.sides
    return prepare_job(job.settings, source, folder), prepare_job(job.settings, target, folder)

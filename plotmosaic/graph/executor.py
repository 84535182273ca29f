"""Run pair registrations in parallel: a local process pool or a Dask distributed cluster.

Results come back to the calling process one by one (`on_result`), which writes the cache, so
whatever finished before an interruption is kept. A pair that fails becomes a failed record, never
a crash of the whole run. The scheduling itself is concurrent.futures' or Dask's, not ours.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from plotmosaic.errors import InputError, RegistrationFailed
from plotmosaic.graph.cache import file_hash


@dataclass(frozen=True)
class PairJob:
    """Everything a worker needs to register one pair (plain data: pickles to any process or machine)."""

    key: str
    source: str  # scan ids
    target: str
    source_path: str
    target_path: str
    source_kind: str
    target_kind: str
    levels_source: int | None
    levels_target: int | None
    config_json: str
    seed: int


# Prepared clouds (voxels, normals, levels) of this worker process, so a scan that takes part in
# several pairs is prepared once per role instead of once per pair. Small: memory stays bounded.
_PREPARED: OrderedDict[tuple, object] = OrderedDict()
_PREPARED_MAX = 6


def _prepared(path: str, kind: str, levels: int | None, config, config_json: str, seed: int, role: str):
    from plotmosaic.align.config import default_levels
    from plotmosaic.align.prepare import prepare_cloud
    from plotmosaic.io.las import read_cloud

    memo = (file_hash(path), kind, levels, config_json, seed, role)
    if memo in _PREPARED:
        _PREPARED.move_to_end(memo)
        return _PREPARED[memo], 0.0
    start = time.perf_counter()
    cloud = read_cloud(path, attributes=False)
    prepared = prepare_cloud(cloud, kind, levels or default_levels(kind), config, seed, role)
    _PREPARED[memo] = prepared
    while len(_PREPARED) > _PREPARED_MAX:
        _PREPARED.popitem(last=False)
    return prepared, time.perf_counter() - start


def run_pair_job(job: PairJob) -> dict:
    """Register one pair with ForestAlign; a record with status "ok" (PairResult fields) or "failed".

    Same stages and seeds as plotmosaic.align.pipeline.align_files (source prepared with `seed`,
    target with `seed + 1`), with the prepared clouds memoised per worker process.
    """
    from plotmosaic.align.config import AlignConfig
    from plotmosaic.align.pipeline import register_prepared

    start = time.perf_counter()
    record = {"source": job.source, "target": job.target, "key": job.key}
    try:
        config = AlignConfig.model_validate_json(job.config_json)
        src, t_src = _prepared(job.source_path, job.source_kind, job.levels_source, config, job.config_json, job.seed, "source")
        tgt, t_tgt = _prepared(job.target_path, job.target_kind, job.levels_target, config, job.config_json, job.seed + 1, "target")
        result = register_prepared(src, tgt, config, None, job.seed)
        result.timings = {"prepare_source": t_src, "prepare_target": t_tgt, **result.timings}
        record.update(result.to_dict(), status="ok")
    except RegistrationFailed as exc:  # a real outcome of this pair: cache it, with its figures
        record.update(status="failed", error=str(exc), cacheable=True)
        res = getattr(exc, "result", None)
        if res is not None:
            record.update(fitness=res.fitness, inlier_rmse=res.inlier_rmse, overlap=res.overlap, confidence=res.confidence)
    except Exception as exc:  # bad file, out of memory, a bug: record it, retry on the next run
        record.update(status="failed", error=f"{type(exc).__name__}: {exc}", cacheable=False)
    record["seconds"] = time.perf_counter() - start
    return record


def _limit_threads() -> None:
    # Several workers on few cores: one thread each, set before numpy/open3d are imported.
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    from plotmosaic.parallel import set_threads

    set_threads(1)  # the pool is the parallelism: no two-thread maps or multi-thread queries inside


def _progress(enabled: bool) -> Progress:
    return Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
        disable=not enabled, transient=False,
    )


def _failed(job, exc: BaseException) -> dict:
    return {"source": job.source, "target": job.target, "key": job.key, "status": "failed",
            "error": f"{type(exc).__name__}: {exc}", "cacheable": False}


def run_pairs(
    jobs: Sequence[PairJob],
    on_result: Callable[[dict], None] | None = None,
    executor: str = "local",
    n_jobs: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
    worker: Callable[[PairJob], dict] = run_pair_job,
) -> list[dict]:
    """Run `worker` on every job; `on_result(record)` is called in this process as each one finishes."""
    if executor not in ("local", "dask"):
        raise InputError(f"--executor must be 'local' or 'dask', not {executor!r}")
    if not jobs:
        return []
    records: list[dict] = []

    def done(record: dict) -> None:
        records.append(record)
        if on_result is not None:
            on_result(record)

    with _progress(progress) as bar:
        task = bar.add_task("registering pairs", total=len(jobs))

        def tick(record: dict) -> None:
            done(record)
            bar.advance(task)

        if executor == "dask":
            _run_dask(jobs, tick, n_jobs, scheduler, worker)
        else:
            _run_local(jobs, tick, n_jobs, worker)
    return records


def _run_local(jobs, tick, n_jobs, worker) -> None:
    n_jobs = n_jobs or os.cpu_count() or 1
    if n_jobs == 1 or len(jobs) == 1:
        for job in jobs:
            tick(worker(job))
        return
    # spawn: Open3D and BLAS thread pools do not survive fork reliably
    pool = ProcessPoolExecutor(min(n_jobs, len(jobs)), mp_context=multiprocessing.get_context("spawn"), initializer=_limit_threads)
    try:
        pending = {pool.submit(worker, job): job for job in jobs}
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                job = pending.pop(fut)
                try:
                    record = fut.result()
                except Exception as exc:  # the worker process died (e.g. killed for memory)
                    record = _failed(job, exc)
                tick(record)
    except BaseException:
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.terminate()  # a pair already running would otherwise finish after Ctrl-C
        raise
    pool.shutdown(wait=True)


def _run_dask(jobs, tick, n_jobs, scheduler, worker) -> None:
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:  # pragma: no cover - dask[distributed] is a dependency
        raise InputError("--executor dask needs dask[distributed] installed") from None
    cluster = None
    try:
        if scheduler:
            client = Client(scheduler, timeout="20s")
        else:  # no cluster given: a local one, same semantics as the process pool
            cluster = LocalCluster(n_workers=n_jobs or os.cpu_count() or 1, threads_per_worker=1, dashboard_address=None)
            client = Client(cluster)
    except (OSError, TimeoutError) as exc:
        raise InputError(f"--scheduler {scheduler}: cannot connect to the Dask scheduler ({exc})") from None
    futures = []
    try:
        futures = client.map(worker, list(jobs), key=[f"pair-{job.key}-{job.seed}" for job in jobs], pure=False)
        by_key = {f.key: job for f, job in zip(futures, jobs)}
        for fut in as_completed(futures):
            try:
                record = fut.result()
            except Exception as exc:  # worker lost, KilledWorker, ...
                record = _failed(by_key[fut.key], exc)
            tick(record)
    finally:
        if futures:
            client.cancel(futures)
        client.close()
        if cluster is not None:
            cluster.close()


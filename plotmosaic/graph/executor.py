"""Run pair registrations in parallel: a local process pool or a Dask distributed cluster.

Results come back to the calling process one by one (`on_result`), which writes the cache, so
whatever finished before an interruption is kept. A pair that fails becomes a failed record, never
a crash of the whole run. The scheduling itself is concurrent.futures' or Dask's, not ours.
"""

from __future__ import annotations

import atexit
import os
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from functools import partial

import numpy as np
from threadpoolctl import threadpool_limits

from plotmosaic.align.memo import RunMemo
from plotmosaic.align.pair import Start, register_prepared
from plotmosaic.errors import InputError, RegistrationFailed
from plotmosaic.graph import prepared as store
from plotmosaic.graph.jobs import PairJob, failed_pair, prepare_jobs_for
from plotmosaic.graph.prepared import PrepareJob, get_prepared
from plotmosaic.io.progress import progress_bar
from plotmosaic.lifetime import DeafSpawnContext, bind_to_parent
from plotmosaic.parallel import limited, set_threads

# Prepared clouds of this worker process when no cache folder is given (small: memory stays bounded).
_PREPARED: OrderedDict[tuple, object] = OrderedDict()
_PREPARED_MAX = 4


def _prepared_in_memory(job: PrepareJob):
    memo = (job.key, job.scan)
    if memo in _PREPARED:
        _PREPARED.move_to_end(memo)
        return _PREPARED[memo], 0.0
    start = time.perf_counter()
    prepared = store._compute(job)
    _PREPARED[memo] = prepared
    while len(_PREPARED) > _PREPARED_MAX:
        _PREPARED.popitem(last=False)
    return prepared, time.perf_counter() - start


# What the stages compute once per scan and role (the coarse stage's levelled sample is seeded per
# role), and per source scan its latest pair's global search and judged rivals (align/memo.py).
_MEMOS = RunMemo(max_clouds=2 * _PREPARED_MAX)


def run_pair_job(job: PairJob) -> dict:
    """Register one pair with `register_prepared` (the one pairwise path); a record with status "ok" or "failed".

    Both scans come from the prepared-cloud cache (`job.prepared`), computed there by whichever
    job needs them first; without a cache folder they are prepared in this process (memoised).
    """
    start = time.perf_counter()
    record = {"source": job.source, "target": job.target, "key": job.key}
    try:
        get = get_prepared if job.prepared else _prepared_in_memory
        ps, pt = prepare_jobs_for(job, job.prepared or "")
        src, t_src = get(ps)
        tgt, t_tgt = get(pt)
        init = None if job.init is None else np.asarray(job.init, dtype=np.float64)
        memo = _MEMOS.pair(ps.key, pt.key)
        result = register_prepared(
            src, tgt, job.config, init, job.seed, start=Start(job.start), memo=memo
        )
        record.update(result.to_dict(), status="ok")
        record["timings"] = {"prepare_source": t_src, "prepare_target": t_tgt, **result.timings}
    except RegistrationFailed as exc:  # a real outcome of this pair: cache it, with its figures
        record.update(status="failed", error=str(exc), cacheable=True)
        res = getattr(exc, "result", None)
        if res is not None:
            record.update(
                fitness=res.fitness,
                inlier_rmse=res.inlier_rmse,
                overlap=res.overlap,
                confidence=res.confidence,
            )
            if np.isfinite(res.transform).all():  # never a pose: a start another check may verify
                record["refused_transform"] = np.asarray(res.transform, dtype=float).tolist()
    except Exception as exc:  # bad file, out of memory, a bug: record it, retry on the next run
        record.update(status="failed", error=f"{type(exc).__name__}: {exc}", cacheable=False)
    record["seconds"] = time.perf_counter() - start
    return record


def _limit_threads(n: int = 1, most: int | None = None) -> None:
    """Pool initializer: this worker's share of the thread budget for BLAS, set before numpy/open3d
    are imported; `most`, the run's whole budget, is what a job may be given (call_with_threads)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = str(n)
    set_threads(most or n)  # two-thread maps and KD-tree queries take what their job is given
    bind_to_parent()  # a SIGKILLed run leaves no orphaned workers


def budget(n_jobs: int | None) -> int:
    """The run's thread budget: `--jobs` when given, else the cores (never more threads than that)."""
    return max(1, n_jobs or os.cpu_count() or 1)


def split(n_jobs: int | None, n_tasks: int) -> tuple[int, int]:
    """(worker processes, threads per worker) sharing the budget: processes first (pairs are independent)."""
    total = budget(n_jobs)
    workers = max(1, min(total, n_tasks))
    return workers, max(1, total // workers)


def call_with_threads(threads: int, worker: Callable, job):
    """`worker(job)` within a thread budget (Dask workers: no initializer of ours runs there)."""
    with limited(threads), threadpool_limits(threads):
        return worker(job)


def _failed(job, exc: BaseException) -> dict:
    error = f"{type(exc).__name__}: {exc}"
    if isinstance(job, PrepareJob):
        return {
            "key": job.key,
            "scan": job.scan,
            "kind": "prepare",
            "status": "failed",
            "error": error,
        }
    return failed_pair(job, error)


@dataclass(frozen=True)
class Workers:
    """Where a run's jobs run: `executor` "local" (a process pool) or "dask" (at `scheduler`, else a
    local cluster), with `jobs` threads in all (None: the cores), a progress bar or not."""

    executor: str = "local"
    jobs: int | None = None
    scheduler: str | None = None
    progress: bool = True


def run_pairs(
    jobs: Sequence[PairJob],
    workers: Workers = Workers(),
    on_result: Callable[[dict], None] | None = None,
    worker: Callable[[PairJob], dict] = run_pair_job,
    label: str = "registering pairs",
) -> list[dict]:
    """Run `worker` on every job; `on_result(record)` is called in this process as each one finishes."""
    if workers.executor not in ("local", "dask"):
        raise InputError(f"--executor must be 'local' or 'dask', not {workers.executor!r}")
    if not jobs:
        return []
    records: list[dict] = []

    def done(record: dict) -> None:
        records.append(record)
        if on_result is not None:
            on_result(record)

    with progress_bar(workers.progress) as bar:
        task = bar.add_task(label, total=len(jobs))

        def tick(record: dict) -> None:
            done(record)
            bar.advance(task)

        if workers.executor == "dask":
            _run_dask(jobs, tick, workers.jobs, workers.scheduler, worker)
        else:
            _run_local(jobs, tick, workers.jobs, worker)
    return records


# The run's process pool, kept for its next stage with the same shape: preparing the scans and then
# registering their pairs use one spawn of the workers (each spawn imports numpy, scipy, ... anew)
# instead of two, and a worker's memo of the clouds it prepared or loaded serves its later pairs.
_POOL: dict[tuple[int, int, int], ProcessPoolExecutor] = {}  # (workers, threads each, most a job)


def _pool(workers: int, per_worker: int, most: int) -> ProcessPoolExecutor:
    shape = (workers, per_worker, most)
    pool = _POOL.get(shape)
    if pool is not None and not getattr(pool, "_broken", False):
        return pool
    close_pool()
    # spawn: Open3D and BLAS thread pools do not survive fork reliably
    _POOL[shape] = pool = ProcessPoolExecutor(
        workers,
        mp_context=DeafSpawnContext(),
        initializer=_limit_threads,
        initargs=(per_worker, most),
    )
    return pool


def close_pool(kill: bool = False) -> None:
    """Shut the kept pool down (at exit, on a new shape, or killed after an interruption)."""
    for pool in _POOL.values():
        procs = list((getattr(pool, "_processes", None) or {}).values())
        if kill:  # SIGKILL: workers hold SIGINT / SIGTERM blocked, and a running pair would finish
            for proc in procs:
                proc.kill()
        pool.shutdown(wait=True, cancel_futures=kill)
    _POOL.clear()


atexit.register(close_pool)


def _run_local(jobs, tick, n_jobs, worker) -> None:
    workers, per_worker = split(n_jobs, len(jobs))
    if workers == 1:  # in this process, with the whole budget
        for job in jobs:
            tick(call_with_threads(budget(n_jobs), worker, job))
        return
    most = budget(n_jobs)
    try:
        pool = _pool(workers, per_worker, most)
        # a stage's last `workers` jobs get the whole budget: as the others end, the cores they free
        # would idle while the last jobs run alone (results do not depend on a job's threads). Only
        # when the budget is the whole machine: a smaller -j leaves the other cores to other work.
        tail = len(jobs) - workers if most >= (os.cpu_count() or 1) else len(jobs)
        pending = {
            pool.submit(call_with_threads, most if i >= tail else per_worker, worker, job): job
            for i, job in enumerate(jobs)
        }
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
        close_pool(kill=True)
        raise


def _kind(job) -> str:
    return "prepare" if isinstance(job, PrepareJob) else "pair"


def _run_dask(jobs, tick, n_jobs, scheduler, worker) -> None:
    try:  # deferred: dask is heavy and only --executor dask needs it
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:  # pragma: no cover - dask[distributed] is a dependency
        raise InputError("--executor dask needs dask[distributed] installed") from None
    cluster = None
    try:
        if scheduler:
            client = Client(scheduler, timeout="20s")
        else:  # no cluster given: a local one, same semantics as the process pool
            workers, per_worker = split(n_jobs, len(jobs))
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, dashboard_address=None)
            client = Client(cluster)
    except (OSError, TimeoutError) as exc:
        raise InputError(
            f"--scheduler {scheduler}: cannot connect to the Dask scheduler ({exc})"
        ) from None
    futures = []
    try:
        # someone else's cluster: one thread per Dask task thread, each already has its core
        if scheduler:
            per_worker = 1
        run = partial(call_with_threads, per_worker, worker)
        futures = client.map(
            run, list(jobs), key=[f"{_kind(job)}-{job.key}-{job.seed}" for job in jobs], pure=False
        )
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

"""Running a benchmark's trials in this process or in worker processes, each finished trial handed
back as it ends (bench/real_suite.py, bench/overlap_suite.py).

A trial that raises is logged by `crashed` and left for a re-run; the others go on.
"""

from __future__ import annotations

import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from typing import TypeVar

from plotmosaic.parallel import set_threads, threads

J = TypeVar("J")
R = TypeVar("R")


def _init_worker(n_threads: int) -> None:
    os.environ["OMP_NUM_THREADS"] = str(n_threads)  # Open3D's OpenMP, imported after this
    os.environ["RAYON_NUM_THREADS"] = str(n_threads)  # Rust peers' thread pools (Sylva)
    set_threads(n_threads)


def run_each(
    todo: Sequence[J],
    jobs: int,
    trial: Callable[[J], R],
    finish: Callable[[R, J], None],
    crashed: Callable[[J, Exception], None],
) -> None:
    """`finish(trial(job), job)` for every job, in `jobs` spawned processes sharing the thread
    budget when more than one (`trial` must then be a module-level function)."""
    if jobs <= 1 or len(todo) <= 1:
        for job in todo:
            try:
                finish(trial(job), job)
            except Exception as exc:  # noqa: BLE001 - one broken trial is logged and left for a re-run
                crashed(job, exc)
        return
    share = max(1, threads() // jobs)
    ctx = multiprocessing.get_context("spawn")  # no fork of a parent holding OpenMP threads
    with ProcessPoolExecutor(
        jobs, mp_context=ctx, initializer=_init_worker, initargs=(share,)
    ) as pool:
        started = {pool.submit(trial, job): job for job in todo}
        for fut in as_completed(started):
            try:
                finish(fut.result(), started[fut])
            except Exception as exc:  # noqa: BLE001 - one broken trial is logged and left for a re-run
                crashed(started[fut], exc)

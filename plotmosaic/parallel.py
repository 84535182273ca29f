"""One thread budget for the whole process, and independent jobs run side by side in threads.

numpy, scipy, Open3D and lazrs release the GIL for their heavy parts, so threads pay. The budget
(`set_threads`, default: the cores) is shared: a pool of N worker processes gives each 1 thread;
inside a two-thread map each inner KD-tree query or FFT takes what is left (`inner_workers`), so no
more threads run than the budget allows.
"""

from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

_budget = max(1, os.cpu_count() or 1)
_local = threading.local()  # .share: the budget of the current thread (set inside our pools)


def set_threads(n: int | None) -> int:
    """Set the process's thread budget (None or < 1: every core); returns it."""
    global _budget
    _budget = max(1, int(n)) if n and n > 0 else max(1, os.cpu_count() or 1)
    return _budget


def threads() -> int:
    """Threads the current thread may use (the whole budget outside our pools)."""
    return getattr(_local, "share", _budget)


@contextlib.contextmanager
def limited(n: int) -> Iterator[int]:
    """Within the block, the current thread (and the maps it starts) use at most `n` threads.

    Thread-local, so several jobs in one process (a threaded Dask worker) each keep their own share."""
    had = getattr(_local, "share", None)
    _local.share = max(1, min(int(n), _budget if had is None else had))
    try:
        yield _local.share
    finally:
        if had is None:
            del _local.share
        else:
            _local.share = had


def inner_workers() -> int:
    """`workers=` for a scipy KD-tree query or FFT: the current thread's share of the budget."""
    return threads()


def _pool_map(fn: Callable, items: list) -> list:
    n = min(2, threads(), len(items))
    if n <= 1:
        return [fn(x) for x in items]
    share = max(1, threads() // n)

    def run(x):
        _local.share = share
        try:
            return fn(x)
        finally:
            del _local.share

    with ThreadPoolExecutor(max_workers=n) as pool:
        return list(pool.map(run, items))


def both(fn: Callable, a, b) -> tuple:
    """(fn(a), fn(b)), side by side when the budget allows; an exception in either is raised here."""
    ra, rb = _pool_map(fn, [a, b])
    return ra, rb


def in_two_threads(fn: Callable, items) -> list:
    """[fn(x) for x in items], two at a time when the budget allows, in the order of `items` (deterministic)."""
    return _pool_map(fn, list(items))

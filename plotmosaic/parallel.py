"""Independent jobs two at a time, in threads: numpy, scipy, Open3D and lazrs release the GIL for their heavy parts."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor


def both(fn: Callable, a, b) -> tuple:
    """(fn(a), fn(b)), computed side by side; an exception in either is raised here."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        fa, fb = pool.submit(fn, a), pool.submit(fn, b)
        return fa.result(), fb.result()


def in_two_threads(fn: Callable, items) -> list:
    """[fn(x) for x in items], two at a time, results in the order of `items` (deterministic)."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        return list(pool.map(fn, items))

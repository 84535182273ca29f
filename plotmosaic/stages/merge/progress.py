"""The merge's progress bar over points."""

from __future__ import annotations

import contextlib

from plotmosaic.io.progress import progress_bar, shows_progress


def points_bar(enabled: bool, total: int):
    """A progress bar over points on stderr (nothing when disabled or not a terminal)."""
    if not shows_progress(enabled):
        return contextlib.nullcontext(None)
    return _ProgressTask(progress_bar(True, "merge {task.description}"), total)


class _ProgressTask:
    def __init__(self, bar, total: int):
        self.bar, self.total = bar, total

    def __enter__(self):
        self.bar.__enter__()
        self.task = self.bar.add_task("", total=self.total)
        return self

    def __exit__(self, *exc):
        return self.bar.__exit__(*exc)

    def advance(self, n: int, description: str) -> None:
        self.bar.update(self.task, advance=n, description=description)

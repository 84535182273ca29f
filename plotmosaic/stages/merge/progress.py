"""The merge's progress bar over points."""

from __future__ import annotations

import contextlib


def progress_bar(enabled: bool, total: int):
    """A rich progress bar over points on stderr (nothing when disabled or not a terminal)."""
    if not enabled:
        return contextlib.nullcontext(None)
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeRemainingColumn,
    )

    console = Console(stderr=True)
    if not console.is_terminal:
        return contextlib.nullcontext(None)
    bar = Progress(
        TextColumn("merge {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    )
    return _ProgressTask(bar, total)


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

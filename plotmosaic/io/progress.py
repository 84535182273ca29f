"""The one progress bar of long runs (pairs, bench trials, merged points), drawn on stderr.

Bars are drawn only on a terminal, and cleared when they end: a log or a pipe gets no bar, and the
error line of a command that fails is the only thing it prints on stderr."""

from __future__ import annotations

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)


def shows_progress(enabled: bool) -> bool:
    """Whether a bar asked for is drawn: only on a terminal's stderr."""
    return enabled and Console(stderr=True).is_terminal


def progress_bar(enabled: bool, label: str = "{task.description}") -> Progress:
    """A rich progress bar on stderr (stdout stays for results); disabled, it draws nothing."""
    return Progress(
        TextColumn(label),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=Console(stderr=True),
        disable=not shows_progress(enabled),
        transient=True,
    )

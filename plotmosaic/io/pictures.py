"""PNG pictures written atomically: the one writer of every picture (reports, levels, benchmarks)."""

from __future__ import annotations

import functools
from pathlib import Path

from plotmosaic.io.atomic import atomic_output


@functools.cache
def pyplot():
    """matplotlib's pyplot on the Agg backend (files only, never a window), imported on first use:
    matplotlib is a heavy import, and pair workers that draw nothing must not pay for it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def savefig(fig, path: str | Path, dpi: int = 110, tight: bool = True) -> Path:
    """PNG written atomically (an interrupted run leaves the old picture), the figure closed
    (pictures of long runs must not pile up); `tight` crops the margins."""
    path = Path(path)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight" if tight else None)
    pyplot().close(fig)
    return path

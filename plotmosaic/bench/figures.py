"""The bench's figures: matplotlib without a display, and one way to save a PNG (atomic, figure closed)."""

from __future__ import annotations

from pathlib import Path

from plotmosaic.io.atomic import atomic_output


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_png(fig, path: str | Path, dpi: int = 100) -> Path:
    """Write `fig` as a PNG at `path` (atomically: an interrupted run leaves the old picture) and close it."""
    path = Path(path)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    pyplot().close(fig)
    return path

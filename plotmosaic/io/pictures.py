"""PNG pictures written atomically: the one writer of every picture (reports, levels, benchmarks)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, never a window: selected before pyplot loads
import matplotlib.pyplot as plt  # noqa: E402

from plotmosaic.io.atomic import atomic_output  # noqa: E402


def savefig(fig, path: str | Path, dpi: int = 110, tight: bool = True) -> Path:
    """PNG written atomically (an interrupted run leaves the old picture), the figure closed
    (pictures of long runs must not pile up); `tight` crops the margins."""
    path = Path(path)
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight" if tight else None)
    plt.close(fig)
    return path

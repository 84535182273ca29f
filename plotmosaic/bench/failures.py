"""Pictures of the trials a method got wrong: where it put the source, against where the truth puts it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.bench.figures import pyplot
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.pictures import savefig


def _thin(xyz: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    return xyz if len(xyz) <= n else xyz[np.sort(rng.choice(len(xyz), n, replace=False))]


def plot_failure(
    source: np.ndarray,
    target: np.ndarray,
    estimate: np.ndarray,
    truth: np.ndarray,
    path: Path,
    title: str,
    max_points: int = 60_000,
    seed: int = 0,
) -> Path:
    """Top (x-y) and side (x-z) views: target grey, source at the estimate red, source at the truth blue.

    Coordinates are shown relative to the target's centre so UTM values stay readable.
    """
    plt = pyplot()

    rng = np.random.default_rng(seed)
    src = _thin(np.asarray(source, dtype=np.float64), max_points, rng)
    tgt = _thin(np.asarray(target, dtype=np.float64), max_points, rng)
    centre = np.median(tgt, axis=0)
    layers = [
        (tgt - centre, "#9e9e9e", "target"),
        (apply_transform(truth, src) - centre, "#2b6cb0", "source at the truth"),
        (apply_transform(estimate, src) - centre, "#d7301f", "source where the method put it"),
    ]
    fig, axes = plt.subplots(1, 2, figsize=(14, 6.2))
    for ax, (a, b, label) in zip(axes, ((0, 1, "top (x-y, m)"), (0, 2, "side (x-z, m)"))):
        for xyz, colour, name in layers:
            ax.scatter(xyz[:, a], xyz[:, b], s=0.2, c=colour, linewidths=0, label=name)
        ax.set_aspect("equal")
        ax.set_title(label)
        ax.legend(loc="upper right", markerscale=25, fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return savefig(fig, path, dpi=100, tight=False)

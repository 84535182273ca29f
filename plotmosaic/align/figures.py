"""`--save-levels`: the complexity levels as LAZ (a `level` attribute) and a PNG, like the paper's Fig. 6."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.align.prepare import PreparedCloud
from plotmosaic.io.las import PointCloud, write_cloud
from plotmosaic.io.pictures import pyplot, savefig

COLOURS = ["#8c6d31", "#2b8cbe", "#31a354", "#de2d26", "#756bb1"]  # level 0 (least complex) first


def write_levels_laz(prepared: PreparedCloud, path: Path, crs=None) -> Path:
    """The labelled points (one delta0 point per level cell) in file coordinates with their level (0 = least complex)."""
    cloud = PointCloud(
        prepared.frame.to_global(prepared.level_points),
        {"level": prepared.levels.astype(np.uint8)},
        crs,
    )
    return write_cloud(path, cloud)


def plot_levels(
    clouds: dict[str, PreparedCloud], path: Path, max_points: int = 150_000, seed: int = 0
) -> Path:
    """Per cloud a side view (x-z) and a top view (x-y), points coloured by level."""
    rng = np.random.default_rng(seed)
    fig, axes = pyplot().subplots(len(clouds), 2, figsize=(13, 5.2 * len(clouds)), squeeze=False)
    for row, (name, p) in enumerate(clouds.items()):
        idx = np.arange(len(p.level_points))
        if len(idx) > max_points:
            idx = np.sort(rng.choice(len(idx), max_points, replace=False))
        xyz, lv = p.level_points[idx], p.levels[idx]
        for col, (a, b, label) in enumerate(((0, 2, "side (x-z)"), (0, 1, "top (x-y)"))):
            ax = axes[row, col]
            for k, st in enumerate(p.level_stats):
                sel = lv == k
                ax.scatter(
                    xyz[sel, a],
                    xyz[sel, b],
                    s=0.15,
                    c=COLOURS[k % len(COLOURS)],
                    linewidths=0,
                    label=f"level {k}: {st['size']:,} pts, kappa {st['kappa']:.1f}",
                )
            ax.set_aspect("equal")
            ax.set_title(f"{name} ({p.kind}, K={p.k}) {label}")
            ax.legend(loc="upper right", markerscale=20, fontsize=8)
    fig.tight_layout()
    return savefig(fig, path, dpi=110, tight=False)


def save_levels(
    outdir: Path, source: PreparedCloud, target: PreparedCloud, crs_source=None, crs_target=None
) -> list[Path]:
    outdir = Path(outdir)
    return [
        write_levels_laz(source, outdir / "source_levels.laz", crs_source),
        write_levels_laz(target, outdir / "target_levels.laz", crs_target),
        plot_levels({"source": source, "target": target}, outdir / "levels.png"),
    ]

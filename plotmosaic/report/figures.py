"""Pictures for `plotmosaic report` that the register-plot report does not already draw.

Top/side views of placed scans come from `plotmosaic.report.pictures` and the pose-graph map
from `plotmosaic.report.views`; this module adds a thin vertical slice (where misalignment shows as
doubled stems and ground) and the structural-complexity levels of a prepared cloud.
Everything is matplotlib (Agg, imported on first use), metres on equal-aspect axes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.io.pictures import pyplot, savefig


def subsample(xyz: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """At most n points, a seeded random subset: enough to see structure, cheap to draw."""
    if len(xyz) <= n:
        return xyz
    return xyz[np.sort(rng.choice(len(xyz), n, replace=False))]


def origin_of(clouds: dict[str, np.ndarray]) -> np.ndarray:
    """A round-metre origin for axis labels, so UTM clouds plot as metres from a corner."""
    lo = np.min([p.min(axis=0) for p in clouds.values() if len(p)], axis=0)  # no stacked copy
    return np.floor(lo / 10.0) * 10.0 if np.abs(lo).max() > 1e4 else np.zeros(3)


def plot_slice(
    path: Path,
    clouds: dict[str, np.ndarray],
    title: str,
    width: float = 2.0,
    origin: np.ndarray | None = None,
) -> Path:
    """Side view (x, z) of a `width`-metre band through the middle in y, one colour per scan."""
    origin = origin_of(clouds) if origin is None else origin
    allxyz = np.vstack(list(clouds.values()))
    yc = float(np.median(allxyz[:, 1]))
    fig, ax = pyplot().subplots(figsize=(13, 5))
    cmap = pyplot().get_cmap("tab10" if len(clouds) <= 10 else "tab20")
    for n, (name, xyz) in enumerate(clouds.items()):
        band = xyz[np.abs(xyz[:, 1] - yc) <= width / 2] - origin
        ax.scatter(
            band[:, 0],
            band[:, 2],
            s=0.5,
            color=cmap(n % cmap.N),
            label=f"{name} ({len(band)} pts)",
            rasterized=True,
        )
    ax.set_aspect("equal")
    ax.set_xlabel(f"x - {origin[0]:.0f} (m)" if origin.any() else "x (m)")
    ax.set_ylabel(f"z - {origin[2]:.0f} (m)" if origin.any() else "z (m)")
    ax.set_title(f"{title}\nslice |y - {yc - origin[1]:.1f} m| <= {width / 2:g} m")
    ax.legend(markerscale=10, fontsize=8, loc="upper right")
    return savefig(fig, path)


def plot_levels(
    path: Path,
    clouds: dict[str, tuple[np.ndarray, np.ndarray]],
    title: str,
    max_points: int = 60000,
    seed: int = 0,
) -> Path:
    """Top and side view of each prepared cloud coloured by complexity level (0 = least complex).

    `clouds` maps a name to (points, levels) in the cloud's local frame.
    """
    rng = np.random.default_rng(seed)
    fig, axes = pyplot().subplots(
        len(clouds),
        2,
        figsize=(13, 5.2 * len(clouds)),
        squeeze=False,
        gridspec_kw={"width_ratios": [1, 1.3]},
    )
    for row, (name, (xyz, levels)) in zip(axes, clouds.items()):
        k = int(levels.max()) + 1 if len(levels) else 1
        colours = pyplot().get_cmap("viridis")(np.linspace(0, 0.9, k))
        idx = subsample(np.arange(len(xyz)), max_points, rng)
        # the paper finds ground / stems / foliage for K = 3 on TLS; say only what the data say
        names = [
            "least complex" if i == 0 else "most complex" if i == k - 1 else "" for i in range(k)
        ]
        top, side = row
        for lv in range(k):
            sel = idx[levels[idx] == lv]
            share = float(np.mean(levels == lv)) * 100
            top.scatter(
                xyz[sel, 0],
                xyz[sel, 1],
                s=0.3,
                color=colours[lv],
                label=f"level {lv + 1} {names[lv]} ({share:.0f}% of points)",
                rasterized=True,
            )
            side.scatter(xyz[sel, 0], xyz[sel, 2], s=0.3, color=colours[lv], rasterized=True)
        top.set_aspect("equal")
        side.set_aspect("equal")
        top.set_title(f"{name}: top view, K = {k}")
        side.set_title(f"{name}: side view")
        top.set(xlabel="x (m, local)", ylabel="y (m, local)")
        side.set(xlabel="x (m, local)", ylabel="z (m, local)")
        top.legend(markerscale=12, fontsize=8, loc="best")
    fig.suptitle(title)
    return savefig(fig, path)

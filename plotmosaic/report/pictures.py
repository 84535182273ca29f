"""Picture helpers shared by the reports: atomic PNG saving and the scans' top / side view."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.io.pictures import pyplot, savefig


def dots(ax, x, y, s: float, color, **kwargs):
    """`ax.scatter(x, y, s=s, color=color)` drawn as one line's markers: Agg stamps one cached marker per
    point instead of a path each (the same picture, drawn at a fraction of the cost)."""
    return ax.plot(x, y, "o", ms=float(np.sqrt(s)), color=color, ls="none", **kwargs)


def scan_colours(names: list[str]) -> dict[str, tuple]:
    """One colour per scan, the same in every picture of a page."""
    cmap = pyplot().get_cmap("tab10" if len(names) <= 10 else "tab20")
    return {n: cmap(k % cmap.N) for k, n in enumerate(names)}


def plot_scans(
    path: Path, clouds: dict[str, np.ndarray], title: str, origin: np.ndarray | None = None
) -> Path:
    """Top and side view of every placed scan (points already in the common frame), one colour per scan."""
    origin = np.zeros(3) if origin is None else origin
    fig, (top, side) = pyplot().subplots(
        1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1, 1.3]}
    )
    # the ALS, in the background, takes no scan's colour
    colours = scan_colours([n for n in clouds if n != "ALS"])
    for name, xyz in clouds.items():
        xyz = xyz - origin
        colour = colours.get(name, "lightgrey")
        dots(top, xyz[:, 0], xyz[:, 1], 0.3, colour, label=name, rasterized=True)
        dots(side, xyz[:, 0], xyz[:, 2], 0.3, colour, rasterized=True)
    top.set_aspect("equal")
    top.set_title("top view (x, y)")
    side.set_title("side view (x, z)")
    for ax in (top, side):
        ax.set_xlabel("x (m)" if not origin.any() else f"x - {origin[0]:.0f} (m)")
    top.set_ylabel("y (m)" if not origin.any() else f"y - {origin[1]:.0f} (m)")
    side.set_ylabel("z (m)" if not origin.any() else f"z - {origin[2]:.0f} (m)")
    # below the views, never over the points: loc="best" scores every point at every candidate place
    fig.legend(
        markerscale=12, fontsize=8, loc="lower center", ncol=min(len(clouds), 8), frameon=False
    )
    fig.subplots_adjust(left=0.06, right=0.98, top=0.9, bottom=0.15, wspace=0.2)
    fig.suptitle(title)
    return savefig(fig, path, tight=False)

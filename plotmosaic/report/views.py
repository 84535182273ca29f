"""Figures of the HTML report: breast-height slice with zoomed stems, distance maps, the plot map.

matplotlib (Agg, imported on first use); coordinates are drawn in metres from `origin` (a round corner of a
UTM plot), colours are one per scan in the order given.
"""

from __future__ import annotations

from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.io.pictures import pyplot, savefig
from plotmosaic.report.pictures import dots, scan_colours
from plotmosaic.report.slice import Ground, Stem, cell_minima, ground_model


def plot_breast_slice(
    path: Path,
    slices: dict[str, np.ndarray],
    stems: list[Stem],
    title: str,
    origin: np.ndarray,
    insets: int = 4,
    colours: dict | None = None,
) -> Path:
    """The slice from above, one colour per scan, and zoomed stems (the ones most scans see) at 1 cm scale."""
    colours = colours or scan_colours(list(slices))
    chosen = stems[:insets]
    n_in = len(chosen)
    cols = 2 if n_in > 1 else 1
    rows_in = max(1, (n_in + cols - 1) // cols)
    fig = pyplot().figure(figsize=(9 + 4.2 * cols, max(8.5, 4.2 * rows_in)))
    gs = fig.add_gridspec(rows_in, 2 + cols, width_ratios=[1.1, 1.1] + [1] * cols)
    ax = fig.add_subplot(gs[:, :2])
    for name, xyz in slices.items():
        p = xyz[:, :2] - origin[:2]
        dots(ax, p[:, 0], p[:, 1], 1.5, colours[name], label=f"{name} ({len(p)} pts)")
    for k, st in enumerate(chosen):
        c = st.centre - origin[:2]
        h = st.radius + 0.15
        ax.add_patch(
            pyplot().Rectangle(
                (c[0] - h, c[1] - h), 2 * h, 2 * h, fill=False, ec="black", lw=0.8, zorder=3
            )
        )
        ax.text(c[0] + h, c[1] + h, f" {k + 1}", fontsize=9, weight="bold")
    ax.set_aspect("equal")
    ax.set_title(title)
    ax.set_xlabel(f"x - {origin[0]:.0f} (m)" if origin.any() else "x (m)")
    ax.set_ylabel(f"y - {origin[1]:.0f} (m)" if origin.any() else "y (m)")
    ax.legend(markerscale=6, fontsize=8, loc="upper right")
    for k, st in enumerate(chosen):
        sub = fig.add_subplot(gs[k // cols, 2 + k % cols])
        _stem_inset(sub, st, colours, origin, k + 1)
    fig.subplots_adjust(left=0.05, right=0.98, top=0.95, bottom=0.06, wspace=0.3, hspace=0.3)
    return savefig(fig, path, tight=False)  # fixed margins: a tight box is a second layout pass


def _stem_inset(ax, st: Stem, colours: dict, origin: np.ndarray, number: int) -> None:
    c = st.centre - origin[:2]
    h = st.radius + 0.12
    for name, p in st.points.items():
        q = p - origin[:2]
        label = name if name in st.arcs else None
        dots(ax, q[:, 0], q[:, 1], 6, colours.get(name, "grey"), label=label)
    ax.add_patch(
        pyplot().Circle(tuple(c), st.radius, fill=False, ls="--", lw=0.7, ec="black", zorder=3)
    )
    ax.set(xlim=(c[0] - h, c[0] + h), ylim=(c[1] - h, c[1] + h))
    ax.set_aspect("equal")
    # a 1 cm grid (lines, not ticks: cheap to draw) so a centimetre offset between rings can be read off
    for step, lw, colour in ((0.01, 0.25, "0.85"), (0.1, 0.6, "0.55")):
        xs = np.arange(np.ceil((c[0] - h) / step) * step, c[0] + h, step)
        ys = np.arange(np.ceil((c[1] - h) / step) * step, c[1] + h, step)
        ax.vlines(xs, c[1] - h, c[1] + h, lw=lw, color=colour, zorder=0)
        ax.hlines(ys, c[0] - h, c[0] + h, lw=lw, color=colour, zorder=0)
    ax.set_xticks(np.arange(np.ceil((c[0] - h) * 10) / 10, c[0] + h, 0.1))
    ax.set_yticks(np.arange(np.ceil((c[1] - h) * 10) / 10, c[1] + h, 0.1))
    ax.tick_params(labelsize=7)
    ax.set_title(
        f"stem {number}: r = {st.radius * 100:.1f} cm, {len(st.arcs)} scans, ring spread {st.spread * 100:.1f} cm",
        fontsize=9,
    )
    ax.legend(fontsize=6, markerscale=1.5, loc="upper right")


def plot_edge_distances(
    path: Path, edges: list[dict], origin: np.ndarray, colour_max: float, cell: float = 0.5
) -> Path:
    """Per edge: histogram of distances to the other scan's local surface in the overlap, and a map of them from above.

    Drawn cheaply for many edges: each histogram one filled step line (not a bar per bin), one colour
    bar for all maps (they share the 0 - colour_max scale), fixed margins instead of a tight-box pass."""
    n = max(1, len(edges))
    height = 4.3 * n
    fig, axes = pyplot().subplots(
        n,
        2,
        figsize=(12, height),
        squeeze=False,
        gridspec_kw={"width_ratios": [1, 1.25], "hspace": 0.45},
    )
    fig.subplots_adjust(left=0.07, right=0.86, top=1 - 0.45 / height, bottom=0.55 / height)
    cmap = pyplot().get_cmap("turbo")
    sc = None
    for (hist, top), e in zip(axes, edges):
        d = e["distances"]
        bins = np.linspace(0, e["max_distance"] * 100, 61)
        hist.stairs(np.histogram(d * 100, bins)[0], bins, fill=True, color="tab:blue")
        hist.axvline(e["median"] * 100, color="black", ls="--", lw=1)
        hist.set(xlabel="distance to the other scan's local surface (cm)", ylabel="points")
        hist.set_title(
            f"{e['source']} -> {e['target']}: median {e['median'] * 100:.2f} cm, "
            f"90% {e['p90'] * 100:.2f} cm ({len(d)} points)",
            fontsize=9,
        )
        img, ext = _distance_raster(e["points"][:, :2] - origin[:2], d, cell)
        sc = top.imshow(
            np.minimum(img, colour_max) * 100,
            origin="lower",
            extent=ext,
            cmap=cmap,
            vmin=0,
            vmax=colour_max * 100,
            interpolation="nearest",
        )
        top.set_aspect("equal")
        top.set_title(f"overlap from above, mean distance per {cell * 100:.0f} cm cell", fontsize=9)
    if sc is not None:
        bar = fig.add_axes(
            (0.9, 1 - 0.45 / height - min(0.3, 4.0 / height), 0.015, min(0.3, 4.0 / height))
        )
        fig.colorbar(sc, cax=bar, label="mean distance per cell (cm), every map")
    else:
        axes[0, 0].text(0.5, 0.5, "no kept edge", ha="center")
    return savefig(fig, path, tight=False)


def _distance_raster(xy: np.ndarray, d: np.ndarray, cell: float) -> tuple[np.ndarray, tuple]:
    """Mean distance per cell (NaN where the overlap has no point): a map, cheap whatever the point count."""
    if not len(xy):
        return np.full((1, 1), np.nan), (0, 1, 0, 1)
    lo = np.floor(xy.min(axis=0) / cell) * cell
    ij = np.floor((xy - lo) / cell).astype(np.int64)
    shape = tuple(ij.max(axis=0)[::-1] + 1)
    flat = ij[:, 1] * shape[1] + ij[:, 0]
    total = np.bincount(flat, d, minlength=shape[0] * shape[1])
    count = np.bincount(flat, minlength=shape[0] * shape[1])
    with np.errstate(invalid="ignore"):
        img = (total / count).reshape(shape)
    return img, (lo[0], lo[0] + shape[1] * cell, lo[1], lo[1] + shape[0] * cell)


def plot_scan_distances(path: Path, medians: dict[str, float], spreads: dict[str, float]) -> Path:
    """Per scan: median distance to its neighbours after the joint solve, and the ring spread of its stems."""
    names = list(medians)
    fig, ax = pyplot().subplots(figsize=(max(6, 0.6 * len(names) + 3), 4.2))
    x = np.arange(len(names))
    ax.bar(
        x - 0.2, [medians[n] * 100 for n in names], 0.4, label="median distance to neighbours (cm)"
    )
    ax.bar(
        x + 0.2,
        [spreads.get(n, np.nan) * 100 for n in names],
        0.4,
        label="median ring spread of its stems (cm)",
    )
    ax.set_xticks(
        x, names, rotation=45 if len(names) > 8 else 0, ha="right" if len(names) > 8 else "center"
    )
    ax.set_ylabel("cm")
    ax.set_title("per scan, after the joint solve")
    ax.legend(fontsize=8)
    ax.grid(axis="y", lw=0.3)
    return savefig(fig, path)


def _map_positions(
    G: nx.Graph, positions: dict[str, np.ndarray], origin: np.ndarray
) -> dict[str, np.ndarray]:
    """Each node's map position: placed scans where they are, unplaced ones in a row below."""
    pos = {n: positions[n][:2] - origin[:2] for n in G.nodes if n in positions}
    x0, y0 = 0.0, 0.0
    if pos:
        xy = np.array(list(pos.values()))
        x0, y0 = xy[:, 0].min(), xy[:, 1].min() - 0.15 * (np.ptp(xy[:, 1]) + 5)
    unplaced = [n for n in G.nodes if n not in pos]
    pos.update({n: np.array([x0 + 4.0 * k, y0]) for k, n in enumerate(unplaced)})
    return pos


def plot_map(
    path: Path,
    G: nx.Graph,
    positions: dict[str, np.ndarray],
    background: tuple[np.ndarray, tuple, str] | None,
    title: str,
    origin: np.ndarray,
    unsure: set[tuple[str, str]] = frozenset(),
) -> Path:
    """The pose-graph map: scans from above (unplaced ones grey, in a row below) and edges, kept
    (solid, residual after the solve), dropped (red dashed, reason), unsure (orange dotted).

    `background` is (image, extent in the same frame as positions, label): canopy height or hillshade.
    """
    fig, ax = pyplot().subplots(figsize=(9, 8))
    if background is not None:
        img, ext, label = background
        e = (ext[0] - origin[0], ext[1] - origin[0], ext[2] - origin[1], ext[3] - origin[1])
        im = ax.imshow(
            np.ma.masked_invalid(img),
            origin="lower",
            extent=e,
            cmap="Greens" if "canopy" in label else "gray",
            alpha=0.75,
            vmin=0 if "canopy" not in label else None,
            vmax=1 if "canopy" not in label else None,
        )
        if "canopy" in label:
            fig.colorbar(im, ax=ax, label=label, shrink=0.7)
    pos = _map_positions(G, positions, origin)
    for u, v, e in G.edges(data=True):
        (x1, y1), (x2, y2) = pos[u], pos[v]
        key = tuple(sorted((u, v)))
        if e.get("dropped"):
            ax.plot([x1, x2], [y1, y2], "--", color="red", lw=1.8)
            label = f"dropped: {e.get('drop_reason')}"
        elif key in unsure:
            ax.plot([x1, x2], [y1, y2], ":", color="darkorange", lw=2.2)
            label = "unsure, kept (loop confirms)"
        else:
            ax.plot([x1, x2], [y1, y2], "-", color="tab:blue", lw=2.2)
            r = e.get("residual_after")
            label = f"{r['translation'] * 100:.1f} cm" if r else ""
        box = {"fc": "white", "ec": "none", "alpha": 0.75, "pad": 0.5}
        ax.text((x1 + x2) / 2, (y1 + y2) / 2, label, fontsize=7, ha="center", va="center", bbox=box)
    for n, (x, y) in pos.items():
        placed = n in positions
        colour = "gold" if placed else "lightgrey"
        ax.scatter([x], [y], s=150, color=colour, edgecolor="black", zorder=3, marker="^")
        name = f"  {n}" + ("" if placed else " (unplaced)")
        ax.text(x, y, name, fontsize=9, va="bottom", zorder=4, weight="bold")
    ax.plot([], [], "-", color="tab:blue", label="kept edge (residual after the solve)")
    ax.plot([], [], "--", color="red", label="dropped edge (reason)")
    ax.plot([], [], ":", color="darkorange", label="unsure edge (low coarse confidence)")
    ax.legend(fontsize=8, loc="lower right")
    # without a background the limits widen, not the figure shrink: a row of scans stays readable
    ax.set_aspect("equal", adjustable="box" if background is not None else "datalim")
    ax.set_title(title + (f"\nbackground: {background[2]}" if background is not None else ""))
    ax.set_xlabel(f"x - {origin[0]:.0f} (m)" if origin.any() else "x (m)")
    ax.set_ylabel(f"y - {origin[1]:.0f} (m)" if origin.any() else "y (m)")
    return savefig(fig, path)


def hillshade_background(ground: Ground) -> tuple[np.ndarray, tuple, str]:
    return ground.hillshade(), ground.extent, "hillshade of the ground from the scans"


def canopy_height(als_xyz: np.ndarray, cell: float = 1.0) -> tuple[np.ndarray, tuple, str]:
    """ALS canopy height model: highest minus lowest return per cell (ground filled from neighbours)."""
    ground = ground_model(cell_minima(als_xyz, cell), cell, spike=2.0)
    keys = np.floor(als_xyz[:, :2] / cell).astype(np.int64)
    lo = np.array([round(ground.x0 / cell), round(ground.y0 / cell)])
    ij = keys - lo
    top = np.full(ground.z.shape, np.nan)
    ok = (
        (ij[:, 0] >= 0)
        & (ij[:, 1] >= 0)
        & (ij[:, 0] < ground.z.shape[1])
        & (ij[:, 1] < ground.z.shape[0])
    )
    np.fmax.at(top, (ij[ok, 1], ij[ok, 0]), als_xyz[ok, 2])
    chm = np.clip(np.nan_to_num(top - ground.z, nan=0.0), 0, None)
    return chm, ground.extent, "ALS canopy height (m)"

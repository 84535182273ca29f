"""Pictures of a plot's fit to the ALS (report/als_fit.py): ground difference, canopy tops, per scan.

Coordinates in metres from `origin` (a round corner of a UTM plot); matplotlib imported on first use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.io.pictures import pyplot, savefig
from plotmosaic.report.als_fit import AlsFit, Raster

# fixed margins of a map beside a histogram: a tight layout is a second pass over every text
MARGINS = {"left": 0.05, "right": 0.98, "top": 0.92, "bottom": 0.1, "wspace": 0.25}


def _extent(r: Raster, origin: np.ndarray) -> tuple[float, float, float, float]:
    x0, x1, y0, y1 = r.extent
    return (x0 - origin[0], x1 - origin[0], y0 - origin[1], y1 - origin[1])


def _axes_labels(ax, origin: np.ndarray) -> None:
    ax.set_xlabel(f"x - {origin[0]:.0f} (m)" if origin.any() else "x (m)")
    ax.set_ylabel(f"y - {origin[1]:.0f} (m)" if origin.any() else "y (m)")
    ax.set_aspect("equal")


def plot_ground_difference(path: Path, fit: AlsFit, origin: np.ndarray, colour_max: float) -> Path:
    """Map of TLS ground minus ALS ground per cell (blue: TLS lower, red: TLS higher) and its histogram."""
    plt = pyplot()
    fig, (ax, hist) = plt.subplots(1, 2, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1.2, 1]})
    im = ax.imshow(
        fit.ground_diff.z * 100,
        origin="lower",
        extent=_extent(fit.ground_diff, origin),
        cmap="RdBu_r",
        vmin=-colour_max * 100,
        vmax=colour_max * 100,
        interpolation="nearest",
    )
    fig.colorbar(im, ax=ax, label="TLS ground - ALS ground (cm)", shrink=0.8)
    _axes_labels(ax, origin)
    ax.set_title(
        f"plot {fit.plot}: ground difference per {fit.ground_diff.cell:g} m cell", fontsize=10
    )
    g = fit.ground
    values = np.clip(fit.ground_values, -2 * colour_max, 2 * colour_max) * 100
    hist.stairs(*np.histogram(values, 60), fill=True, color="tab:blue")  # one path, not 60 bars
    hist.axvline(0, color="grey", lw=0.8)
    hist.axvline(g.median * 100, color="black", ls="--", lw=1.2, label="median")
    for sign in (-1, 1):
        hist.axvline((g.median + sign * g.nmad) * 100, color="black", ls=":", lw=1)
    hist.set(xlabel="TLS ground - ALS ground (cm)", ylabel="cells")
    hist.set_title(
        f"median {g.median * 100:+.1f} cm, NMAD {g.nmad * 100:.1f} cm ({g.count} cells)",
        fontsize=10,
    )
    hist.legend(fontsize=8)
    fig.subplots_adjust(**MARGINS)
    return savefig(fig, path, tight=False)


def plot_canopy(path: Path, fit: AlsFit, origin: np.ndarray) -> Path:
    """TLS canopy top minus ALS canopy top where both see the top (map), and one against the other."""
    plt = pyplot()
    fig, (ax, sc) = plt.subplots(1, 2, figsize=(13, 5.2), gridspec_kw={"width_ratios": [1.2, 1]})
    diff = fit.tls_top.z - fit.als_top.z
    lim = max(1.0, float(np.nanquantile(np.abs(diff), 0.95))) if np.isfinite(diff).any() else 1.0
    im = ax.imshow(
        diff,
        origin="lower",
        extent=_extent(fit.tls_top, origin),
        cmap="RdBu_r",
        vmin=-lim,
        vmax=lim,
        interpolation="nearest",
    )
    fig.colorbar(im, ax=ax, label="TLS top - ALS top (m)", shrink=0.8)
    _axes_labels(ax, origin)
    ax.set_title(f"plot {fit.plot}: canopy top per {fit.tls_top.cell:g} m cell", fontsize=10)
    ok = np.isfinite(diff)
    a, t = fit.als_top.z[ok], fit.tls_top.z[ok]
    sc.plot(a, t, "o", ms=3, color="tab:green", alpha=0.6)
    hi = float(max(a.max(), t.max())) if ok.any() else 1.0
    sc.plot([0, hi], [0, hi], "-", color="grey", lw=0.8, label="1:1")
    sc.set(xlabel="ALS canopy height (m)", ylabel="TLS canopy height (m)")
    c = fit.canopy
    sc.set_title(f"median {c.median:+.2f} m, NMAD {c.nmad:.2f} m ({c.count} cells)", fontsize=10)
    sc.set_aspect("equal")
    sc.legend(fontsize=8)
    fig.subplots_adjust(**MARGINS)
    return savefig(fig, path, tight=False)


def plot_scan_residuals(path: Path, fit: AlsFit) -> Path:
    """Per scan: median ground and canopy-top difference to the ALS, NMAD as the bar."""
    plt = pyplot()
    names = [s.scan for s in fit.scans]
    fig, (g_ax, c_ax) = plt.subplots(1, 2, figsize=(max(9, 1.1 * len(names) + 4), 4.2))
    x = np.arange(len(names))
    g = np.array([[s.ground.median, s.ground.nmad] for s in fit.scans]).reshape(-1, 2) * 100
    c = np.array([[s.canopy.median, s.canopy.nmad] for s in fit.scans]).reshape(-1, 2)
    g_ax.bar(x, g[:, 0], yerr=g[:, 1], color="tab:blue", capsize=3)
    g_ax.set_ylabel("scan ground - ALS ground (cm)")
    c_ax.bar(x, c[:, 0], yerr=c[:, 1], color="tab:green", capsize=3)
    c_ax.set_ylabel("scan canopy top - ALS top (m)")
    for ax in (g_ax, c_ax):
        ax.axhline(0, color="grey", lw=0.8)
        rot = 45 if len(names) > 6 else 0
        ax.set_xticks(x, names, rotation=rot, ha="right" if rot else "center")
        ax.grid(axis="y", lw=0.3)
    g_ax.set_title("ground, median and NMAD", fontsize=10)
    c_ax.set_title("canopy top, median and NMAD", fontsize=10)
    fig.suptitle(f"plot {fit.plot}: each scan against the ALS")
    fig.subplots_adjust(left=0.08, right=0.98, top=0.86, bottom=0.12 + 0.1 * (len(names) > 6))
    return savefig(fig, path, tight=False)

"""Summaries of bench trials: the paper-style RMSE table and the error-distribution plots.

RMSE is over every trial, failures included (a failed trial keeps its initial error), as in
the paper's Tables 1-4. The "initial" row is the RMSE of the perturbations themselves.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from plotmosaic.bench.figures import pyplot
from plotmosaic.bench.protocol import PARAMS
from plotmosaic.io.pictures import savefig

INITIAL = "initial"


def _groups(rows: list[dict]) -> list[tuple]:
    """(overlap_wanted, method) in first-seen order, with an 'initial' row first in each overlap."""
    keys: list[tuple] = []
    for r in rows:
        for key in ((r["overlap_wanted"], INITIAL), (r["overlap_wanted"], r["method"])):
            if key not in keys:
                keys.append(key)
    return keys


def summarise(rows: list[dict]) -> list[dict]:
    """One dict per (overlap, method): n, rmse per parameter, success rate, seconds per trial."""
    out = []
    for wanted, method in _groups(rows):
        if method == INITIAL:
            # each (pair, trial) perturbation once, not once per method
            seen = {}
            for r in rows:
                if r["overlap_wanted"] == wanted:
                    seen[(r["pair"], r["trial"])] = [r[f"init_{p}"] for p in PARAMS]
            errors = np.array(list(seen.values()), dtype=float)
            sub = []
        else:
            sub = [r for r in rows if r["overlap_wanted"] == wanted and r["method"] == method]
            errors = np.array([[r[p] for p in PARAMS] for r in sub], dtype=float)
        rmse = np.sqrt(np.mean(errors**2, axis=0))
        overlaps = [
            r["overlap"] for r in rows if r["overlap_wanted"] == wanted and r["overlap"] is not None
        ]
        out.append(
            {
                "overlap_wanted": wanted,
                "overlap": float(np.mean(overlaps)) if overlaps else None,
                "method": method,
                "n": int(len(errors)),
                **{f"rmse_{p}": float(v) for p, v in zip(PARAMS, rmse)},
                "success_rate": float(np.mean([r["success"] for r in sub])) if sub else None,
                "failed": int(sum(r["failed"] for r in sub)),
                "seconds": float(np.mean([r["seconds"] for r in sub])) if sub else None,
            }
        )
    return out


def _num(value: float) -> str:
    if value >= 100:
        return f"{value:.1f}"
    if value >= 1:
        return f"{value:.2f}"
    return f"{value:.3f}"


def markdown_table(summary: list[dict]) -> str:
    """Rows method (and overlap when swept); RMSE roll/pitch/yaw (deg), tx/ty/tz (m), success %,
    trials the method itself reported as failed, s/trial."""
    sweep = any(s["overlap_wanted"] is not None for s in summary)
    head = ["overlap"] if sweep else []
    head += [
        "method",
        "n",
        "roll (deg)",
        "pitch (deg)",
        "yaw (deg)",
        "tx (m)",
        "ty (m)",
        "tz (m)",
        "success",
        "failed",
        "s/trial",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in summary:
        cells = []
        if sweep:
            cells.append(
                "—"
                if s["overlap"] is None
                else f"~{s['overlap_wanted']:g}% ({100 * s['overlap']:.1f}%)"
            )
        cells += [s["method"], str(s["n"])]
        cells += [_num(s[f"rmse_{p}"]) for p in PARAMS]
        cells.append("—" if s["success_rate"] is None else f"{100 * s['success_rate']:.0f}%")
        cells.append("—" if s["method"] == INITIAL else str(s["failed"]))
        cells.append("—" if s["seconds"] is None else f"{s['seconds']:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_errors(rows: list[dict], path: str | Path, title: str = "") -> Path:
    """Violins of initial (blue) and estimated (orange) errors per parameter, like the paper's Figs. 8-9.

    One panel per parameter; along x one group per (overlap, method). Symmetric-log y so the
    +-45 deg / +-15 m starts and the centimetre results are readable together.
    """
    plt = pyplot()

    groups = [g for g in _groups(rows) if g[1] != INITIAL]
    fig, axes = plt.subplots(
        2, 3, figsize=(max(11.0, 3 + 1.8 * 3 * len(groups) / 2), 8), squeeze=False
    )
    for ax, p, unit in zip(axes.ravel(), PARAMS, ("deg",) * 3 + ("m",) * 3):
        init_data, est_data, labels = [], [], []
        for wanted, method in groups:
            sub = [r for r in rows if r["overlap_wanted"] == wanted and r["method"] == method]
            init_data.append(np.array([r[f"init_{p}"] for r in sub], dtype=float))
            est_data.append(np.array([r[p] for r in sub], dtype=float))
            labels.append(method if wanted is None else f"{method}\n~{wanted:g}%")
        pos = np.arange(len(groups), dtype=float)
        for data, offset, colour, name in (
            (init_data, -0.2, "tab:blue", "initial"),
            (est_data, 0.2, "tab:orange", "estimate"),
        ):
            ok = [i for i, d in enumerate(data) if len(d) > 1 and np.ptp(d) > 0]
            if ok:
                parts = ax.violinplot(
                    [data[i] for i in ok], positions=pos[ok] + offset, widths=0.35, showmedians=True
                )
                for body in parts["bodies"]:
                    body.set_facecolor(colour)
                    body.set_alpha(0.5)
                for key in ("cmedians", "cmins", "cmaxes", "cbars"):
                    if key in parts:
                        parts[key].set_color(colour)
            # every trial as a dot too: with few trials a violin says little
            for i, d in enumerate(data):
                ax.plot(
                    np.full(len(d), pos[i] + offset),
                    d,
                    "o",
                    color=colour,
                    mec="black",
                    mew=0.3,
                    alpha=0.8,
                    ms=3,
                    zorder=3,
                    label=name if i == 0 else None,
                )
        rmse = [np.sqrt(np.mean(d**2)) if len(d) else np.nan for d in est_data]
        ax.set_title(f"{p} error ({unit})\nRMSE " + " / ".join(_num(v) for v in rmse), fontsize=9)
        linthresh = 1.0 if unit == "deg" else 0.1
        ax.set_yscale("symlog", linthresh=linthresh)
        values = np.concatenate([*init_data, *est_data]) if groups else np.zeros(1)
        lim = max(float(np.max(np.abs(values))) * 1.5, linthresh)
        ax.set_ylim(-lim, lim)
        ax.axhline(0, color="grey", lw=0.5)
        ax.set_xticks(pos, labels, fontsize=8)
        ax.set_ylabel(f"error ({unit})")
        ax.grid(axis="y", alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize=8)
    fig.suptitle(
        (title + "\n" if title else "")
        + "blue: initial error (the perturbation), orange: error after registration; symmetric-log axis"
    )
    fig.tight_layout()
    return savefig(fig, path, dpi=110, tight=False)

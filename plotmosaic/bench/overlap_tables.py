"""The overlap benchmark's tables and curve from its trials (bench/overlap_suite.py runs them)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from plotmosaic.bench.figures import pyplot
from plotmosaic.bench.methods import OURS
from plotmosaic.bench.overlap_pairs import SOURCES, Bin, bin_label
from plotmosaic.bench.peers import PEERS
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.pictures import savefig

# the baselines of bench/methods.py (forestalign-placement is for airborne targets) and the peers
ALL_METHODS = ("forestalign", "icp", "fpfh-ransac", "cpd", *PEERS)


def _bin(r: dict) -> Bin:
    return (float(r["bin"][0]), float(r["bin"][1]))


def summarise(rows: list[dict]) -> list[dict]:
    """One dict per (source or 'all', bin, method): n, found, refused, wrong, overlaps, CPU s."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        for src in ("all", r["source"]):
            groups.setdefault((src, _bin(r), r["method"]), []).append(r)
    order = ["all", *SOURCES]
    meths = list(ALL_METHODS)
    out = []
    for src, b, m in sorted(
        groups,
        key=lambda k: (
            order.index(k[0]) if k[0] in order else 99,
            k[1],
            meths.index(k[2]) if k[2] in meths else 99,
        ),
    ):
        sub = groups[(src, b, m)]
        out.append(
            {
                "source": src,
                "bin": list(b),
                "method": m,
                "n": len(sub),
                "pairs": len({(r["source"], r["pair"]) for r in sub}),
                "found": sum(r["outcome"] == "found" for r in sub),
                "refused": sum(r["outcome"] == "refused" for r in sub),
                "wrong": sum(r["outcome"] == "wrong" for r in sub),
                "overlap_st": [
                    float(np.min([r["overlap_st"] for r in sub])),
                    float(np.median([r["overlap_st"] for r in sub])),
                    float(np.max([r["overlap_st"] for r in sub])),
                ],  # fmt: skip
                "overlap_ts": [
                    float(np.min([r["overlap_ts"] for r in sub])),
                    float(np.median([r["overlap_ts"] for r in sub])),
                    float(np.max([r["overlap_ts"] for r in sub])),
                ],  # fmt: skip
                "cpu_median_s": float(np.median([r["cpu_seconds"] for r in sub])),
                "commits": sorted({r.get("commit", "?") for r in sub}),
            }
        )
    return out


def _cell(s: dict) -> str:
    wrong = f"**{s['wrong']}**" if s["wrong"] and s["method"] in OURS else str(s["wrong"])
    return f"{s['found']} / {s['refused']} / {wrong}"


def markdown(summary: list[dict]) -> str:
    """Per source (and all pooled) and bin: N, overlap both ways, found / refused / wrong per method."""
    methods = [m for m in ALL_METHODS if any(s["method"] == m for s in summary)]
    groups: dict[tuple, dict[str, dict]] = {}
    for s in summary:
        groups.setdefault((s["source"], tuple(s["bin"])), {})[s["method"]] = s
    head = ["source", "overlap bin", "pairs", "N", "overlap s->t", "overlap t->s"]
    head += [f"{m} found / refused / wrong" for m in methods]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (src, b), per in groups.items():
        any_ = next(iter(per.values()))
        n = max(s["n"] for s in per.values())
        cells = [
            f"**{src}**" if src == "all" else src,
            f"[{b[0]:.2f}, {b[1]:.2f}{']' if b[1] >= 0.5 else ')'}",
            str(any_["pairs"]),
            str(n),
            "{1:.2f} ({0:.2f}-{2:.2f})".format(*any_["overlap_st"]),
            "{1:.2f} ({0:.2f}-{2:.2f})".format(*any_["overlap_ts"]),
        ]
        cells += [_cell(per[m]) if m in per else "—" for m in methods]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def cpu_table(rows: list[dict]) -> str:
    """Median CPU seconds a trial per method and source (all bins)."""
    methods = [m for m in ALL_METHODS if any(r["method"] == m for r in rows)]
    lines = ["| source | " + " | ".join(methods) + " |", "|" + "---|" * (len(methods) + 1)]
    for src in ("all", *SOURCES):
        cells = []
        for m in methods:
            cpu = [
                r["cpu_seconds"] for r in rows if r["method"] == m and src in ("all", r["source"])
            ]
            cells.append(f"{np.median(cpu):.1f}" if cpu else "—")
        if any(c != "—" for c in cells):
            lines.append(f"| {src} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def pairs_table(rows: list[dict]) -> str:
    """The pairs behind each source and bin: scanner distance and range (what sets the overlap)."""
    groups: dict[tuple, dict[str, dict]] = {}
    for r in rows:
        groups.setdefault((r["source"], tuple(_bin(r))), {})[r["pair"]] = r
    lines = [
        "| source | overlap bin | pairs | scanners apart (m) | range (m) |",
        "|---|---|---|---|---|",
    ]
    for (src, b), pairs in sorted(
        groups.items(), key=lambda kv: (SOURCES.index(kv[0][0]), kv[0][1])
    ):
        d = [p["distance_m"] for p in pairs.values()]
        rng = [p["max_range"] for p in pairs.values()]
        lines.append(
            f"| {src} | {bin_label(b)} | {len(pairs)} | {min(d):.1f}-{max(d):.1f} | "
            f"{min(rng):.1f}-{max(rng):.1f} |"
        )
    return "\n".join(lines) + "\n"


def plot_curve(summary: list[dict], path: str | Path) -> Path:
    """Found share against overlap bin, one line per method: all sources pooled, then each source."""
    plt = pyplot()
    panels = ["all", *[s for s in SOURCES if any(x["source"] == s for x in summary)]]
    bins = sorted({tuple(s["bin"]) for s in summary})
    methods = [m for m in ALL_METHODS if any(s["method"] == m for s in summary)]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.6), sharey=True)
    axes = np.atleast_1d(axes)
    x = np.arange(len(bins))
    markers = "osD^vPX*"
    for ax, src in zip(axes, panels):
        for k, m in enumerate(methods):
            per = {tuple(s["bin"]): s for s in summary if s["source"] == src and s["method"] == m}
            y = [
                per[b]["found"] / per[b]["n"] if b in per and per[b]["n"] else np.nan for b in bins
            ]
            style = {"lw": 2.4, "color": "k"} if m in OURS else {"lw": 1.2, "alpha": 0.85}
            dodge = 0.06 * (k - (len(methods) - 1) / 2)  # lines at equal shares stay visible
            ax.plot(x + dodge, y, marker=markers[k % len(markers)], ms=5, label=m, **style)
        n = [max((s["n"] for s in summary if s["source"] == src and tuple(s["bin"]) == b), default=0) for b in bins]  # fmt: skip
        ax.set_xticks(x, [f"{b[0]:.2f}-{b[1]:.2f}\nN={k}" for b, k in zip(bins, n)], fontsize=7)
        ax.set_title("all sources" if src == "all" else src, fontsize=10)
        ax.set_ylim(-0.03, 1.03)
        ax.grid(alpha=0.3)
        ax.set_xlabel("pair overlap (larger share, 25 cm)", fontsize=8)
    axes[0].set_ylabel("found (within 1 deg / 10 cm)")
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("paper protocol: found share against overlap", fontsize=10)
    return savefig(fig, path)


def write_outputs(
    rows: list[dict], out: str | Path, command: str, figure: str | Path | None
) -> dict:
    """OUT/table.md, OUT/summary.json and the curve (OUT/overlap.png unless `figure`)."""
    out = Path(out)
    summary = summarise(rows)
    wrong = [r for r in rows if r["method"] in OURS and r["outcome"] == "wrong"]
    text = (
        f"Command:\n\n    {command}\n\n"
        + markdown(summary)
        + "\nThe pairs (each bin's draws cycle over them):\n\n"
        + pairs_table(rows)
        + "\nMedian CPU seconds a trial:\n\n"
        + cpu_table(rows)
        + f"\nplotmosaic wrong poses with exit 0: {len(wrong)} of "
        + f"{sum(r['method'] in OURS for r in rows)} trials\n"
    )
    states: dict[tuple, int] = {}
    for r in rows:
        k = (r.get("commit", "?"), r.get("code", "?"))
        states[k] = states.get(k, 0) + 1
    text += (
        "\nCode measured (commit, source hash: rows): "
        + "; ".join(f"{c}, {h}: {n}" for (c, h), n in states.items())
        + "\n"
    )
    paths = {
        "table": write_text_atomic(out / "table.md", text),
        "summary": write_text_atomic(
            out / "summary.json", json.dumps(summary, indent=1, default=float)
        ),
        "figure": plot_curve(summary, figure or out / "overlap.png"),
    }
    return paths

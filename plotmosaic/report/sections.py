"""Sections every report page shares: the summary lines, the per-plot tables, the time table."""

from __future__ import annotations

from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.report import html as H
from plotmosaic.report.model import PlotView, ReportInput, Stage
from plotmosaic.report.slice import ring_spread
from plotmosaic.report.tables import edge_counts

STAGES_MARK = "<!-- more stages -->"


def cm(metres: float) -> str:
    return "-" if not np.isfinite(metres) else f"{metres * 100:.2f}"


def has_loop(G: nx.Graph) -> bool:
    """Whether the kept edges close a loop: without one, every edge residual after the joint
    solve is zero by construction and says nothing about the fit."""
    K = nx.Graph([(u, v) for u, v, e in G.edges(data=True) if not e.get("dropped")])
    return K.number_of_edges() > K.number_of_nodes() - nx.number_connected_components(K)


def _edge_lines(inp: ReportInput) -> list[str]:
    G = inp.graph
    out = [edge_counts(G, len(inp.failed))]
    if not has_loop(G):
        return out
    kept = [
        (u, v, e)
        for u, v, e in G.edges(data=True)
        if not e.get("dropped") and e.get("residual_after")
    ]
    if kept:
        u, v, e = max(kept, key=lambda t: t[2]["residual_after"]["translation"])
        r = e["residual_after"]
        out.append(
            f"worst edge: {e.get('source', u)}-{e.get('target', v)}, {r['translation'] * 100:.2f} cm"
            f" / {r['rotation_deg']:.3f} deg off the joint solution"
        )
    b = inp.bundle
    if b and b.get("edges"):
        out.append(
            "bundle error (kept edges after the joint solve): translation RMS "
            f"{b['translation_rms'] * 100:.2f} cm, rotation RMS {b['rotation_rms_deg']:.3f} deg"
        )
    return out


def _plot_lines(v: PlotView) -> list[str]:
    out = []
    if v.als is not None and v.als.ground.count:
        g = v.als.ground
        out.append(
            f"plot {v.plot}: ground {g.median * 100:+.1f} cm off the ALS ground (median), "
            f"NMAD {g.nmad * 100:.1f} cm over {g.count} cells"
        )
    if v.als is not None and v.als.canopy.count:
        c = v.als.canopy
        out.append(
            f"plot {v.plot}: canopy top {c.median:+.2f} m off the ALS top (median), NMAD "
            f"{c.nmad:.2f} m over {c.count} cells where both see the top"
        )
    if v.stems:
        out.append(
            f"plot {v.plot}: {len(v.stems)} stems in the breast-height slice, median ring spread "
            f"{v.spread * 100:.2f} cm"
        )
    if v.edges:
        worst = max(v.edges, key=lambda e: e["median"])
        best = min(e["median"] for e in v.edges)
        out.append(
            f"plot {v.plot}: cloud-to-cloud median distance per edge {best * 100:.2f}"
            f"-{worst['median'] * 100:.2f} cm (worst {worst['source']}-{worst['target']})"
        )
    return out


def summary_lines(inp: ReportInput, views_: list[PlotView]) -> list[str]:
    scans = [s for ids in inp.plots.values() for s in ids]
    placed = [s for s in scans if s in inp.poses]
    not_placed = f" (not placed: {', '.join(inp.unplaced)})" if inp.unplaced else ""
    out = [f"scans placed: {len(placed)} of {len(scans)}{not_placed}", *_edge_lines(inp)]
    for v in views_:
        out += _plot_lines(v)
    return out


def _stage_rows(stages) -> list[list[object]]:
    return [
        [s.name, "not recorded" if s.seconds is None else f"{s.seconds:.1f}", s.note]
        for s in stages
    ]


def stage_table(stages) -> str:
    t = H.table(["stage", "seconds", "note"], _stage_rows(stages), "How long each stage took")
    return t.replace("</tbody>", STAGES_MARK + "</tbody>")


def add_stages(page: Path, stages: list[Stage]) -> Path:
    """Append rows to a written report.html's stage table (e.g. the demo's own stages, known only later)."""
    text = Path(page).read_text()
    rows = "".join(
        "<tr>" + "".join(f"<td>{H.esc(c)}</td>" for c in r) + "</tr>" for r in _stage_rows(stages)
    )
    return write_text_atomic(page, text.replace(STAGES_MARK, rows + STAGES_MARK, 1))


def stem_table(view: PlotView, origin: np.ndarray, n: int = 12) -> str:
    rows = []
    for k, st in enumerate(view.stems[:n]):
        c = st.centre - origin[:2]
        worst = max(st.offsets.values(), default=0.0)
        spread = f"{st.spread * 100:.2f}"
        rows.append(
            [
                k + 1,
                f"{c[0]:.2f}",
                f"{c[1]:.2f}",
                f"{st.radius * 200:.1f}",
                ", ".join(st.scans),
                spread,
                f"{worst * 100:.2f}",
            ]
        )
    header = [
        "stem",
        "x (m)",
        "y (m)",
        "DBH (cm)",
        "scans",
        "ring spread (cm)",
        "worst ring offset (cm)",
    ]
    return H.table(
        header,
        rows,
        f"Plot {view.plot}: stems in the breast-height slice, those most scans see first",
    )


def distance_tables(v: PlotView) -> list[str]:
    if not v.edges:
        return []
    rows = [
        [
            e["source"],
            e["target"],
            len(e["distances"]),
            cm(e["median"]),
            cm(e["p90"]),
            f"{e['share'] * 100:.0f}",
        ]
        for e in v.edges
    ]
    header = [
        "source",
        "target",
        "overlap points",
        "median (cm)",
        "90 % (cm)",
        "share of source in overlap (%)",
    ]
    per_scan = [[s, cm(m), cm(ring_spread(v.stems, s))] for s, m in v.medians.items()]
    return [
        H.table(header, rows, f"Plot {v.plot}: cloud-to-cloud distances of the kept edges"),
        H.table(
            ["scan", "median distance to neighbours (cm)", "median ring spread of its stems (cm)"],
            per_scan,
            f"Plot {v.plot}: per scan after the joint solve",
        ),
    ]


def als_table(v: PlotView) -> list[str]:
    if v.als is None:
        return []
    rows = [
        [
            s.scan,
            cm(s.ground.median),
            cm(s.ground.nmad),
            s.ground.count,
            f"{s.canopy.median:+.2f}" if s.canopy.count else "-",
            s.canopy.count,
        ]
        for s in v.als.scans
    ]
    header = [
        "scan",
        "ground - ALS, median (cm)",
        "NMAD (cm)",
        "cells",
        "canopy top - ALS (m)",
        "cells",
    ]
    return [H.table(header, rows, f"Plot {v.plot}: each scan against the ALS")]

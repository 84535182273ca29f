"""Plain-words warnings of a report: weak links first, then what the slice and the distances say."""

from __future__ import annotations

import networkx as nx
import numpy as np

from plotmosaic.config.report import ReportConfig
from plotmosaic.report.model import PlotView

REASONS = {
    "cycle": "its loops with the other edges do not close",
    "residual": "it disagrees with the joint solution of the others",
    "unverified": "the coarse stage was unsure and no loop confirms it",
}


def length(metres: float) -> str:
    return f"{metres * 100:.0f} cm" if metres < 1 else f"{metres:.1f} m"


def unsure_edges(G: nx.Graph, min_confidence: float) -> set[tuple[str, str]]:
    return {
        tuple(sorted((u, v)))
        for u, v, e in G.edges(data=True)
        if not e.get("dropped")
        and e.get("confidence") is not None
        and e["confidence"] < min_confidence
    }


def _link_warnings(G: nx.Graph, unplaced: list[str], unsure: set) -> list[str]:
    out = [f"scan {s} is not placed: no kept pair links it to the reference" for s in unplaced]
    # tie-to-als holds each scan to its plot's reference as register-plot placed it and the plot
    # to the ALS by one anchor, by construction: checked by register-plot's report and the fit to
    # the ALS, not by other edges
    K = nx.Graph(
        [
            (u, v)
            for u, v, e in G.edges(data=True)
            if not (e.get("dropped") or e.get("from_poses") or e.get("anchor"))
        ]
    )
    scans = [n for n in G.nodes if G.nodes[n].get("kind") != "als"]
    for n in sorted(scans) if len(scans) > 2 else []:  # a lone pair has one edge by definition
        if n in K and K.degree(n) == 1 and n not in unplaced:
            out.append(
                f"scan {n} is held by one edge only ({next(iter(K[n]))}): nothing checks that link"
            )
    order = sorted(
        G.edges(data=True), key=lambda t: (t[2].get("source", t[0]), t[2].get("target", t[1]))
    )
    for u, v, e in order:
        name = f"edge {e.get('source', u)}-{e.get('target', v)}"
        if e.get("dropped"):
            r = e.get("residual_after")
            off = (
                f"; it is {length(r['translation'])} / {r['rotation_deg']:.2f} deg off the solution"
                if r
                else ""
            )
            why = REASONS.get(e.get("drop_reason"), e.get("drop_reason"))
            out.append(f"{name} dropped: {why}{off}")
        elif tuple(sorted((u, v))) in unsure:
            out.append(
                f"{name} was ambiguous (coarse confidence {e['confidence']:.2f}); "
                "kept because a loop confirms it"
            )
    return out


def _plot_warnings(v: PlotView, cfg: ReportConfig) -> list[str]:
    out = []
    if np.isfinite(v.spread) and v.spread > cfg.weak_ring_spread:
        out.append(
            f"plot {v.plot}: stem rings at breast height are {v.spread * 100:.1f} cm apart "
            "(median): doubled stems, a scan is off"
        )
    for s, m in v.medians.items():
        if m > cfg.weak_distance:
            out.append(
                f"scan {s}: median distance to its neighbours is {m * 100:.1f} cm after the joint solve"
            )
    if v.ground is not None and not v.stems:
        out.append(
            f"plot {v.plot}: no stem seen by two scans in the breast-height slice "
            "(too sparse, or no trees)"
        )
    if v.als is not None and abs(v.als.ground.median) > cfg.weak_ground_offset:
        out.append(
            f"plot {v.plot}: its ground is {v.als.ground.median * 100:+.1f} cm off the ALS ground "
            "(median): the plot sits too high or too low"
        )
    return out


def warnings_for(
    G: nx.Graph,
    views_: list[PlotView],
    unplaced: list[str],
    failed: list[dict],
    cfg: ReportConfig,
    unsure: set,
) -> list[str]:
    """Plain-words warnings: weak links first, then what the slice and the distances say."""
    out = _link_warnings(G, list(unplaced), unsure)
    out += [
        f"pair {f['source']}-{f['target']} could not be registered: {f.get('error')}"
        for f in failed
    ]
    for v in views_:
        out += _plot_warnings(v, cfg)
    return out

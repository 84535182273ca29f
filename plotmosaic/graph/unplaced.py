"""Why a scan is not placed: its best attempt, for the report and the command's summary."""

from __future__ import annotations

from dataclasses import dataclass

import networkx as nx


@dataclass(frozen=True, kw_only=True)
class Unplaced:
    """Why a scan is not placed: its best attempt (the highest overlap it reached), or none."""

    scan: str
    partner: str | None  # the other scan of that attempt (None: no pair was tried)
    overlap: float | None
    why: str

    def line(self) -> str:
        if self.partner is None:
            return f"{self.scan}: {self.why}"
        return f"{self.scan}: best overlap {self.overlap:.3f} with {self.partner} ({self.why})"


def unplaced_reasons(G: nx.Graph, unplaced: list[str]) -> list[Unplaced]:
    """Each unplaced scan with its best attempt: a refused pair or a dropped edge, whichever reached
    the highest overlap, and the reason it was not used."""
    attempts: dict[str, list[tuple[float, str, str]]] = {}
    for f in G.graph.get("failed", []):
        why = str(f.get("error") or "failed").removeprefix("pair cannot be registered: ")
        for a, b in ((f["source"], f["target"]), (f["target"], f["source"])):
            attempts.setdefault(a, []).append((float(f.get("overlap") or 0.0), b, why))
    for u, v, e in G.edges(data=True):
        if e.get("dropped"):
            why = f"edge dropped: {e.get('drop_reason')}"
            for a, b in ((u, v), (v, u)):
                attempts.setdefault(a, []).append((float(e.get("overlap") or 0.0), b, why))
    out = []
    for scan in unplaced:
        tried = sorted(attempts.get(scan, []), key=lambda t: (-t[0], t[1]))
        if not tried:
            out.append(Unplaced(scan=scan, partner=None, overlap=None, why="no pair was tried"))
            continue
        overlap, partner, why = tried[0]
        out.append(Unplaced(scan=scan, partner=partner, overlap=overlap, why=why.split(" (")[0]))
    return out

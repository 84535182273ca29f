"""report.md's tables of a run (poses, edges) and the figures several pages share."""

from __future__ import annotations

from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.report.model import Figure, Stage


def fmt(value, scale=1.0, digits=1) -> str:
    return "-" if value is None else f"{value * scale:.{digits}f}"


def yaw_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def edge_counts(G: nx.Graph, failed: int) -> str:
    kept = sum(1 for *_, e in G.edges(data=True) if not e.get("dropped"))
    return f"edges: {kept} kept, {G.number_of_edges() - kept} dropped, {failed} pairs failed"


def edge_table(G: nx.Graph) -> list[str]:
    rows = [
        "| source | target | fitness | RMSE (cm) | overlap | before (cm / deg) | after (cm / deg) | chi2 after | status |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for _u, _v, e in sorted(G.edges(data=True), key=lambda t: (t[2]["source"], t[2]["target"])):
        b, a = e.get("residual_before"), e.get("residual_after")
        status = f"**dropped** ({e.get('drop_reason')})" if e.get("dropped") else "kept"
        rows.append(
            f"| {e['source']} | {e['target']} | {fmt(e.get('fitness'), 1, 3)} | {fmt(e.get('inlier_rmse'), 100, 2)} "
            f"| {fmt(e.get('overlap'), 1, 3)} | {fmt(b and b['translation'], 100, 2)} / {fmt(b and b['rotation_deg'], 1, 3)} "
            f"| {fmt(a and a['translation'], 100, 2)} / {fmt(a and a['rotation_deg'], 1, 3)} | {fmt(a and a['chi2'], 1, 1)} | {status} |"
        )
    return rows


def pose_table(
    names: list[str], poses: dict[str, np.ndarray], sigmas: dict[str, np.ndarray]
) -> list[str]:
    rows = [
        "| scan | x (m) | y (m) | z (m) | yaw (deg) | tilt (deg) | sigma xyz (mm) | sigma rot (deg) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n in names:
        if n not in poses:
            rows.append(f"| {n} | unplaced | | | | | | |")
            continue
        T, s = poses[n], sigmas.get(n)
        tilt = float(np.degrees(np.arccos(np.clip(T[2, 2], -1, 1))))
        sig_t = "-" if s is None else " / ".join(f"{v * 1000:.1f}" for v in s[3:])
        sig_r = "-" if s is None else " / ".join(f"{np.degrees(v):.4f}" for v in s[:3])
        rows.append(
            f"| {n} | {T[0, 3]:.3f} | {T[1, 3]:.3f} | {T[2, 3]:.3f} | {yaw_deg(T):.2f} | {tilt:.2f} | {sig_t} | {sig_r} |"
        )
    return rows


def residual_summary(G: nx.Graph) -> dict:
    kept = [
        e["residual_after"]
        for _, _, e in G.edges(data=True)
        if not e.get("dropped") and e.get("residual_after")
    ]
    if not kept:
        return {"edges": 0}
    t = np.array([r["translation"] for r in kept])
    r = np.array([r["rotation_deg"] for r in kept])
    return {
        "edges": len(kept),
        "translation_rms": float(np.sqrt(np.mean(t**2))),
        "translation_max": float(t.max()),
        "rotation_rms_deg": float(np.sqrt(np.mean(r**2))),
        "rotation_max_deg": float(r.max()),
    }


def pair_seconds(G: nx.Graph, anchors_only: bool = False) -> tuple[float | None, int]:
    """Sum of the recorded per-pair times over the graph's edges (cached pairs keep their first run's time)."""
    secs = [
        e["seconds"]
        for *_, e in G.edges(data=True)
        if isinstance(e.get("seconds"), (int, float)) and (e.get("anchor") or not anchors_only)
    ]
    return (float(sum(secs)) if secs else None), len(secs)


def recorded(result) -> list[Stage]:
    """Stages a result records in a `timings` dict (name -> wall seconds), when its pipeline keeps one."""
    timings = getattr(result, "timings", None)
    if not isinstance(timings, dict):
        return []
    return [
        Stage(k, float(v), "wall time") for k, v in timings.items() if isinstance(v, (int, float))
    ]


def md_figures(figures: list[Figure], plot: str | None = None) -> list[str]:
    """report.md's picture lines (a plot's, or all), each followed by how to read it."""
    lines = []
    for f in figures:
        if plot is None or f.plot == plot:
            lines += [f"![{f.caption}]({Path(f.png).name})", ""]
            if f.read:
                lines += [f"*How to read:* {f.read}", ""]
    return lines

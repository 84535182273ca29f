"""report.md and pictures for register-plot / tie-to-als: what was kept, dropped, and where scans sit."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.config.report import ReportConfig
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import apply_transform, inverse, pose_error
from plotmosaic.io.las import read_cloud
from plotmosaic.report.build import ReportInput, Stage, build_report
from plotmosaic.report.views import plot_map


def _fmt(value, scale=1.0, digits=1) -> str:
    return "-" if value is None else f"{value * scale:.{digits}f}"


def yaw_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(T[1, 0], T[0, 0])))


def edge_table(G: nx.Graph) -> list[str]:
    rows = [
        "| source | target | fitness | RMSE (cm) | overlap | before (cm / deg) | after (cm / deg) | chi2 after | status |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for _u, _v, e in sorted(G.edges(data=True), key=lambda t: (t[2]["source"], t[2]["target"])):
        b, a = e.get("residual_before"), e.get("residual_after")
        status = f"**dropped** ({e.get('drop_reason')})" if e.get("dropped") else "kept"
        rows.append(
            f"| {e['source']} | {e['target']} | {_fmt(e.get('fitness'), 1, 3)} | {_fmt(e.get('inlier_rmse'), 100, 2)} "
            f"| {_fmt(e.get('overlap'), 1, 3)} | {_fmt(b and b['translation'], 100, 2)} / {_fmt(b and b['rotation_deg'], 1, 3)} "
            f"| {_fmt(a and a['translation'], 100, 2)} / {_fmt(a and a['rotation_deg'], 1, 3)} | {_fmt(a and a['chi2'], 1, 1)} | {status} |"
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
        R = T[:3, :3]
        tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))))
        sig_t = "-" if s is None else " / ".join(f"{v * 1000:.1f}" for v in s[3:])
        sig_r = "-" if s is None else " / ".join(f"{np.degrees(v):.4f}" for v in s[:3])
        rows.append(
            f"| {n} | {T[0, 3]:.3f} | {T[1, 3]:.3f} | {T[2, 3]:.3f} | {yaw_deg(T):.2f} | {tilt:.2f} | {sig_t} | {sig_r} |"
        )
    return rows


def sample_clouds(
    paths: dict[str, Path],
    poses: dict[str, np.ndarray],
    n_points: int,
    seed: int,
    reader: Callable[[Path], np.ndarray],
) -> dict[str, np.ndarray]:
    """A seeded random subset of each placed scan, moved into the common frame."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, path in paths.items():
        if name not in poses:
            continue
        xyz = reader(path)
        if len(xyz) > n_points:
            xyz = xyz[rng.choice(len(xyz), n_points, replace=False)]
        out[name] = apply_transform(poses[name], xyz)
    return out


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


# ---------------------------------------------------------------- report.md + report.html of a run


def _read_scan(path: Path) -> np.ndarray:

    return read_cloud(path, attributes=False).xyz


def _pair_seconds(G: nx.Graph, nodes: list[str] | None = None) -> tuple[float | None, int]:
    """Sum of the recorded per-pair times over the graph's edges (cached pairs keep their first run's time)."""
    sub = G if nodes is None else G.subgraph(nodes)
    secs = [
        e["seconds"] for *_, e in sub.edges(data=True) if isinstance(e.get("seconds"), (int, float))
    ]
    return (float(sum(secs)) if secs else None), len(secs)


def _md_figures(figures: list[tuple[str, str, Path]], plot: str) -> list[str]:
    lines = []
    for p, caption, png in figures:
        if p == plot:
            lines += [f"![{caption}]({png.name})", ""]
    return lines


def _recorded(result) -> list:
    """Stages a result records in a `timings` dict (name -> wall seconds), when its pipeline keeps one."""
    timings = getattr(result, "timings", None)
    return (
        [Stage(k, float(v), "wall time") for k, v in timings.items() if isinstance(v, (int, float))]
        if isinstance(timings, dict)
        else []
    )


def write_register_report(
    result, manifest, config, seed: int, reader: Callable[[Path], np.ndarray] | None = None
) -> Path:
    """report.md (tables, pictures) and report.html (summary, breast-height slice, distances, map) of register-plot."""
    out, G = result.out, result.graph
    kept = sum(1 for *_, e in G.edges(data=True) if not e.get("dropped"))
    dropped = G.number_of_edges() - kept
    lines = [
        "# register-plot report",
        "",
        f"- manifest: `{manifest.source}`",
        f"- pairs: {result.pairs} ({result.computed} registered in this run, {result.pairs - result.computed} from the cache)",
        f"- edges: {kept} kept, {dropped} dropped, {len(result.failed)} pairs failed",
        f"- time: {result.seconds:.1f} s",
        "",
        "The same in one page, with the breast-height slice, cloud-to-cloud distances and a map: [report.html](report.html)",
        "",
    ]
    if result.unplaced:
        lines += [
            f"**Not placed** (no pair left linking them to the reference): {', '.join(result.unplaced)}",
            "",
        ]
    poses = {n: T for r in result.plots for n, T in r.solution.poses.items()}
    pair_s, n_timed = _pair_seconds(G)
    stages = [
        Stage(
            "pairwise registration",
            pair_s,
            f"sum of the per-pair times of {n_timed} pairs ({result.computed} run now, "
            "the rest from the cache); the pairs ran in parallel, so the wall time is shorter",
        ),
        Stage(
            "register-plot until this report",
            result.seconds,
            "pairs, pose graph and its checks, poses.json",
        ),
        *_recorded(result),
    ]
    tables = []
    for r in result.plots:
        tables += [
            (
                f"Plot {r.plot}: poses (plot frame)",
                pose_table(r.scans, r.solution.poses, r.solution.sigmas),
            ),
            (f"Plot {r.plot}: edges", edge_table(G.subgraph(r.scans))),
        ]
    inp = ReportInput(
        title="register-plot report",
        out=out,
        graph=G,
        poses=poses,
        paths={n: Path(G.nodes[n]["path"]) for n in G.nodes if "path" in G.nodes[n]},
        plots={r.plot: r.scans for r in result.plots},
        reader=reader or _read_scan,
        stages=stages,
        unplaced=result.unplaced,
        failed=result.failed,
        tables_md=tables,
        facts=[
            f"manifest: {manifest.source}",
            "frame: the plot frame (each plot's reference scan)",
        ],
        min_confidence=getattr(
            getattr(config, "graph", None), "min_confidence", PoseGraphConfig().min_confidence
        ),
        bundle=residual_summary(G),
    )
    cfg = getattr(config, "report", None) or ReportConfig()
    _, figures = build_report(inp, cfg, seed, overview=True)
    for r in result.plots:
        sub = G.subgraph(r.scans)
        s = residual_summary(sub)
        lines += [f"## Plot {r.plot}", "", f"Reference scan (plot frame): **{r.reference}**.", ""]
        if r.unplaced:
            lines += [f"Not placed: **{', '.join(r.unplaced)}**.", ""]
        if r.solution.dropped:
            lines += [
                "Dropped edges (inconsistent): "
                + ", ".join(
                    f"{d['source']} -> {d['target']} ({d['reason']})" for d in r.solution.dropped
                ),
                "",
            ]
        if s["edges"]:
            lines += [
                (
                    f"Kept-edge residuals after optimisation: translation RMS {s['translation_rms'] * 100:.2f} cm "
                    f"(max {s['translation_max'] * 100:.2f}), rotation RMS {s['rotation_rms_deg']:.3f} deg "
                    f"(max {s['rotation_max_deg']:.3f})."
                ),
                "",
            ]
        lines += ["### Poses", ""] + pose_table(r.scans, r.solution.poses, r.solution.sigmas) + [""]
        lines += [
            "### Edges",
            "",
            "Residuals before = at the spanning-tree initialisation, after = at the optimised poses.",
            "",
        ]
        lines += edge_table(sub) + [""]
        failed = [f for f in result.failed if f["source"] in r.scans]
        if failed:
            lines += (
                ["### Failed pairs", ""]
                + [f"- {f['source']} -> {f['target']}: {f.get('error')}" for f in failed]
                + [""]
            )
        graph_png = plot_map(
            out / f"{r.plot}_graph.png",
            sub,
            {n: T[:3, 3] for n, T in r.solution.poses.items()},
            None,
            f"plot {r.plot}: pose graph",
            np.zeros(3),
        )
        lines += _md_figures(figures, r.plot) + [f"![graph]({graph_png.name})", ""]
    return write_text_atomic(out / "report.md", "\n".join(lines))


def rigid_plots(result, earlier, earlier_report: Path | None, cfg) -> dict[str, tuple[str, str]]:
    """Plots the region solve moved as one piece (each scan's pose relative to the plot's reference
    as register-plot left it, within the report's rigid tolerance): judged in register-plot's report."""
    if earlier is None or earlier_report is None or not Path(earlier_report).is_file():
        return {}
    after = result.poses
    out = {}
    for a in result.anchors:
        ref = a.reference
        scans = [s for s in after.scans if after.scans[s].plot == a.plot]
        if (
            a.status != "ok"
            or ref not in earlier.scans
            or any(s not in earlier.scans for s in scans)
        ):
            continue
        worst_t = worst_r = 0.0
        for s in scans:
            before = inverse(earlier.transform(ref)) @ earlier.transform(s)
            now = inverse(after.transform(ref)) @ after.transform(s)
            r, t = pose_error(now, before)
            worst_t, worst_r = max(worst_t, t), max(worst_r, r)
        if worst_t <= cfg.rigid_translation and worst_r <= cfg.rigid_rotation_deg:
            out[a.plot] = (
                os.path.relpath(earlier_report, result.out),
                f"The region solve moved plot {a.plot} as one piece (its scans relative to {ref} "
                f"changed by at most {worst_t * 1000:.2f} mm / {worst_r:.4f} deg)",
            )
    return out


def write_tie_report(
    result,
    manifest,
    als,
    config,
    seed: int,
    reader: Callable[[Path], np.ndarray] | None = None,
    earlier=None,
    earlier_report: Path | None = None,
) -> Path:
    """report.md and report.html of tie-to-als: anchors, poses in the ALS CRS, slice and distances, map over the ALS CHM.

    `earlier` (register-plot's poses) and `earlier_report` (its report.html): a plot the region solve
    moved rigidly is shown over the ALS, its within-plot checks are linked, not recomputed."""
    out, G = result.out, result.graph
    lines = [
        "# tie-to-als report",
        "",
        f"- manifest: `{manifest.source}`",
        f"- region solved in ALS CRS minus offset ({', '.join(f'{v:.0f}' for v in result.offset)})",
        f"- plot -> ALS registrations: {len(result.anchors)} ({result.computed} run now, rest cached)",
        "",
        (
            "The same in one page, with the breast-height slice, cloud-to-cloud distances and a map over the ALS "
            "canopy height: [report.html](report.html)"
        ),
        "",
    ]
    if result.unplaced:
        lines += [f"**Not placed**: {', '.join(result.unplaced)}", ""]
    anchor_rows = [
        "| plot | reference scan | status | fitness | inlier RMSE (cm) | overlap | ALS crop | anchor residual (cm / deg) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for a in result.anchors:
        r = a.residual
        res = "-" if not r else f"{r['translation'] * 100:.2f} / {r['rotation_deg']:.3f}"
        status = a.status if a.status == "ok" else f"failed: {a.error}"
        anchor_rows.append(
            f"| {a.plot} | {a.reference} | {status} | {_fmt(a.fitness, 1, 3)} | {_fmt(a.inlier_rmse, 100, 2)} "
            f"| {_fmt(a.overlap, 1, 3)} | {a.crop} | {res} |"
        )
    pose_rows = pose_table(
        [s.id for s in manifest.scans],
        {k: v.transform for k, v in result.poses.scans.items()},
        {k: v.sigma for k, v in result.poses.scans.items()},
    )
    edge_rows = edge_table(G)
    lines += [
        "## Anchors (plot -> ALS)",
        "",
        *anchor_rows,
        "",
        "## Poses (ALS CRS)",
        "",
        *pose_rows,
        "",
        "## Edges",
        "",
        *edge_rows,
        "",
    ]
    poses = {k: v.transform for k, v in result.poses.scans.items()}
    plots = {p.id: [s.id for s in p.scans] for p in manifest.plots}
    anchor_s = [
        e.get("seconds")
        for *_, e in G.edges(data=True)
        if e.get("anchor") and isinstance(e.get("seconds"), (int, float))
    ]
    stages = [
        Stage(
            "plot -> ALS registration",
            float(sum(anchor_s)) if anchor_s else None,
            f"sum of the per-pair times of {len(anchor_s)} anchor pairs ({result.computed} run now)",
        ),
        Stage(
            "tie-to-als until this report",
            result.seconds,
            "ALS crop, plot -> ALS pairs, region pose graph, poses.json",
        ),
        *_recorded(result),
    ]
    als_xyz = _als_near(als.xyz, poses, 40.0)
    cfg = getattr(config, "report", None) or ReportConfig()
    judged = rigid_plots(result, earlier, earlier_report, cfg)
    inp = ReportInput(
        title="tie-to-als report (georeferenced)",
        out=out,
        graph=G,
        poses=poses,
        paths={s.id: manifest.resolve(s.path) for s in manifest.scans},
        plots=plots,
        reader=reader or _read_scan,
        stages=stages,
        unplaced=result.unplaced,
        tables_md=[
            ("Anchors (plot -> ALS)", anchor_rows),
            ("Poses (ALS CRS)", pose_rows),
            ("Edges", edge_rows),
        ],
        facts=[f"manifest: {manifest.source}", "frame: the ALS CRS"]
        + [_anchor_fact(a) for a in result.anchors],
        als_xyz=als_xyz,
        judged_in=judged,
        min_confidence=getattr(
            getattr(config, "graph", None), "min_confidence", PoseGraphConfig().min_confidence
        ),
        bundle=residual_summary(G),
    )
    _, figures = build_report(inp, cfg, seed, overview=True)
    for p in plots:
        if p in judged:
            href, why = judged[p]
            lines += [f"{why}: its within-plot checks are in [{href}]({href}).", ""]
        lines += _md_figures(figures, p)
    return write_text_atomic(out / "report.md", "\n".join(lines))


def _anchor_fact(a) -> str:
    if a.status != "ok":
        return f"plot {a.plot} -> ALS: failed ({a.error})"
    r = a.residual
    res = (
        f", {r['translation'] * 100:.2f} cm / {r['rotation_deg']:.3f} deg off the joint solution"
        if r
        else ""
    )
    return (
        f"plot {a.plot} -> ALS (through {a.reference}): fitness {_fmt(a.fitness, 1, 3)}, "
        f"inlier RMSE {_fmt(a.inlier_rmse, 100, 1)} cm{res}"
    )


def _als_near(
    als_xyz: np.ndarray, poses: dict[str, np.ndarray], margin: float
) -> np.ndarray | None:
    """ALS points within `margin` of the scanners' bounding box: the map's canopy-height background."""
    if not len(als_xyz) or not poses:
        return None
    xy = np.array([T[:2, 3] for T in poses.values()])
    lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    keep = np.all((als_xyz[:, :2] >= lo) & (als_xyz[:, :2] <= hi), axis=1)
    return als_xyz[keep] if keep.sum() >= 100 else None

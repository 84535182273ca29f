"""register-plot's report (report.md and report.html): what was kept, dropped, and where scans sit.

Rendered from a `RegisterRun`: built by register-plot from its result, or by `plotmosaic report`
from the folder the run wrote (poses.json, graph.json), so both write the same page."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.config.report import ReportConfig
from plotmosaic.graph.unplaced import unplaced_reasons
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.report import tables
from plotmosaic.report.build import build_report
from plotmosaic.report.collect import read_scan
from plotmosaic.report.model import ReportInput, Stage
from plotmosaic.report.views import plot_map


@dataclass(frozen=True, kw_only=True)
class PlotRun:
    """One plot as register-plot solved it."""

    plot: str
    reference: str
    scans: tuple[str, ...]
    poses: dict[str, np.ndarray]  # placed scans, plot frame
    sigmas: dict[str, np.ndarray]
    dropped: tuple[dict, ...] = ()  # {"source", "target", "reason"}
    unplaced: tuple[str, ...] = ()


@dataclass(frozen=True, kw_only=True)
class RegisterRun:
    """What register-plot's report shows; `None` where the folder does not record it."""

    out: Path
    graph: nx.Graph
    plots: tuple[PlotRun, ...]
    paths: dict[str, Path]
    source: str  # where the scans came from, as a summary line ("manifest: ..." or "folder: ...")
    pairs: int | None = None
    computed: int | None = None
    failed: tuple[dict, ...] = ()
    seconds: float | None = None
    stages: tuple[Stage, ...] = ()  # stages the run timed itself

    @property
    def unplaced(self) -> list[str]:
        return [s for p in self.plots for s in p.unplaced]


def run_of(result, manifest) -> RegisterRun:
    """The RegisterRun of register-plot's result."""
    G = result.graph
    plots = tuple(
        PlotRun(
            plot=r.plot,
            reference=r.reference,
            scans=tuple(r.scans),
            poses=dict(r.solution.poses),
            sigmas=dict(r.solution.sigmas),
            dropped=tuple(r.solution.dropped),
            unplaced=tuple(r.unplaced),
        )
        for r in result.plots
    )
    return RegisterRun(
        out=result.out,
        graph=G,
        plots=plots,
        paths={n: Path(G.nodes[n]["path"]) for n in G.nodes if "path" in G.nodes[n]},
        source=f"manifest: {manifest.source}",
        pairs=result.pairs,
        computed=result.computed,
        failed=tuple(result.failed),
        seconds=result.seconds,
        stages=tuple(tables.recorded(result)),
    )


def _stages(run: RegisterRun) -> list[Stage]:
    pair_s, n_timed = tables.pair_seconds(run.graph)
    now = "" if run.computed is None else f" ({run.computed} run now, the rest from the cache)"
    return [
        Stage(
            "pairwise registration",
            pair_s,
            f"sum of the per-pair times of {n_timed} pairs{now}; the pairs ran in parallel, so "
            "the wall time is shorter",
        ),
        Stage(
            "register-plot until this report",
            run.seconds,
            "pairs, pose graph and its checks, poses.json",
        ),
        *run.stages,
    ]


def _head(run: RegisterRun) -> list[str]:
    lines = ["# register-plot report", "", f"- {run.source}"]
    if run.pairs is not None:
        cached = (
            ""
            if run.computed is None
            else f" ({run.computed} registered in this run, {run.pairs - run.computed} from the cache)"
        )
        lines.append(f"- pairs: {run.pairs}{cached}")
    lines.append(f"- {tables.edge_counts(run.graph, len(run.failed))}")
    if run.seconds is not None:
        lines.append(f"- time: {run.seconds:.1f} s")
    lines += [
        "",
        "The same in one page, with the breast-height slice, cloud-to-cloud distances and a map: "
        "[report.html](report.html)",
        "",
    ]
    if run.unplaced:
        lines += [
            "**Not placed** (nothing links them to the reference: no verified pair, map or ALS"
            " placement):",
            "",
            *(f"- {u.line()}" for u in unplaced_reasons(run.graph, run.unplaced)),
            "",
        ]
    return lines


def _calibration(G: nx.Graph, plot: str) -> list[str]:
    """How the plot's sigmas were scaled: each edge group's residuals against its claimed noise."""
    groups = G.graph.get("calibration", {}).get(plot) or {}
    if not groups:
        return []
    rows = [
        f"| {name.replace('/', ' ')} | {g['factor']:.2f} | x {np.sqrt(g['factor']):.2f} "
        f"| {g['redundancy']:.0f} |"
        for name, g in sorted(groups.items())
    ]
    return [
        "Sigmas calibrated on the kept edges' residuals (a variance factor above 1: the pairs "
        "were noisier than their information said, so their sigmas grew):",
        "",
        "| edge group | variance factor | sigmas | redundancy (dof) |",
        "|---|---|---|---|",
        *rows,
        "",
    ]


def _plot_md(run: RegisterRun, r: PlotRun, figures) -> list[str]:
    sub = run.graph.subgraph(r.scans)
    s = tables.residual_summary(sub)
    lines = [f"## Plot {r.plot}", "", f"Reference scan (plot frame): **{r.reference}**.", ""]
    if r.unplaced:
        lines += [f"Not placed: **{', '.join(r.unplaced)}**.", ""]
    if r.dropped:
        dropped = ", ".join(f"{d['source']} -> {d['target']} ({d['reason']})" for d in r.dropped)
        lines += [f"Dropped edges (inconsistent): {dropped}", ""]
    if s["edges"]:
        lines += [
            f"Kept-edge residuals after optimisation: translation RMS {s['translation_rms'] * 100:.2f} cm "
            f"(max {s['translation_max'] * 100:.2f}), rotation RMS {s['rotation_rms_deg']:.3f} deg "
            f"(max {s['rotation_max_deg']:.3f}).",
            "",
        ]
    lines += _calibration(run.graph, r.plot)
    lines += ["### Poses", "", *tables.pose_table(list(r.scans), r.poses, r.sigmas), ""]
    lines += [
        "### Edges",
        "",
        "Residuals before = at the spanning-tree initialisation, after = at the optimised poses.",
        "",
        *tables.edge_table(sub),
        "",
    ]
    failed = [f for f in run.failed if f["source"] in r.scans]
    if failed:
        lines += [
            "### Failed pairs",
            "",
            *[f"- {f['source']} -> {f['target']}: {f.get('error')}" for f in failed],
            "",
        ]
    positions = {n: T[:3, 3] for n, T in r.poses.items()}
    title = f"plot {r.plot}: pose graph"
    graph_png = plot_map(run.out / f"{r.plot}_graph.png", sub, positions, None, title, np.zeros(3))
    return lines + tables.md_figures(figures, r.plot) + [f"![graph]({graph_png.name})", ""]


def render_register(
    run: RegisterRun,
    cfg: ReportConfig,
    min_confidence: float,
    seed: int,
    reader: Callable[[Path], np.ndarray],
) -> Path:
    """report.md and report.html (with the run's view3d.html) of a register-plot run."""
    md_tables = []
    for r in run.plots:
        md_tables += [
            (
                f"Plot {r.plot}: poses (plot frame)",
                tables.pose_table(list(r.scans), r.poses, r.sigmas),
            ),
            (f"Plot {r.plot}: edges", tables.edge_table(run.graph.subgraph(r.scans))),
        ]
        if calibration := _calibration(run.graph, r.plot):
            md_tables.append((f"Plot {r.plot}: sigma calibration", calibration))
    inp = ReportInput(
        title="register-plot report",
        out=run.out,
        graph=run.graph,
        poses={n: T for r in run.plots for n, T in r.poses.items()},
        paths=run.paths,
        plots={r.plot: list(r.scans) for r in run.plots},
        reader=reader,
        stages=tuple(_stages(run)),
        unplaced=tuple(run.unplaced),
        failed=run.failed,
        tables_md=tuple(md_tables),
        facts=(run.source, "frame: the plot frame (each plot's reference scan)"),
        min_confidence=min_confidence,
        bundle=tables.residual_summary(run.graph),
        overview=True,
    )
    _, figures = build_report(inp, cfg, seed)
    lines = _head(run)
    for r in run.plots:
        lines += _plot_md(run, r, figures)
    return write_text_atomic(run.out / "report.md", "\n".join(lines))


def write_register_report(
    result, manifest, config, seed: int, reader: Callable[[Path], np.ndarray] | None = None
) -> Path:
    """report.md and report.html of register-plot's result (`reader`: a scan's points; default
    its file)."""
    cfg = getattr(config, "report", None) or ReportConfig()
    graph_cfg = getattr(config, "graph", None) or PoseGraphConfig()
    run = run_of(result, manifest)
    return render_register(run, cfg, graph_cfg.sure_edge_confidence, seed, reader or read_scan)

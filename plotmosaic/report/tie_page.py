"""tie-to-als's report (report.md and report.html, georeferenced): how each plot sits on the ALS.

Rendered from a `TieRun`: built by tie-to-als from its result, or by `plotmosaic report` from the
folder the run wrote (poses.json, graph.json, plots/*_als.laz), so both write the same page. The
page leads with the fit to the ALS (ground, canopy, per scan), then each plot's breast-height
slice and map; edge residuals that are zero by construction (no loop: one anchor per plot) are
left out."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.config.report import ReportConfig
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import inverse, pose_error
from plotmosaic.report import tables
from plotmosaic.report.build import build_report
from plotmosaic.report.collect import read_scan
from plotmosaic.report.model import ReportInput, Stage
from plotmosaic.report.tables import fmt


@dataclass(frozen=True, kw_only=True)
class AnchorRow:
    """One plot's registration to the ALS, as the run recorded it."""

    plot: str
    reference: str
    status: str
    fitness: float | None = None
    inlier_rmse: float | None = None
    overlap: float | None = None
    crop: str = ""
    error: str | None = None
    fine_margin: float | None = None  # the judge's margin of the pair's fine pose
    als_offset_median_m: float | None = None  # ALS returns minus the TLS surfaces, median (m)
    als_offset_nmad_m: float | None = None


@dataclass(frozen=True, kw_only=True)
class TieRun:
    """What tie-to-als's report shows; `None` where the folder does not record it."""

    out: Path
    graph: nx.Graph
    anchors: tuple[AnchorRow, ...]
    poses: dict[str, np.ndarray]  # ALS CRS
    sigmas: dict[str, np.ndarray]
    plots: dict[str, list[str]]
    paths: dict[str, Path]
    offset: np.ndarray
    als_xyz: np.ndarray | None  # the ALS around the scanners
    source: str  # where the scans came from, as a summary line ("manifest: ..." or "folder: ...")
    unplaced: tuple[str, ...] = ()
    computed: int | None = None
    seconds: float | None = None
    stages: tuple[Stage, ...] = ()
    judged_in: dict[str, tuple[str, str]] = field(default_factory=dict)


def als_near(als_xyz: np.ndarray, poses: dict[str, np.ndarray], margin: float):
    """ALS points within `margin` of the scanners' bounding box; None with too few."""
    if not len(als_xyz) or not poses:
        return None
    xy = np.array([T[:2, 3] for T in poses.values()])
    lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    keep = np.all((als_xyz[:, :2] >= lo) & (als_xyz[:, :2] <= hi), axis=1)
    return als_xyz[keep] if keep.sum() >= 100 else None


def anchor_rows(anchors: tuple[AnchorRow, ...]) -> list[str]:
    head = (
        "| plot | reference scan | status | fitness | inlier RMSE (cm) | overlap | fine margin "
        "| ALS - TLS surfaces, median (cm) | NMAD (cm) | ALS crop |"
    )
    rows = [head, "|---" * 10 + "|"]
    for a in anchors:
        status = a.status if a.status == "ok" else f"failed: {a.error}"
        rows.append(
            f"| {a.plot} | {a.reference} | {status} | {fmt(a.fitness, 1, 3)} | {fmt(a.inlier_rmse, 100, 2)} "
            f"| {fmt(a.overlap, 1, 3)} | {fmt(a.fine_margin, 1, 2)} | {fmt(a.als_offset_median_m, 100, 2)} "
            f"| {fmt(a.als_offset_nmad_m, 100, 2)} | {a.crop} |"
        )
    return rows


def anchor_fact(a: AnchorRow) -> str:
    if a.status != "ok":
        return f"plot {a.plot} -> ALS: failed ({a.error})"
    profile = (
        f", ALS returns {a.als_offset_median_m * 100:+.1f} cm off the TLS surfaces (median, NMAD "
        f"{fmt(a.als_offset_nmad_m, 100, 1)} cm)"
        if a.als_offset_median_m is not None
        else ""
    )
    margin = f", fine margin {a.fine_margin:.2f}" if a.fine_margin is not None else ""
    return (
        f"plot {a.plot} -> ALS (through {a.reference}): fitness {fmt(a.fitness, 1, 3)}, "
        f"inlier RMSE {fmt(a.inlier_rmse, 100, 1)} cm{profile}{margin}"
    )


def _stages(run: TieRun) -> list[Stage]:
    secs, n = tables.pair_seconds(run.graph, anchors_only=True)
    now = "" if run.computed is None else f" ({run.computed} run now)"
    return [
        Stage(
            "plot -> ALS registration", secs, f"sum of the per-pair times of {n} anchor pairs{now}"
        ),
        Stage(
            "tie-to-als until this report",
            run.seconds,
            "ALS crop, plot -> ALS pairs, region pose graph, poses.json",
        ),
        *run.stages,
    ]


def render_tie(
    run: TieRun,
    cfg: ReportConfig,
    min_confidence: float,
    seed: int,
    reader: Callable[[Path], np.ndarray],
) -> Path:
    """report.md and report.html (with the run's view3d.html) of a tie-to-als run."""
    anchors = anchor_rows(run.anchors)
    poses = tables.pose_table([s for ids in run.plots.values() for s in ids], run.poses, run.sigmas)
    edges = tables.edge_table(run.graph)
    inp = ReportInput(
        title="tie-to-als report (georeferenced)",
        out=run.out,
        graph=run.graph,
        poses=run.poses,
        paths=run.paths,
        plots=run.plots,
        reader=reader,
        stages=tuple(_stages(run)),
        unplaced=run.unplaced,
        tables_md=(
            ("Anchors (plot -> ALS)", anchors),
            ("Poses (ALS CRS)", poses),
            ("Edges", edges),
        ),
        facts=(run.source, "frame: the ALS CRS", *(anchor_fact(a) for a in run.anchors)),
        als_xyz=run.als_xyz,
        judged_in=run.judged_in,
        min_confidence=min_confidence,
        bundle=tables.residual_summary(run.graph),
        overview=True,
    )
    _, figures = build_report(inp, cfg, seed)
    lines = [
        "# tie-to-als report",
        "",
        f"- {run.source}",
        f"- region solved in ALS CRS minus offset ({', '.join(f'{v:.0f}' for v in run.offset)})",
        f"- plot -> ALS registrations: {len(run.anchors)}"
        + ("" if run.computed is None else f" ({run.computed} run now, rest cached)"),
        "",
        "The same in one page, with the fit to the ALS, the breast-height slice and a map over the "
        "ALS canopy height: [report.html](report.html)",
        "",
    ]
    if run.unplaced:
        lines += [f"**Not placed**: {', '.join(run.unplaced)}", ""]
    for p in run.plots:
        lines += [f"## Plot {p}", ""]
        if p in run.judged_in:
            href, why = run.judged_in[p]
            lines += [f"{why}: its cloud-to-cloud distances are in [{href}]({href}).", ""]
        lines += tables.md_figures(figures, p)
    lines += ["## Anchors (plot -> ALS)", "", *anchors, "", "## Poses (ALS CRS)", "", *poses, ""]
    lines += ["## Edges", "", *edges, ""]
    return write_text_atomic(run.out / "report.md", "\n".join(lines))


def rigid_plots(result, earlier, earlier_report: Path | None, cfg) -> dict[str, tuple[str, str]]:
    """Plots the region solve moved as one piece (each scan's pose relative to the plot's reference
    as register-plot left it, within the report's rigid tolerance): their distances are the earlier report's."""
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


ANCHOR_FIELDS = tuple(f.name for f in dataclasses.fields(AnchorRow))


def anchor_row(recorded: dict) -> AnchorRow:
    """An AnchorRow from the anchor's fields as tie-to-als records them (its poses.json form:
    the fit's figures flat beside the pair's)."""
    return AnchorRow(**{k: v for k, v in recorded.items() if k in ANCHOR_FIELDS and v is not None})


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
    """report.md and report.html of tie-to-als's result. `earlier` (register-plot's poses) and
    `earlier_report` (its report.html): a plot the region solve moved rigidly keeps that report's
    cloud-to-cloud distances (linked); its fit to the ALS and its slice are drawn here."""
    cfg = getattr(config, "report", None) or ReportConfig()
    graph_cfg = getattr(config, "graph", None) or PoseGraphConfig()
    poses = {k: v.transform for k, v in result.poses.scans.items()}
    run = TieRun(
        out=result.out,
        graph=result.graph,
        anchors=tuple(anchor_row({**vars(a), **(a.fit or {})}) for a in result.anchors),
        poses=poses,
        sigmas={k: v.sigma for k, v in result.poses.scans.items()},
        plots={p.id: [s.id for s in p.scans] for p in manifest.plots},
        paths={s.id: manifest.resolve(s.path) for s in manifest.scans},
        offset=np.asarray(result.offset, float),
        als_xyz=als_near(als.xyz, poses, cfg.als_margin),
        source=f"manifest: {manifest.source}",
        unplaced=tuple(result.unplaced),
        computed=result.computed,
        seconds=result.seconds,
        stages=tuple(tables.recorded(result)),
        judged_in=rigid_plots(result, earlier, earlier_report, cfg),
    )
    return render_tie(run, cfg, graph_cfg.sure_edge_confidence, seed, reader or read_scan)

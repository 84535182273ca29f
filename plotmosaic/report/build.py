"""report.html of registered scans (a pair, a register-plot run or a tie-to-als run).

Each scan is read once (report/collect.py). The page reads top-down: summary and warnings, the
pictures that decide (each with a line on how to read it), the tables, the time table last.
"""

from __future__ import annotations

import time
from pathlib import Path

from plotmosaic.config.report import ReportConfig
from plotmosaic.report import html as H
from plotmosaic.report.collect import collect, with_als_fit, with_distances
from plotmosaic.report.figures import origin_of
from plotmosaic.report.model import Figure, PlotView, ReportInput, Stage
from plotmosaic.report.plot_figures import plot_figures
from plotmosaic.report.sections import (
    add_stages,
    als_table,
    distance_tables,
    stage_table,
    stem_table,
    summary_lines,
)
from plotmosaic.report.view3d import write_3d_view
from plotmosaic.report.warnings import unsure_edges, warnings_for

__all__ = ["ReportInput", "Stage", "add_stages", "build_report", "collect"]

VIEW3D = "view3d.html"


def plot_views(inp: ReportInput, cfg: ReportConfig, seed: int) -> list[PlotView]:
    """Each plot's slice, stems, distances (unless measured in an earlier report) and ALS fit."""
    views_ = []
    for plot, scans in inp.plots.items():
        v = collect(plot, scans, inp.paths, inp.poses, inp.reader, cfg, seed)
        if plot not in inp.judged_in:
            v = with_distances(v, inp.graph, cfg, seed)
        views_.append(with_als_fit(v, inp.als_xyz, cfg))
    return views_


def build_report(
    inp: ReportInput, cfg: ReportConfig | None = None, seed: int = 0
) -> tuple[Path, list[Figure]]:
    """Compute the slice, stems, distances and ALS fit; draw; write out/report.html and the run's
    3D view. Returns the page and the figures drawn (the caller's first)."""
    cfg = cfg or ReportConfig()
    t0 = time.perf_counter()
    views_ = plot_views(inp, cfg, seed)
    unsure = unsure_edges(inp.graph, inp.min_confidence)
    warnings = warnings_for(inp.graph, views_, list(inp.unplaced), list(inp.failed), cfg, unsure)
    figs = list(inp.figures)
    for v in views_:
        figs += plot_figures(v, inp, cfg, unsure, seed)
    clouds = {s: p for v in views_ for s, p in v.thinned.items()}
    view3d = write_3d_view(inp.out / VIEW3D, clouds, inp.als_xyz, cfg, seed)
    stage = Stage(
        "report (this page)",
        time.perf_counter() - t0,
        "each scan's points once (its prepared cloud or its file), slice, distances, figures",
    )
    page = _write_page(inp, views_, figs, warnings, view3d, cfg, [*inp.stages, stage])
    return page, figs


def _summary(page: H.Page, inp: ReportInput, views_, warnings, cfg: ReportConfig) -> None:
    page.raw('<div class="summary">')
    page.heading("Summary")
    page.raw(H.bullets([*inp.facts, *summary_lines(inp, views_)]))
    page.heading("Warnings", 3)
    page.raw(
        H.bullets(warnings, "warn")
        if warnings
        else '<p class="ok">none: every scan is held by two or more edges, no edge was dropped, '
        "the stem rings at breast height agree (median spread under "
        f"{cfg.weak_ring_spread * 100:.0f} cm).</p>"
    )
    page.raw("</div>")


def _pictures(page: H.Page, inp: ReportInput, views_, figs: list[Figure], view3d) -> None:
    for f in figs:
        if f.plot == "":
            page.raw(H.image(f.png, f.caption, f.read))
    if view3d is not None:
        page.link(view3d.name, f"Interactive 3D view of the placed scans, thinned ({view3d.name})")
    else:
        page.paragraph(
            "No interactive 3D view (plotly is not installed, or the page would be too large)."
        )
    for v in views_:
        page.heading(f"Plot {v.plot}")
        if v.plot in inp.judged_in:
            href, why = inp.judged_in[v.plot]
            page.paragraph(
                f"{why}: its cloud-to-cloud distances are those of the report that placed its "
                "scans, moved with the plot:"
            )
            page.link(href, href)
        for f in figs:
            if f.plot == v.plot:
                page.raw(H.image(f.png, f.caption, f.read))


def _tables(page: H.Page, inp: ReportInput, views_) -> None:
    page.heading("Tables")
    for v in views_:
        if v.stems:
            page.raw(stem_table(v, origin_of(v.thinned)))
        for t in distance_tables(v) + als_table(v):
            page.raw(t)
    for caption, lines in inp.tables_md:
        page.raw(H.markdown_table(lines, caption))


def _write_page(inp, views_, figs, warnings, view3d, cfg, stages) -> Path:
    page = H.Page(inp.title)
    _summary(page, inp, views_, warnings, cfg)
    for heading, fragment in inp.blocks:
        page.heading(heading)
        page.raw(fragment)
    _pictures(page, inp, views_, figs, view3d)
    _tables(page, inp, views_)
    page.heading("Time")
    page.raw(stage_table(stages))
    return page.write(inp.out / "report.html")

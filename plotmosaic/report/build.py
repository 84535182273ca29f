"""report.html for registered scans (a pair, a register-plot run or a tie-to-als run).

Each scan is read once: moved by its pose, it leaves its cell minima (for the ground model), its low
stratum (points that can lie in the breast-height slice) and a thinned copy (for cloud-to-cloud
distances, the pictures and the 3D view). Summary and warnings first, then figures and tables.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.report import ReportConfig
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import apply_transform
from plotmosaic.report import html as H
from plotmosaic.report import views
from plotmosaic.report.distance import edge_distances, scan_medians, thin
from plotmosaic.report.figures import origin_of
from plotmosaic.report.pictures import plot_scans as scans_picture
from plotmosaic.report.slice import (
    Ground,
    Stem,
    breast_height_slice,
    cell_floor,
    find_stems,
    ground_model,
    low_stratum,
    merge_minima,
    ring_spread,
)


@dataclass
class Stage:
    name: str
    seconds: float | None
    note: str = ""


@dataclass
class PlotView:
    """What the report computes for one plot (a set of scans in one frame)."""

    plot: str
    scans: list[str]
    ground: Ground | None = None
    slices: dict[str, np.ndarray] = field(default_factory=dict)
    stems: list[Stem] = field(default_factory=list)
    thinned: dict[str, np.ndarray] = field(default_factory=dict)
    edges: list[dict] = field(default_factory=list)  # per kept edge: distances and their figures
    medians: dict[str, float] = field(default_factory=dict)

    @property
    def spread(self) -> float:
        return ring_spread(self.stems)


def collect(
    plot: str,
    scans: list[str],
    paths: dict[str, Path],
    poses: dict[str, np.ndarray],
    reader: Callable[[Path], np.ndarray],
    cfg: ReportConfig,
    seed: int,
) -> PlotView:
    """One read per placed scan; the slice, stems and thinned clouds of the plot."""
    view = PlotView(plot, scans)
    rng = np.random.default_rng(seed)
    minima = (np.zeros((0, 2), np.int64), np.zeros(0))
    low = {}
    for sid in scans:
        if sid not in poses or sid not in paths:
            continue
        xyz = apply_transform(poses[sid], reader(paths[sid]))
        floor = cell_floor(
            xyz, cfg.slice.dtm_cell
        )  # one cell pass: the ground model and the stratum
        minima = merge_minima(minima, floor[:2])
        low[sid] = thin(
            low_stratum(xyz, cfg.slice, floor), cfg.slice.stratum_voxel, len(xyz), rng
        )  # memory: area, not points
        del floor
        view.thinned[sid] = thin(xyz, cfg.distance.voxel, cfg.distance.max_points, rng)
        del xyz
    if not low:
        return view
    view.ground = ground_model(minima, cfg.slice.dtm_cell, cfg.slice.dtm_spike)
    view.slices = breast_height_slice(low, view.ground, cfg.slice)
    view.stems = find_stems(view.slices, cfg.slice)
    return view


def glance(plot: str, scans: list[str], inp: ReportInput, cfg: ReportConfig, seed: int) -> PlotView:
    """A plot judged in an earlier report: only a seeded sample of each scan, for the pictures."""
    view = PlotView(plot, scans)
    rng = np.random.default_rng(seed)
    for sid in scans:
        if sid in inp.poses and sid in inp.paths:
            xyz = inp.reader(inp.paths[sid])
            pick = np.sort(rng.choice(len(xyz), min(len(xyz), cfg.picture_points), replace=False))
            view.thinned[sid] = apply_transform(inp.poses[sid], xyz[pick])
    return view


def kept_edges(G: nx.Graph, scans: list[str]) -> list[tuple[str, str]]:
    return sorted(
        (e["source"], e["target"])
        for u, v, e in G.subgraph(scans).edges(data=True)
        if not e.get("dropped")
    )


def add_distances(view: PlotView, G: nx.Graph, cfg: ReportConfig) -> None:
    trees: dict = {}
    for s, t in kept_edges(G, view.scans):
        if s in view.thinned and t in view.thinned:
            view.edges.append(edge_distances(s, t, view.thinned, trees, cfg.distance))
    view.medians = scan_medians(view.edges)


def unsure_edges(G: nx.Graph, min_confidence: float) -> set[tuple[str, str]]:
    return {
        tuple(sorted((u, v)))
        for u, v, e in G.edges(data=True)
        if not e.get("dropped")
        and e.get("confidence") is not None
        and e["confidence"] < min_confidence
    }


def scan_position(T: np.ndarray, cloud: np.ndarray | None) -> np.ndarray:
    """The scanner: the file's origin moved by the pose, if inside the cloud's extent, else the cloud's centre."""
    p = T[:3, 3]
    if cloud is None or not len(cloud):
        return p
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    return (
        p
        if np.all(p[:2] >= lo[:2] - 5) and np.all(p[:2] <= hi[:2] + 5)
        else np.median(cloud, axis=0)
    )


REASONS = {
    "cycle": "its loops with the other edges do not close",
    "residual": "it disagrees with the joint solution of the others",
    "unverified": "the coarse stage was unsure and no loop confirms it",
}


def _length(metres: float) -> str:
    return f"{metres * 100:.0f} cm" if metres < 1 else f"{metres:.1f} m"


def _cm(metres: float) -> str:
    return "-" if not np.isfinite(metres) else f"{metres * 100:.2f}"


def warnings_for(
    G: nx.Graph,
    views_: list[PlotView],
    unplaced: list[str],
    failed: list[dict],
    cfg: ReportConfig,
    unsure: set,
) -> list[str]:
    """Plain-words warnings: weak links first, then what the slice and the distances say."""
    out = [f"scan {s} is not placed: no kept pair links it to the reference" for s in unplaced]
    K = nx.Graph([(u, v) for u, v, e in G.edges(data=True) if not e.get("dropped")])
    scans = [n for n in G.nodes if G.nodes[n].get("kind") != "als"]
    for n in sorted(scans) if len(scans) > 2 else []:  # a lone pair has one edge by definition
        if n in K and K.degree(n) == 1 and n not in unplaced:
            out.append(
                f"scan {n} is held by one edge only ({next(iter(K[n]))}): nothing checks that link"
            )
    for u, v, e in sorted(
        G.edges(data=True), key=lambda t: (t[2].get("source", t[0]), t[2].get("target", t[1]))
    ):
        if e.get("dropped"):
            r = e.get("residual_after")
            off = (
                f"; it is {_length(r['translation'])} / {r['rotation_deg']:.2f} deg off the solution"
                if r
                else ""
            )
            out.append(
                f"edge {e.get('source', u)}-{e.get('target', v)} dropped: "
                f"{REASONS.get(e.get('drop_reason'), e.get('drop_reason'))}{off}"
            )
        elif tuple(sorted((u, v))) in unsure:
            out.append(
                f"edge {e.get('source', u)}-{e.get('target', v)} was ambiguous (coarse confidence "
                f"{e['confidence']:.2f}); kept because a loop confirms it"
            )
    out += [
        f"pair {f['source']}-{f['target']} could not be registered: {f.get('error')}"
        for f in failed
    ]
    for v in views_:
        if np.isfinite(v.spread) and v.spread > cfg.weak_ring_spread:
            out.append(
                f"plot {v.plot}: stem rings at breast height are {v.spread * 100:.1f} cm apart (median): "
                "doubled stems, a scan is off"
            )
        for s, m in v.medians.items():
            if m > cfg.weak_distance:
                out.append(
                    f"scan {s}: median distance to its neighbours is {m * 100:.1f} cm after the joint solve"
                )
        if v.ground is not None and not v.stems:
            out.append(
                f"plot {v.plot}: no stem seen by two scans in the breast-height slice (too sparse, or no trees)"
            )
    return out


STAGES_MARK = "<!-- more stages -->"


def _stage_rows(stages: list[Stage]) -> list[list[object]]:
    return [
        [s.name, "not recorded" if s.seconds is None else f"{s.seconds:.1f}", s.note]
        for s in stages
    ]


def stage_table(stages: list[Stage]) -> str:
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
        worst = max((o for s, o in st.offsets.items()), default=0.0)
        rows.append(
            [
                k + 1,
                f"{c[0]:.2f}",
                f"{c[1]:.2f}",
                f"{st.radius * 200:.1f}",
                ", ".join(st.scans),
                f"{st.spread * 100:.2f}",
                f"{worst * 100:.2f}",
            ]
        )
    return H.table(
        [
            "stem",
            "x (m)",
            "y (m)",
            "DBH (cm)",
            "scans",
            "ring spread (cm)",
            "worst ring offset (cm)",
        ],
        rows,
        f"Plot {view.plot}: stems in the breast-height slice, those most scans see first",
    )


def write_3d_view(path: Path, views_: list[PlotView], cfg: ReportConfig, seed: int) -> Path | None:
    """plotly offline page of the thinned merged cloud, one colour per scan; None without plotly or over the cap."""
    try:
        import plotly.graph_objects as go
    except ImportError:
        return None

    rng = np.random.default_rng(seed)
    allp = [p for v in views_ for p in v.thinned.values()]
    if not allp or cfg.view3d_points == 0:
        return None
    origin = np.floor(np.min([p.min(axis=0) for p in allp], axis=0))
    colours = views.scan_colours([s for v in views_ for s in v.thinned])
    per_scan = max(100, min(cfg.view3d_points, cfg.view3d_total // len(allp)))
    fig = go.Figure()
    for v in views_:
        for s, p in v.thinned.items():
            q = p if len(p) <= per_scan else p[np.sort(rng.choice(len(p), per_scan, replace=False))]
            q = np.round(q - origin, 3)
            c = colours[s]
            fig.add_trace(
                go.Scatter3d(
                    x=q[:, 0],
                    y=q[:, 1],
                    z=q[:, 2],
                    mode="markers",
                    name=s,
                    marker={
                        "size": 1,
                        "color": f"rgb({c[0] * 255:.0f},{c[1] * 255:.0f},{c[2] * 255:.0f})",
                    },
                )
            )
    fig.update_layout(
        scene={"aspectmode": "data"},
        title=f"thinned merged cloud (origin {origin[0]:.0f}, {origin[1]:.0f}, {origin[2]:.0f})",
        margin={"l": 0, "r": 0, "t": 40, "b": 0},
    )
    text = fig.to_html(include_plotlyjs=True, full_html=True)
    if len(text) > cfg.view3d_max_mb * 1e6:
        return None
    return write_text_atomic(path, text)


@dataclass
class ReportInput:
    """Everything build_report needs, from whichever run made the poses."""

    title: str
    out: Path
    graph: nx.Graph
    poses: dict[str, np.ndarray]
    paths: dict[str, Path]
    plots: dict[str, list[str]]  # plot id -> scan ids
    reader: Callable[[Path], np.ndarray]
    stages: list[Stage] = field(default_factory=list)
    unplaced: list[str] = field(default_factory=list)
    failed: list[dict] = field(default_factory=list)
    facts: list[str] = field(default_factory=list)  # lines for the summary (manifest, frame, ...)
    tables_md: list[tuple[str, list[str]]] = field(
        default_factory=list
    )  # report.md tables to repeat
    figures: list[tuple[str, Path]] = field(
        default_factory=list
    )  # PNGs already drawn (report.md's)
    als_xyz: np.ndarray | None = None
    # plot id -> (link to the report that judged its scans, why): plots that moved rigidly since
    # (tie-to-als after register-plot), so their slice, stems and distances are that report's
    judged_in: dict[str, tuple[str, str]] = field(default_factory=dict)
    min_confidence: float = 0.25
    bundle: dict | None = None  # residual summary of the kept edges


def build_report(
    inp: ReportInput, cfg: ReportConfig | None = None, seed: int = 0, overview: bool = False
) -> tuple[Path, list[tuple[str, str, Path]]]:
    """Compute the slice, stems, distances; draw; write out/report.html.

    Returns its path and the figures drawn as (plot, caption, png); `overview` adds a top and side
    view of each plot's placed scans (from the thinned clouds: no second read).
    """
    cfg = cfg or ReportConfig()
    t0 = time.perf_counter()
    out, G = inp.out, inp.graph
    views_ = []
    for plot, scans in inp.plots.items():
        if plot in inp.judged_in:
            views_.append(glance(plot, scans, inp, cfg, seed))
            continue
        v = collect(plot, scans, inp.paths, inp.poses, inp.reader, cfg, seed)
        add_distances(v, G, cfg)
        views_.append(v)
    unsure = unsure_edges(G, inp.min_confidence)
    warnings = warnings_for(G, views_, inp.unplaced, inp.failed, cfg, unsure)
    figs: list[tuple[str, str, Path]] = []  # (plot, caption, png)
    for v in views_:
        if not v.thinned:
            continue
        origin = origin_of(v.thinned)
        colours = views.scan_colours(v.scans)
        if v.ground is not None:
            figs.append(
                (
                    v.plot,
                    (
                        f"Plot {v.plot}: breast-height slice ({cfg.slice.height:g} m +- {cfg.slice.half_width * 100:.0f} cm "
                        "above the ground from the scans), one colour per scan; right: stems most scans see, 1 cm grid"
                    ),
                    views.plot_breast_slice(
                        out / f"{v.plot}_breast_slice.png",
                        v.slices,
                        v.stems,
                        f"plot {v.plot}: breast-height slice",
                        origin,
                        cfg.slice.insets,
                        colours,
                    ),
                )
            )
        positions = {
            s: scan_position(inp.poses[s], v.thinned.get(s)) for s in v.scans if s in inp.poses
        }
        bg = (
            views.canopy_height(inp.als_xyz)
            if inp.als_xyz is not None
            else None
            if v.ground is None
            else views.hillshade_background(v.ground)
        )
        figs.append(
            (
                v.plot,
                f"Plot {v.plot}: map of scans and edges"
                + (f" over the {bg[2]}" if bg is not None else ""),
                views.plot_map(
                    out / f"{v.plot}_map.png",
                    G.subgraph(v.scans),
                    positions,
                    bg,
                    f"plot {v.plot}: scans and edges",
                    origin,
                    unsure,
                ),
            )
        )
        shown = sorted(v.edges, key=lambda e: -e["median"])[: cfg.distance.edge_figures]
        if shown:
            figs.append(
                (
                    v.plot,
                    (
                        f"Plot {v.plot}: cloud-to-cloud distances per kept edge (worst {len(shown)} of {len(v.edges)} "
                        "by median), histogram and map of the overlap"
                    ),
                    views.plot_edge_distances(
                        out / f"{v.plot}_distances.png", shown, origin, cfg.distance.colour_max
                    ),
                )
            )
            spreads = {s: ring_spread(v.stems, s) for s in v.medians}
            figs.append(
                (
                    v.plot,
                    f"Plot {v.plot}: per scan, median distance to its neighbours and ring spread of its stems",
                    views.plot_scan_distances(
                        out / f"{v.plot}_scan_distances.png", v.medians, spreads
                    ),
                )
            )
        if overview:  # the dense all-points view last: it cannot show centimetres
            rng = np.random.default_rng(seed)
            small = {
                s: p
                if len(p) <= cfg.picture_points
                else p[np.sort(rng.choice(len(p), cfg.picture_points, replace=False))]
                for s, p in v.thinned.items()
            }
            als = _als_under(inp.als_xyz, small) if v.ground is None else None
            if als is not None:  # the ALS the plot was placed on, in grey over the scans
                small = {**small, "ALS": als}
            figs.append(
                (
                    v.plot,
                    f"Plot {v.plot}: placed scans from above and from the side, one colour per scan"
                    + (
                        ", the ALS it was placed on drawn over them (grey)"
                        if als is not None
                        else ""
                    ),
                    scans_picture(
                        out / f"{v.plot}_scans.png", small, f"plot {v.plot}: placed scans", origin
                    ),
                )
            )
    view3d = write_3d_view(out / "view3d.html", views_, cfg, seed)
    inp.stages.append(
        Stage(
            "report (this page)",
            time.perf_counter() - t0,
            "each scan's points once (its prepared cloud or its file), slice, distances, figures",
        )
    )
    return _write_page(inp, views_, figs, warnings, view3d, cfg), figs


def _als_under(als_xyz: np.ndarray | None, clouds: dict[str, np.ndarray]) -> np.ndarray | None:
    """ALS points over the scans' extent (x, y), for the overview behind them."""
    if als_xyz is None or not clouds:
        return None
    xyz = np.vstack(list(clouds.values()))
    lo, hi = xyz[:, :2].min(axis=0), xyz[:, :2].max(axis=0)
    keep = np.all((als_xyz[:, :2] >= lo) & (als_xyz[:, :2] <= hi), axis=1)
    return als_xyz[keep] if keep.any() else None


def _write_page(
    inp: ReportInput,
    views_: list[PlotView],
    figs,
    warnings: list[str],
    view3d: Path | None,
    cfg: ReportConfig,
) -> Path:
    page = H.Page(inp.title)
    G = inp.graph
    scans = [s for ids in inp.plots.values() for s in ids]
    placed = [s for s in scans if s in inp.poses]
    n_kept = sum(1 for *_, e in G.edges(data=True) if not e.get("dropped"))
    kept = [
        (u, v, e)
        for u, v, e in G.edges(data=True)
        if not e.get("dropped") and e.get("residual_after")
    ]
    summary = [
        f"scans placed: {len(placed)} of {len(scans)}"
        + (f" (not placed: {', '.join(inp.unplaced)})" if inp.unplaced else "")
    ]
    summary.append(
        f"edges: {n_kept} kept, {sum(1 for *_, e in G.edges(data=True) if e.get('dropped'))} dropped, "
        f"{len(inp.failed)} pairs failed"
    )
    if kept:
        u, v, e = max(kept, key=lambda t: t[2]["residual_after"]["translation"])
        r = e["residual_after"]
        summary.append(
            f"worst edge: {e.get('source', u)}-{e.get('target', v)}, {r['translation'] * 100:.2f} cm / "
            f"{r['rotation_deg']:.3f} deg off the joint solution"
        )
    if inp.bundle and inp.bundle.get("edges"):
        b = inp.bundle
        summary.append(
            f"bundle error (kept edges after the joint solve): translation RMS {b['translation_rms'] * 100:.2f} cm, "
            f"rotation RMS {b['rotation_rms_deg']:.3f} deg"
        )
    for v in views_:
        if v.stems:
            summary.append(
                f"plot {v.plot}: {len(v.stems)} stems in the breast-height slice, median ring spread "
                f"{v.spread * 100:.2f} cm"
            )
        if v.edges:
            worst = max(v.edges, key=lambda e: e["median"])
            summary.append(
                f"plot {v.plot}: cloud-to-cloud median distance per edge {min(e['median'] for e in v.edges) * 100:.2f}"
                f"-{worst['median'] * 100:.2f} cm (worst {worst['source']}-{worst['target']})"
            )
    page.raw('<div class="summary">')
    page.heading("Summary")
    page.raw(H.bullets(inp.facts + summary))
    page.heading("Warnings", 3)
    page.raw(
        H.bullets(warnings, "warn")
        if warnings
        else '<p class="ok">none: every scan is held by two or more edges, '
        f"no edge was dropped, the stem rings at breast height agree (median spread under {cfg.weak_ring_spread * 100:.0f} cm).</p>"
    )
    page.raw("</div>")
    if view3d is not None:
        page.link(
            view3d.name,
            f"Interactive 3D view of the thinned merged cloud, coloured by scan ({view3d.name})",
        )
    else:
        page.paragraph(
            "No interactive 3D view (plotly is not installed, or the page would be too large)."
        )
    page.heading("Time")
    page.raw(stage_table(inp.stages))
    for v in views_:
        page.heading(f"Plot {v.plot}")
        if v.plot in inp.judged_in:
            href, why = inp.judged_in[v.plot]
            page.paragraph(
                f"{why}: its breast-height slice, stems and cloud-to-cloud distances are those of the "
                "report that placed its scans, moved with the plot:"
            )
            page.link(href, href)
        for plot, caption, png in figs:
            if plot == v.plot:
                page.raw(H.image(png, caption))
        if v.plot in inp.judged_in:
            continue
        origin = origin_of(v.thinned) if v.thinned else np.zeros(3)
        page.raw(stem_table(v, origin))
        rows = [
            [
                e["source"],
                e["target"],
                len(e["distances"]),
                f"{e['median'] * 100:.2f}",
                f"{e['p90'] * 100:.2f}",
                f"{e['share'] * 100:.0f}",
            ]
            for e in v.edges
        ]
        page.raw(
            H.table(
                [
                    "source",
                    "target",
                    "overlap points",
                    "median (cm)",
                    "90 % (cm)",
                    "share of source in overlap (%)",
                ],
                rows,
                f"Plot {v.plot}: cloud-to-cloud distances of the kept edges",
            )
        )
        page.raw(
            H.table(
                [
                    "scan",
                    "median distance to neighbours (cm)",
                    "median ring spread of its stems (cm)",
                ],
                [[s, _cm(m), _cm(ring_spread(v.stems, s))] for s, m in v.medians.items()],
                f"Plot {v.plot}: per scan after the joint solve",
            )
        )
    for caption, lines in inp.tables_md:
        page.heading(caption)
        page.raw(H.markdown_table(lines, caption))
    if inp.figures:
        page.heading("Overview pictures")
        for caption, png in inp.figures:
            page.raw(H.image(png, caption))
    return page.write(inp.out / "report.html")

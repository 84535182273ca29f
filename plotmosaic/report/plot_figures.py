"""Each plot's pictures, in the order that decides: the fit to the ALS (when there is one), the
breast-height slice, the map, the cloud-to-cloud distances, the overview. Each says how to read it."""

from __future__ import annotations

import numpy as np

from plotmosaic.config.report import ReportConfig
from plotmosaic.report import views
from plotmosaic.report.als_pictures import plot_canopy, plot_ground_difference, plot_scan_residuals
from plotmosaic.report.collect import als_under, sample, scan_position
from plotmosaic.report.figures import origin_of
from plotmosaic.report.model import Figure, PlotView, ReportInput
from plotmosaic.report.pictures import plot_scans
from plotmosaic.report.slice import ring_spread

# every per-plot picture a run's page may write, as <plot>_<name>.png (the commands' output plans)
PLOT_FIGURES = (
    "ground_vs_als",
    "canopy_vs_als",
    "scans_vs_als",
    "breast_slice",
    "map",
    "distances",
    "scan_distances",
    "scans",
)


def als_figures(v: PlotView, origin: np.ndarray, inp: ReportInput, cfg: ReportConfig) -> list:
    fit, out = v.als, inp.out
    if fit is None:
        return []
    figs = []
    if fit.ground.count:
        figs.append(
            Figure(
                plot=v.plot,
                caption=f"Plot {v.plot}: ground height of the placed scans minus the ALS ground",
                png=plot_ground_difference(
                    out / f"{v.plot}_ground_vs_als.png", fit, origin, cfg.als_fit.colour_max
                ),
                read="An even colour and a narrow histogram centred on 0 mean the plot sits at the "
                "ALS height; the median is the plot's vertical offset, a colour ramp across the "
                "map a tilt.",
            )
        )
    if fit.canopy.count:
        figs.append(
            Figure(
                plot=v.plot,
                caption=f"Plot {v.plot}: canopy top of the placed scans against the ALS canopy, "
                "where both see the top",
                png=plot_canopy(out / f"{v.plot}_canopy_vs_als.png", fit, origin),
                read="Points on the 1:1 line and a map without red/blue pairs on the crowns mean the "
                "crowns are where the ALS sees them (sparse ALS returns miss some apexes: a few "
                "decimetres above 0 is usual); a red/blue pair on one crown is a shift towards red.",
            )
        )
    if fit.scans:
        figs.append(
            Figure(
                plot=v.plot,
                caption=f"Plot {v.plot}: each scan's ground and canopy top against the ALS",
                png=plot_scan_residuals(out / f"{v.plot}_scans_vs_als.png", fit),
                read="Bars of one height mean the scans agree with each other; one scan's bar apart "
                "from the others is that scan off in height (ground) or place (canopy).",
            )
        )
    return figs


def slice_figure(v: PlotView, origin: np.ndarray, inp: ReportInput, cfg: ReportConfig) -> list:
    if v.ground is None:
        return []
    s = cfg.slice
    title, colours = f"plot {v.plot}: breast-height slice", views.scan_colours(list(v.scans))
    png = views.plot_breast_slice(
        inp.out / f"{v.plot}_breast_slice.png", v.slices, v.stems, title, origin, s.insets, colours
    )
    return [
        Figure(
            plot=v.plot,
            caption=f"Plot {v.plot}: breast-height slice ({s.height:g} m +- "
            f"{s.half_width * 100:.0f} cm above the ground from the scans), one colour per scan; "
            "right: stems most scans see, 1 cm grid",
            png=png,
            read="Each stem one ring means the scans agree; two rings side by side on a stem are a "
            "scan off by their distance.",
        )
    ]


def map_figure(v: PlotView, origin: np.ndarray, inp: ReportInput, unsure: set, background) -> list:
    positions = {  # the stations the view found, else the poses' origins
        s: v.stations[s] if s in v.stations else scan_position(inp.poses[s], v.thinned.get(s))
        for s in v.scans
        if s in inp.poses
    }
    title, sub = f"plot {v.plot}: scans and edges", inp.graph.subgraph(v.scans)
    png = views.plot_map(
        inp.out / f"{v.plot}_map.png", sub, positions, background, title, origin, unsure
    )
    over = f" over the {background[2]}" if background is not None else ""
    return [
        Figure(
            plot=v.plot,
            caption=f"Plot {v.plot}: map of scans and edges{over}",
            png=png,
            read="Every scan should be joined by two or more solid edges; red dashed edges were "
            "dropped, orange dotted ones were unsure.",
        )
    ]


def distance_figures(v: PlotView, origin: np.ndarray, inp: ReportInput, cfg: ReportConfig) -> list:
    shown = sorted(v.edges, key=lambda e: -e["median"])[: cfg.distance.edge_figures]
    if not shown:
        return []
    out = inp.out
    spreads = {s: ring_spread(v.stems, s) for s in v.medians}
    return [
        Figure(
            plot=v.plot,
            caption=f"Plot {v.plot}: cloud-to-cloud distances per kept edge (worst {len(shown)} of "
            f"{len(v.edges)} by median), histogram and map of the overlap",
            png=views.plot_edge_distances(
                out / f"{v.plot}_distances.png", shown, origin, cfg.distance.colour_max
            ),
            read="A median of a few millimetres and a map without a coloured side mean the two "
            "scans' surfaces coincide; a colour growing to one side is a tilt.",
        ),
        Figure(
            plot=v.plot,
            caption=f"Plot {v.plot}: per scan, median distance to its neighbours and ring spread "
            "of its stems",
            png=views.plot_scan_distances(out / f"{v.plot}_scan_distances.png", v.medians, spreads),
            read="One scan's bars above the others' point to that scan.",
        ),
    ]


def overview_figure(
    v: PlotView, origin: np.ndarray, inp: ReportInput, cfg: ReportConfig, seed: int
) -> list:
    small = sample(v.thinned, cfg.picture_points, seed)
    als = None if inp.als_xyz is None else als_under(inp.als_xyz, small)
    if als is not None and len(als):  # the ALS the plot was placed on, in grey behind the scans
        small = {"ALS": als, **small}
    return [
        Figure(
            plot=v.plot,
            caption=f"Plot {v.plot}: placed scans from above and from the side, one colour per scan"
            + (", the ALS around them in grey" if "ALS" in small else ""),
            png=plot_scans(
                inp.out / f"{v.plot}_scans.png", small, f"plot {v.plot}: placed scans", origin
            ),
            read="The dense view cannot show centimetres: it shows a scan far off or upside down.",
        )
    ]


def plot_figures(
    v: PlotView, inp: ReportInput, cfg: ReportConfig, unsure: set, seed: int
) -> list[Figure]:
    """The plot's pictures, those that decide first."""
    if not v.thinned:
        return []
    origin = origin_of(v.thinned)
    if inp.als_xyz is not None:
        background = views.canopy_height(inp.als_xyz)
    else:
        background = None if v.ground is None else views.hillshade_background(v.ground)
    figs = als_figures(v, origin, inp, cfg) + slice_figure(v, origin, inp, cfg)
    figs += map_figure(v, origin, inp, unsure, background)
    figs += distance_figures(v, origin, inp, cfg)
    if inp.overview:  # the dense all-points view last: it cannot show centimetres
        figs += overview_figure(v, origin, inp, cfg, seed)
    return figs

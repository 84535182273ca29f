"""Each placed scan read once: its cell minima (the ground model), its low stratum (points that can
lie in the breast-height slice) and a thinned copy (distances, pictures, the 3D view)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.report import ReportConfig
from plotmosaic.graph.prepared import points_reader
from plotmosaic.io.frame import apply_transform
from plotmosaic.report.als_fit import als_fit
from plotmosaic.report.distance import edge_distances, scan_medians, thin
from plotmosaic.report.model import PlotView
from plotmosaic.report.slice import (
    breast_height_slice,
    cell_floor,
    find_stems,
    ground_model,
    low_stratum,
    merge_minima,
)


def read_scan(path: Path) -> np.ndarray:
    """A scan's points from its file, within the default reading budget (runs pass a reader of
    their prepared clouds and their own budget instead)."""
    return points_reader({})(path)


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
    rng = np.random.default_rng(seed)
    minima = (np.zeros((0, 2), np.int64), np.zeros(0))
    low, thinned, per_scan, stations = {}, {}, {}, {}
    for sid in scans:
        if sid not in poses or sid not in paths:
            continue
        xyz = apply_transform(poses[sid], reader(paths[sid]))
        floor = cell_floor(xyz, cfg.slice.dtm_cell)  # one cell pass: ground model and stratum
        per_scan[sid] = floor[:2]
        minima = merge_minima(minima, floor[:2])
        # memory: the stratum kept grows with the area, not with the points
        low[sid] = thin(low_stratum(xyz, cfg.slice, floor), cfg.slice.stratum_voxel, len(xyz), rng)
        del floor
        thinned[sid] = thin(xyz, cfg.distance.voxel, cfg.distance.max_points, rng)
        stations[sid] = scan_position(poses[sid], thinned[sid])
        del xyz
    view = PlotView(
        plot=plot, scans=tuple(scans), thinned=thinned, scan_minima=per_scan, stations=stations
    )
    if not low:
        return view
    ground = ground_model(minima, cfg.slice.dtm_cell, cfg.slice.dtm_spike)
    slices = breast_height_slice(low, ground, cfg.slice)
    return dataclasses.replace(
        view, ground=ground, slices=slices, stems=find_stems(slices, cfg.slice)
    )


def kept_edges(G: nx.Graph, scans: list[str]) -> list[tuple[str, str]]:
    return sorted(
        (e["source"], e["target"])
        for u, v, e in G.subgraph(scans).edges(data=True)
        if not e.get("dropped")
    )


def with_distances(view: PlotView, G: nx.Graph, cfg: ReportConfig, seed: int) -> PlotView:
    """The view with the cloud-to-cloud distances of its kept edges."""
    trees: dict = {}
    rng = np.random.default_rng(seed)
    edges = [
        edge_distances(s, t, view.thinned, trees, cfg.distance, rng)
        for s, t in kept_edges(G, list(view.scans))
        if s in view.thinned and t in view.thinned
    ]
    return dataclasses.replace(view, edges=edges, medians=scan_medians(edges))


def with_als_fit(view: PlotView, als_xyz: np.ndarray | None, cfg: ReportConfig) -> PlotView:
    """The view with its fit to the ALS (when there is an ALS and a ground model)."""
    if als_xyz is None or view.ground is None:
        return view
    fit = als_fit(
        plot=view.plot,
        ground=view.ground,
        scan_minima=view.scan_minima,
        stations=view.stations,
        clouds=view.thinned,
        als_xyz=als_xyz,
        spike=cfg.slice.dtm_spike,
        cfg=cfg.als_fit,
    )
    return dataclasses.replace(view, als=fit)


def scan_position(T: np.ndarray, cloud: np.ndarray | None) -> np.ndarray:
    """The scanner: the file's origin moved by the pose, if inside the cloud's extent, else the cloud's centre."""
    p = T[:3, 3]
    if cloud is None or not len(cloud):
        return p
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    inside = np.all(p[:2] >= lo[:2] - 5) and np.all(p[:2] <= hi[:2] + 5)
    return p if inside else np.median(cloud, axis=0)


def als_under(
    als_xyz: np.ndarray, clouds: dict[str, np.ndarray], margin: float = 0.0
) -> np.ndarray:
    """ALS returns over the clouds' extent (x, y), widened by `margin`."""
    xy = np.vstack([p[:, :2] for p in clouds.values()])
    lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
    return als_xyz[np.all((als_xyz[:, :2] >= lo) & (als_xyz[:, :2] <= hi), axis=1)]


def sample(clouds: dict[str, np.ndarray], n: int, seed: int) -> dict[str, np.ndarray]:
    """At most n points of each cloud, a seeded random subset in the clouds' order."""
    rng = np.random.default_rng(seed)
    return {
        s: p if len(p) <= n else p[np.sort(rng.choice(len(p), n, replace=False))]
        for s, p in clouds.items()
    }

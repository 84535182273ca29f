"""Each placed scan read once: its cell minima (the ground model), its low stratum (points that can
lie in the breast-height slice) and a thinned copy (distances, pictures, the 3D view)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import networkx as nx
import numpy as np

from plotmosaic.config.report import ReportConfig
from plotmosaic.graph.prepared import points_reader
from plotmosaic.io.frame import apply_transform
from plotmosaic.parallel import in_two_threads
from plotmosaic.report.als_fit import als_fit
from plotmosaic.report.distance import edge_distances, scan_medians, target_index, thin
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


@dataclass(frozen=True, eq=False)
class _ScanPart:
    """What the page keeps of one placed scan."""

    minima: tuple[np.ndarray, np.ndarray]  # its DTM cells' keys and lowest z
    low: np.ndarray  # its low stratum, thinned
    thinned: np.ndarray
    station: np.ndarray


def _scan_part(
    path: Path,
    pose: np.ndarray,
    reader: Callable[[Path], np.ndarray],
    cfg: ReportConfig,
    rng: np.random.Generator,
) -> _ScanPart:
    xyz = apply_transform(pose, reader(path))
    floor = cell_floor(xyz, cfg.slice.dtm_cell)  # one cell pass: ground model and stratum
    # memory: the stratum kept grows with the area, not with the points
    low = thin(low_stratum(xyz, cfg.slice, floor), cfg.slice.stratum_voxel, len(xyz), rng)
    thinned = thin(xyz, cfg.distance.voxel, cfg.distance.max_points, rng)
    return _ScanPart(
        minima=floor[:2], low=low, thinned=thinned, station=scan_position(pose, thinned)
    )


def collect(
    plot: str,
    scans: list[str],
    paths: dict[str, Path],
    poses: dict[str, np.ndarray],
    reader: Callable[[Path], np.ndarray],
    cfg: ReportConfig,
    seed: int,
) -> PlotView:
    """One read per placed scan, two scans at a time (each seeded by its place in `scans`, so the
    page does not depend on the threads); the slice, stems and thinned clouds of the plot."""
    placed = [(k, sid) for k, sid in enumerate(scans) if sid in poses and sid in paths]

    def part(job: tuple[int, str]) -> _ScanPart:
        k, sid = job
        return _scan_part(paths[sid], poses[sid], reader, cfg, np.random.default_rng([seed, k]))

    parts = in_two_threads(part, placed)
    minima = (np.zeros((0, 2), np.int64), np.zeros(0))
    for part in parts:  # in the scans' order: the ground model does not depend on the threads
        minima = merge_minima(minima, part.minima)
    ids = [sid for _, sid in placed]
    view = PlotView(
        plot=plot,
        scans=tuple(scans),
        thinned={sid: p.thinned for sid, p in zip(ids, parts, strict=True)},
        scan_minima={sid: p.minima for sid, p in zip(ids, parts, strict=True)},
        stations={sid: p.station for sid, p in zip(ids, parts, strict=True)},
    )
    if not parts:
        return view
    low = {sid: p.low for sid, p in zip(ids, parts, strict=True)}
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
    """The view with the cloud-to-cloud distances of its kept edges: each target indexed once,
    edges two at a time, each seeded by its place among the kept edges."""
    edges = [
        (s, t)
        for s, t in kept_edges(G, list(view.scans))
        if s in view.thinned and t in view.thinned
    ]
    targets = sorted({t for _, t in edges})
    index = dict(
        zip(
            targets,
            in_two_threads(lambda t: target_index(view.thinned[t], cfg.distance), targets),
            strict=True,
        )
    )

    def measure(job: tuple[int, tuple[str, str]]) -> dict:
        k, (source, target) = job
        rng = np.random.default_rng([seed, k])
        return edge_distances(
            source, target, view.thinned[source], index[target], cfg.distance, rng
        )

    measured = in_two_threads(measure, list(enumerate(edges)))
    return dataclasses.replace(view, edges=measured, medians=scan_medians(measured))


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

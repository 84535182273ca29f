"""How a placed plot sits on the ALS: ground-height difference, canopy-top difference, per scan.

Pure computation (arrays in, one frozen `AlsFit` out); report/als_pictures.py draws it. The TLS
ground is the plot's own ground model (the lowest points of the merged placed scans per cell, as
the breast-height slice uses); the ALS ground is built the same way from the ALS returns. A
vertical offset of the plot shows as the median of their difference; NMAD (1.4826 x the median
absolute deviation) is its robust spread. The canopy comparison keeps cells where both see the
top: the ALS has canopy there and the TLS sampled its own highest metre densely (elsewhere the TLS
top is occlusion, not a misfit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.config.report import AlsFitConfig
from plotmosaic.report.slice import (
    GridExtent,
    Ground,
    cell_keys,
    cell_minima,
    flat_keys,
    ground_model,
    runs,
)

NMAD_SCALE = 1.4826  # NMAD = this x median absolute deviation: the std of a normal distribution


@dataclass(frozen=True, kw_only=True)
class Raster(GridExtent):
    """Values at cell centres of a regular grid (rows = y, columns = x); NaN where not compared."""

    x0: float
    y0: float
    cell: float
    z: np.ndarray


@dataclass(frozen=True, kw_only=True)
class Spread:
    """Median, NMAD and count of a set of differences (m); NaN without any."""

    median: float
    nmad: float
    count: int


def spread(values: np.ndarray) -> Spread:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if not len(v):
        return Spread(median=float("nan"), nmad=float("nan"), count=0)
    m = float(np.median(v))
    return Spread(median=m, nmad=NMAD_SCALE * float(np.median(np.abs(v - m))), count=len(v))


@dataclass(frozen=True, kw_only=True)
class ScanFit:
    """One scan against the ALS: its ground and its canopy top minus the ALS's (m)."""

    scan: str
    ground: Spread
    canopy: Spread


@dataclass(frozen=True, kw_only=True)
class AlsFit:
    """One plot against the ALS."""

    plot: str
    ground_diff: Raster  # TLS ground - ALS ground (m), where both saw the ground
    ground: Spread
    ground_values: np.ndarray  # the compared cells' differences, for the histogram
    tls_top: Raster  # TLS canopy top above the ALS ground (m), where both see the top
    als_top: Raster  # ALS canopy top above the ALS ground (m), same cells
    canopy: Spread  # TLS top - ALS top (m)
    scans: tuple[ScanFit, ...]


def _centres(ground: Ground) -> np.ndarray:
    rows, cols = np.indices(ground.z.shape)
    return np.column_stack(
        [
            ground.x0 + (cols.ravel() + 0.5) * ground.cell,
            ground.y0 + (rows.ravel() + 0.5) * ground.cell,
        ]
    )


def _seen_at(ground: Ground, xy: np.ndarray) -> np.ndarray:
    """Whether the cell under each (x, y) held points of the cloud the model was built from."""
    col = np.floor((xy[:, 0] - ground.x0) / ground.cell).astype(np.int64)
    row = np.floor((xy[:, 1] - ground.y0) / ground.cell).astype(np.int64)
    inside = (row >= 0) & (col >= 0) & (row < ground.z.shape[0]) & (col < ground.z.shape[1])
    out = np.zeros(len(xy), bool)
    seen = ground.seen if ground.seen is not None else np.ones(ground.z.shape, bool)
    out[inside] = seen[row[inside], col[inside]]
    return out


def _tops(xyz: np.ndarray, cell: float, band: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(cells (n, 2), highest z per cell, points within `band` below that top per cell)."""
    if not len(xyz):
        return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0, np.int64)
    keys = cell_keys(xyz, cell)
    order, starts, inverse = runs(flat_keys(keys))
    cells = keys[order[starts]]
    top = np.maximum.reduceat(xyz[:, 2][order], starts)
    near = np.bincount(inverse, xyz[:, 2] >= top[inverse] - band, minlength=len(cells))
    return cells, top, near.astype(np.int64)


def _lookup(cells: np.ndarray, values: np.ndarray, want: np.ndarray) -> np.ndarray:
    """values at the `want` cells (NaN where `cells` has none)."""
    out = np.full(len(want), np.nan)
    if not len(cells) or not len(want):
        return out
    lo = np.minimum(cells.min(axis=0), want.min(axis=0))
    span = np.maximum(cells.max(axis=0), want.max(axis=0)) - lo + 1
    flat = (cells[:, 1] - lo[1]) * span[0] + (cells[:, 0] - lo[0])
    order = np.argsort(flat)
    wflat = (want[:, 1] - lo[1]) * span[0] + (want[:, 0] - lo[0])
    pos = np.clip(np.searchsorted(flat[order], wflat), 0, len(flat) - 1)
    hit = flat[order][pos] == wflat
    out[hit] = values[order][pos[hit]]
    return out


def _near(xy: np.ndarray, stations: np.ndarray, reach: float) -> np.ndarray:
    """Whether each (x, y) lies within `reach` of a scanner: farther, a TLS scan's lowest point in a
    cell is mostly understorey seen over the ground, not the ground."""
    if not len(stations):
        return np.zeros(len(xy), bool)
    d, _ = cKDTree(stations[:, :2]).query(xy, k=1)
    return d <= reach


def _ground_difference(
    tls: Ground, als: Ground, stations: np.ndarray, reach: float
) -> tuple[Raster, np.ndarray]:
    xy = _centres(tls)
    seen = tls.seen.ravel() if tls.seen is not None else np.ones(len(xy), bool)
    both = seen & _seen_at(als, xy) & _near(xy, stations, reach)
    diff = np.where(both, tls.z.ravel() - als.at(xy), np.nan)
    raster = Raster(x0=tls.x0, y0=tls.y0, cell=tls.cell, z=diff.reshape(tls.z.shape))
    return raster, diff[both]


def _scan_ground(
    minima: tuple[np.ndarray, np.ndarray],
    tls: Ground,
    als: Ground,
    spike: float,
    station: np.ndarray,
    reach: float,
) -> Spread:
    """A scan's lowest point per cell minus the ALS ground, on cells where that point is ground
    (within `spike` of the plot's ground model) and the ALS saw the ground too."""
    cells, zmin = minima
    if not len(cells):
        return spread(np.zeros(0))
    xy = (cells + 0.5) * tls.cell
    ok = (zmin <= tls.at(xy) + spike) & _seen_at(als, xy) & _near(xy, station[None, :2], reach)
    return spread(zmin[ok] - als.at(xy[ok]))


def _canopy(
    clouds: dict[str, np.ndarray], als_xyz: np.ndarray, als_ground: Ground, cfg: AlsFitConfig
) -> tuple[Raster, Raster, dict[str, np.ndarray]]:
    """TLS and ALS canopy tops (above the ALS ground) on the cells where both see the top, and each
    scan's top minus the ALS top on the cells where that scan sees the plot's top."""
    a_cells, a_top, _ = _tops(als_xyz, cfg.canopy_cell, cfg.top_band)
    empty = Raster(x0=0.0, y0=0.0, cell=cfg.canopy_cell, z=np.full((1, 1), np.nan))
    if not clouds or not len(a_cells):
        return empty, empty, {}
    merged = np.vstack(list(clouds.values()))
    t_cells, t_top, t_near = _tops(merged, cfg.canopy_cell, cfg.top_band)
    xy = (t_cells + 0.5) * cfg.canopy_cell
    ground = als_ground.at(xy)
    als_top = _lookup(a_cells, a_top, t_cells)
    both = (
        (t_near >= cfg.top_points)
        & (als_top - ground >= cfg.canopy_min_height)
        & (t_top - ground >= cfg.canopy_min_height)
    )
    lo = t_cells.min(axis=0)
    shape = tuple(t_cells.max(axis=0) - lo + 1)[::-1]
    x0, y0 = lo * cfg.canopy_cell
    grids = []
    for top in (t_top, als_top):
        z = np.full(shape, np.nan)
        z[t_cells[both, 1] - lo[1], t_cells[both, 0] - lo[0]] = (top - ground)[both]
        grids.append(Raster(x0=x0, y0=y0, cell=cfg.canopy_cell, z=z))
    per_scan = {}
    for name, xyz in clouds.items():
        s_cells, s_top, s_near = _tops(xyz, cfg.canopy_cell, cfg.top_band)
        a = _lookup(a_cells, a_top, s_cells)
        g = als_ground.at((s_cells + 0.5) * cfg.canopy_cell)
        # the scan sees the top where its top is the plot's (within the band): elsewhere the
        # other scans see higher and this one's top is occlusion
        plot_top = _lookup(t_cells, t_top, s_cells)
        ok = (
            (s_near >= cfg.top_points)
            & (s_top >= plot_top - cfg.top_band)
            & (a - g >= cfg.canopy_min_height)
            & (s_top - g >= cfg.canopy_min_height)
        )
        per_scan[name] = (s_top - a)[ok]
    return grids[0], grids[1], per_scan


def als_fit(
    *,
    plot: str,
    ground: Ground,
    scan_minima: dict[str, tuple[np.ndarray, np.ndarray]],
    stations: dict[str, np.ndarray],
    clouds: dict[str, np.ndarray],
    als_xyz: np.ndarray,
    spike: float,
    cfg: AlsFitConfig,
) -> AlsFit | None:
    """The plot's fit to the ALS. `ground`: the plot's TLS ground model; `scan_minima`: each scan's
    lowest point per ground cell (integer cells of `ground.cell`); `stations`: each scanner's
    position; `clouds`: the placed (thinned)
    scans; `als_xyz`: ALS returns around the plot. None when the ALS has no points over the plot."""
    x0, x1, y0, y1 = ground.extent
    m = cfg.margin
    near = (
        (als_xyz[:, 0] >= x0 - m)
        & (als_xyz[:, 0] <= x1 + m)
        & (als_xyz[:, 1] >= y0 - m)
        & (als_xyz[:, 1] <= y1 + m)
    )
    als_xyz = als_xyz[near]
    if len(als_xyz) < cfg.min_als_points:
        return None
    als_ground = ground_model(cell_minima(als_xyz, ground.cell), ground.cell, spike)
    reach = cfg.ground_reach
    at = np.array([stations[s] for s in scan_minima]).reshape(-1, 3)
    diff, values = _ground_difference(ground, als_ground, at, reach)
    tls_top, als_top, canopy_scans = _canopy(clouds, als_xyz, als_ground, cfg)
    canopy = spread(tls_top.z - als_top.z)
    scans = tuple(
        ScanFit(
            scan=s,
            ground=_scan_ground(scan_minima[s], ground, als_ground, spike, stations[s], reach),
            canopy=spread(canopy_scans.get(s, np.zeros(0))),
        )
        for s in scan_minima
    )
    return AlsFit(
        plot=plot,
        ground_diff=diff,
        ground=spread(values),
        ground_values=values,
        tls_top=tls_top,
        als_top=als_top,
        canopy=canopy,
        scans=scans,
    )

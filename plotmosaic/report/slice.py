"""Breast-height slice of registered scans: ground model, slice points, stems and their ring spread.

Misregistration shows as doubled stem rings in a thin horizontal slice 1.3 m above the ground; the
ring spread (RMS distance of every scan's slice points to one circle fitted to all of them) turns
that into a number per stem. The ground comes from the registered scans themselves: the lowest point
per 1 m cell, spikes (cells that only saw a stem base or log) replaced, holes filled, bilinear.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from plotmosaic.align.voxel import groups
from plotmosaic.config.report import SliceConfig

# ---------------------------------------------------------------- ground


def flat_keys(ij: np.ndarray) -> np.ndarray:
    """One int64 per integer cell row (any number of columns): np.unique on it is far faster than axis=0."""
    key = np.zeros(len(ij), np.int64)
    # column by column: axis-0 reductions over (N, k) are several times slower
    for k in range(ij.shape[1]):
        col = ij[:, k] - ij[:, k].min() if len(ij) else ij[:, k]
        key *= int(col.max()) + 1 if len(col) else 1
        key += col
    return key


def cell_keys(xy: np.ndarray, cell: float) -> np.ndarray:
    """(N, 2) integer cells of side `cell` under the points (floor of x / cell, y / cell)."""
    out = np.empty((len(xy), 2), np.int64)
    for k in range(2):
        out[:, k] = np.floor(xy[:, k] / cell)
    return out


def runs(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(order, run starts, inverse) of flat keys: np.unique(return_index, return_inverse) by one plain sort."""
    order, starts = groups(flat)
    inverse = np.empty(len(flat), np.int64)
    run = np.zeros(len(flat), np.int64)
    run[starts[1:]] = 1
    inverse[order] = np.cumsum(run)
    return order, starts, inverse


def cell_floor(xyz: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(unique integer cells (n, 2) in flat-key order, lowest z per cell, each point's cell index)."""
    keys = cell_keys(xyz, cell)
    if not len(keys):
        return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0, np.int64)
    order, starts, inverse = runs(flat_keys(keys))
    zmin = np.minimum.reduceat(xyz[:, 2][order], starts)
    return keys[order[starts]], zmin, inverse


def cell_minima(xyz: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """(unique integer cells (n, 2), lowest z per cell) of the points."""
    cells, zmin, _ = cell_floor(xyz, cell)
    return cells, zmin


def merge_minima(
    a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Cell minima of the union of two point sets from each set's cell minima."""
    keys, z = np.vstack([a[0], b[0]]), np.concatenate([a[1], b[1]])
    if not len(keys):
        return keys, z
    order, starts, _ = runs(flat_keys(keys))
    return keys[order[starts]], np.minimum.reduceat(z[order], starts)


class GridExtent:
    """The (left, right, bottom, top) of a grid with x0, y0, cell and z (rows = y), for imshow."""

    @property
    def extent(self) -> tuple[float, float, float, float]:
        return (
            self.x0,
            self.x0 + self.z.shape[1] * self.cell,
            self.y0,
            self.y0 + self.z.shape[0] * self.cell,
        )


@dataclass(frozen=True)
class Ground(GridExtent):
    """A coarse DTM: z at cell centres of a regular grid (rows = y, columns = x)."""

    x0: float
    y0: float
    cell: float
    z: np.ndarray
    seen: np.ndarray | None = None  # cells that held points (the rest is filled from neighbours)

    def at(self, xy: np.ndarray) -> np.ndarray:
        """Bilinear ground height under each (x, y); outside the grid the edge value."""
        col = (xy[:, 0] - self.x0) / self.cell - 0.5
        row = (xy[:, 1] - self.y0) / self.cell - 0.5
        return ndimage.map_coordinates(self.z, [row, col], order=1, mode="nearest")

    def hillshade(self, azimuth: float = 315.0, altitude: float = 45.0) -> np.ndarray:
        """Shaded relief in [0, 1] (sun from the north-west), for a map background."""
        gy, gx = np.gradient(self.z, self.cell)
        slope = np.arctan(np.hypot(gx, gy))
        aspect = np.arctan2(-gx, gy)
        az, alt = np.radians(azimuth), np.radians(altitude)
        shade = np.clip(
            np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect), 0, 1
        )
        return shade if self.seen is None else np.where(self.seen, shade, np.nan)


def ground_model(
    minima: tuple[np.ndarray, np.ndarray], cell: float, spike: float, opening: int = 5
) -> Ground:
    """DTM from cell minima: cells above a grey opening replaced by it, empty cells from the nearest cell."""
    keys, zmin = minima
    if not len(keys):
        raise ValueError("no points to build a ground model from")
    lo = keys.min(axis=0)
    shape = tuple((keys.max(axis=0) - lo + 1)[::-1])
    grid = np.full(shape, np.nan)
    grid[keys[:, 1] - lo[1], keys[:, 0] - lo[0]] = zmin
    empty = np.isnan(grid)
    filled = _fill_nearest(grid)
    # a grey opening keeps ramps (terrain) and removes bumps narrower than the window: cells whose
    # lowest point is a stem base, a log or foliage where the scans saw no ground
    opened = ndimage.grey_opening(filled, size=(opening, opening), mode="nearest")
    grid = np.where(empty | (filled > opened + spike), opened, filled)
    grid = ndimage.median_filter(grid, size=3, mode="nearest") if min(shape) >= 3 else grid
    return Ground(float(lo[0] * cell), float(lo[1] * cell), cell, grid, ~empty)


def _fill_nearest(grid: np.ndarray) -> np.ndarray:
    empty = np.isnan(grid)
    if not empty.any():
        return grid
    idx = ndimage.distance_transform_edt(empty, return_distances=False, return_indices=True)
    return grid[tuple(idx)]


def low_stratum(
    xyz: np.ndarray,
    cfg: SliceConfig,
    floor: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Points of one scan that can lie in the slice, whatever the other scans say about the ground.

    A slice point is at most height + half_width above the plot's ground, which is at or below this
    scan's own lowest point in the cell; points just above that minimum are this scan's ground.
    `floor`: `cell_floor(xyz, cfg.dtm_cell)` when the caller has it already.
    """
    if not len(xyz):
        return xyz
    _, zmin, inverse = floor if floor is not None else cell_floor(xyz, cfg.dtm_cell)
    dz = xyz[:, 2] - zmin[inverse]
    return xyz[(dz >= cfg.keep_low) & (dz <= cfg.keep_high)]


def breast_height_slice(
    clouds: dict[str, np.ndarray], ground: Ground, cfg: SliceConfig
) -> dict[str, np.ndarray]:
    """Each scan's points within half_width of `height` above the ground."""
    out = {}
    for name, xyz in clouds.items():
        h = xyz[:, 2] - ground.at(xyz[:, :2])
        out[name] = xyz[np.abs(h - cfg.height) <= cfg.half_width]
    return out


# ---------------------------------------------------------------- stems


def _solve3(M: np.ndarray, b: np.ndarray) -> np.ndarray:
    """3x3 normal equations by Cramer's rule (a general solver's call overhead is most of a small
    fit's time); least squares when singular (collinear points)."""
    (a, b_, c), (d, e, f), (g, h, i) = M.tolist()
    det = a * (e * i - f * h) - b_ * (d * i - f * g) + c * (d * h - e * g)
    scale = max(abs(a), abs(e), abs(i), 1e-300)
    if abs(det) <= 1e-12 * scale**3:
        return np.linalg.lstsq(M, b, rcond=None)[0]
    inv = np.array(
        [
            [e * i - f * h, c * h - b_ * i, b_ * f - c * e],
            [f * g - d * i, a * i - c * g, c * d - a * f],
            [d * h - e * g, b_ * g - a * h, a * e - b_ * d],
        ]
    )
    return inv @ b / det


def fit_circle(xy: np.ndarray, iterations: int = 10) -> tuple[np.ndarray, float, float]:
    """(centre, radius, RMS residual) of a circle: algebraic (Kasa) start, then geometric Gauss-Newton.

    Both solved through their 3x3 normal equations (sums over the points): the thousands of small
    fits of a report cost a fraction of a general least-squares call each."""
    mean = xy.mean(axis=0)
    p = xy - mean
    x, y = p[:, 0], p[:, 1]
    n = float(len(p))
    sq = x * x + y * y
    sxx, sxy, syy, sx, sy = x @ x, x @ y, y @ y, x.sum(), y.sum()
    M = np.array([[sxx, sxy, sx], [sxy, syy, sy], [sx, sy, n]])
    sol = _solve3(M, np.array([x @ sq, y @ sq, sq.sum()]))
    c = sol[:2] / 2
    r = float(np.sqrt(max(sol[2] + c @ c, 1e-12)))
    # the algebraic fit is biased on a half arc; the geometric one is not
    for _ in range(iterations):
        dx, dy = x - c[0], y - c[1]
        dist = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-12)
        ux, uy, f = dx / dist, dy / dist, dist - r
        sux, suy = ux.sum(), uy.sum()
        M = np.array([[ux @ ux, ux @ uy, sux], [ux @ uy, uy @ uy, suy], [sux, suy, n]])
        step = _solve3(M, np.array([ux @ f, uy @ f, f.sum()]))  # J = -[ux, uy, 1]: J'J s = -J'f
        c, r = c + step[:2], r + float(step[2])
        if np.abs(step).max() < 1e-7:
            break
    res = np.sqrt(((p - c) ** 2).sum(axis=1)) - r
    return c + mean, abs(r), float(np.sqrt(np.mean(res**2)))


@dataclass(frozen=True)
class Stem:
    """One stem found in the slice: the joint circle and what each scan saw of it."""

    centre: np.ndarray
    radius: float
    spread: float  # ring spread (m): RMS offset of the other scans' rings from the best-seen scan's ring
    # scan -> its (n, 2) slice points here
    points: dict[str, np.ndarray] = field(default_factory=dict)
    # scan -> own circle fit
    arcs: dict[str, tuple[np.ndarray, float, float]] = field(default_factory=dict)
    # scan -> offset of its ring from the best-seen scan's (m)
    offsets: dict[str, float] = field(default_factory=dict)

    @property
    def scans(self) -> list[str]:
        return sorted(self.arcs)


def _own_arc(xy: np.ndarray, cfg: SliceConfig) -> np.ndarray:
    """A scan's points on its own arc: twigs or a neighbour's bark in the cluster are left out.

    Uses only this scan's points, so whatever the registration, a doubled ring is kept whole.
    """
    if len(xy) < cfg.stem_min_points:
        return xy
    for _ in range(2):
        c, r, rmse = fit_circle(xy)
        keep = np.abs(np.linalg.norm(xy - c, axis=1) - r) <= max(3 * rmse, 2 * cfg.stem_arc_rmse)
        if keep.all() or keep.sum() < cfg.stem_min_points:
            break
        xy = xy[keep]
    return xy


def find_stems(slices: dict[str, np.ndarray], cfg: SliceConfig) -> list[Stem]:
    """Stems as small dense clusters of the slice where at least two scans each see an arc of a circle.

    Sorted by how many scans see the stem, then by points. A cluster counts as a stem when its best
    seen arc fits a circle of a stem's radius closely (a bush does not); the joint fit over all scans
    is never used to select, so a doubled ring stays in.
    """
    names = [n for n in slices if len(slices[n])]
    if not names:
        return []
    xy = np.vstack([slices[n][:, :2] for n in names])
    owner = np.concatenate([np.full(len(slices[n]), k) for k, n in enumerate(names)])
    lo = xy.min(axis=0)
    ij = np.floor((xy - lo) / cfg.stem_cell).astype(np.int64)
    occ = np.zeros(tuple(ij.max(axis=0) + 1), bool)
    occ[ij[:, 0], ij[:, 1]] = True
    labels, n_lab = ndimage.label(occ, structure=np.ones((3, 3)))
    lab = labels[ij[:, 0], ij[:, 1]]
    order = np.argsort(lab, kind="stable")
    bounds = np.searchsorted(lab[order], np.arange(1, n_lab + 2))
    max_extent = 2 * cfg.stem_max_radius + 2 * cfg.stem_cell
    stems = []
    for k in range(n_lab):
        idx = order[bounds[k] : bounds[k + 1]]
        if len(idx) < 2 * cfg.stem_min_points or np.ptp(xy[idx], axis=0).max() > max_extent:
            continue
        per = {names[s]: xy[idx[owner[idx] == s]] for s in np.unique(owner[idx])}
        per = {n: _own_arc(p, cfg) for n, p in per.items()}
        arcs = {n: fit_circle(p) for n, p in per.items() if len(p) >= cfg.stem_min_points}
        if len(arcs) < 2:
            continue
        best = max(arcs, key=lambda n: len(per[n]))
        _, r_best, rmse_best = arcs[best]
        if not (
            cfg.stem_min_radius <= r_best <= cfg.stem_max_radius and rmse_best <= cfg.stem_arc_rmse
        ):
            continue
        centre, radius, _ = fit_circle(np.vstack([per[n] for n in arcs]))
        seen = sorted(arcs, key=lambda n: (-len(per[n]), n))
        d = ring_offsets({n: per[n] for n in seen}, seen, (centre, radius))
        offsets = {n: float(np.linalg.norm(v)) for n, v in d.items()}
        spread = float(np.sqrt(np.mean([o**2 for n, o in offsets.items() if n != seen[0]])))
        stems.append(Stem(centre, radius, spread, per, arcs, offsets))
    stems.sort(key=lambda s: (-len(s.arcs), -sum(len(p) for p in s.points.values())))
    return stems


def ring_offsets(
    per: dict[str, np.ndarray],
    names: list[str],
    start: tuple[np.ndarray, float],
    damping: float = 1.0,
    iterations: int = 15,
) -> dict[str, np.ndarray]:
    """Offset (m) of each scan's ring from the first scan's: one radius, one centre per scan.

    Gauss-Newton on |p - c - d_s| - r with d_first = 0. A scan sees only its side of a stem, so an
    offset along its own arc is barely determined; the damping keeps such a direction at zero
    rather than inventing a shift.
    """
    mean = per[names[0]].mean(axis=0)
    pts = [per[n] - mean for n in names]
    c, r = start[0] - mean, start[1]
    d = np.zeros((len(names), 2))
    m = 3 + 2 * (len(names) - 1)
    for _ in range(iterations):
        rows, res = [], []
        for k, p in enumerate(pts):
            v = p - c - d[k]
            dist = np.maximum(np.linalg.norm(v, axis=1), 1e-12)
            J = np.zeros((len(p), m))
            J[:, :2] = -v / dist[:, None]
            J[:, 2] = -1.0
            if k:
                J[:, 3 + 2 * (k - 1) : 5 + 2 * (k - 1)] = -v / dist[:, None]
            rows.append(J)
            res.append(dist - r)
        damp = np.zeros((m - 3, m))
        damp[:, 3:] = np.sqrt(damping) * np.eye(m - 3)
        J = np.vstack(rows + [damp])
        f = np.concatenate(res + [np.sqrt(damping) * d[1:].ravel()])
        step, *_ = np.linalg.lstsq(J, -f, rcond=None)
        c, r = c + step[:2], r + float(step[2])
        d[1:] += step[3:].reshape(-1, 2)
        if np.abs(step).max() < 1e-7:
            break
    return {n: d[k] for k, n in enumerate(names)}


def ring_spread(stems: list[Stem], scan: str | None = None) -> float:
    """Median ring spread over the stems (those `scan` sees, if given); NaN without stems."""
    vals = [s.spread for s in stems if scan is None or scan in s.arcs]
    return float(np.median(vals)) if vals else float("nan")

"""A cloud's sensor kind (tls / mls / uls / als) from its points, when the user gives none.

Airborne clouds are seen from above: every cell of their footprint gets returns, the density is even
(a scan line, not a station), and a canopy hides the understorey from them. Among them, uls is dense
and als sparse. A ground-based cloud is tls when it sees the ground densely (tripod stations, one or
merged) and mls when little ground comes back (a mobile scanner's narrow vertical field grazes it).
Thresholds: config/kinds.py; figures measured on every input: benchmarks/results/kinds.md.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from plotmosaic.align.sampling import sample
from plotmosaic.align.viewpoint import crowding
from plotmosaic.config.align import ViewpointConfig
from plotmosaic.config.kinds import KindConfig
from plotmosaic.io.frame import column_bounds

DEFAULT_KIND = "tls"  # what a cloud too small or too thin to tell is registered as


@dataclass(frozen=True, kw_only=True)
class KindEvidence:
    """The figures a kind is decided on (NaN: not measured, the cloud was too small to tell)."""

    points: int
    extent_m: float  # the wider horizontal side of the cloud
    density_per_m2: float  # points per occupied cell area
    coverage: float  # occupied share of the cells within each row's extent
    dense_share: float  # share of the points in the densest 5 % of cells
    understorey_share: float  # points in the understorey band of columns with a canopy (NaN: none)
    ground_share: float  # points within the ground band of their column's lowest point
    crowding: float  # density near the file origin over the cloud's (align/viewpoint.py)
    station: bool  # crowding enough for one scan taken at the origin


@dataclass(frozen=True, kw_only=True)
class KindDetection:
    kind: str
    reason: str  # one line: the figures that decided, against their thresholds
    evidence: KindEvidence

    def to_dict(self) -> dict:
        """JSON form (PairResult.detected_kinds): a figure not measured is null."""
        figures = {
            k: None if isinstance(v, float) and np.isnan(v) else v
            for k, v in asdict(self.evidence).items()
        }
        return {"kind": self.kind, "reason": self.reason, "evidence": figures}


def occupied_cells(xy: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Occupied cells (K, 2) as integer indices in lexicographic order, each point's cell (N,),
    points per cell (K,)."""
    idx = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64)
    # one key per cell, i * stride + j with 0 <= j < stride: sorting the keys sorts the (i, j) rows
    # lexicographically, and a 1-D unique is several times cheaper than one over rows
    stride = int(idx[:, 1].max()) + 1 if len(idx) else 1
    keys, inverse, counts = np.unique(
        idx[:, 0] * stride + idx[:, 1], return_inverse=True, return_counts=True
    )
    return np.column_stack([keys // stride, keys % stride]), inverse.ravel(), counts


def row_coverage(cells: np.ndarray) -> float:
    """Occupied cells over the cells between each row's first and last occupied one."""
    order = np.lexsort((cells[:, 0], cells[:, 1]))
    rows, start = np.unique(cells[order, 1], return_index=True)
    x = cells[order, 0]
    first = np.minimum.reduceat(x, start)
    last = np.maximum.reduceat(x, start)
    return float(len(cells) / np.sum(last - first + 1)) if len(rows) else 0.0


def dense_share(counts: np.ndarray) -> float:
    """Share of the points in the densest 5 % of the occupied cells (at least one cell)."""
    top = np.sort(counts)[::-1][: max(1, len(counts) // 20)]
    return float(top.sum() / counts.sum())


def column_shares(
    z: np.ndarray, inverse: np.ndarray, n_cells: int, config: KindConfig
) -> tuple[float, float]:
    """(understorey share under a canopy, ground share): heights above each column's lowest point."""
    low = np.full(n_cells, np.inf)
    high = np.full(n_cells, -np.inf)
    np.minimum.at(low, inverse, z)
    np.maximum.at(high, inverse, z)
    h = z - low[inverse]
    canopy = (high - low)[inverse] > config.min_canopy_m
    lo, hi = config.understorey_from_m, config.understorey_to_m
    under = h[canopy]
    understorey = float(np.mean((under >= lo) & (under < hi))) if canopy.any() else float("nan")
    return understorey, float(np.mean(h < config.ground_band_m))


def kind_evidence(
    xyz: np.ndarray, config: KindConfig, viewpoint: ViewpointConfig, rng: np.random.Generator
) -> KindEvidence:
    """The figures of `xyz` (file coordinates: a station in its own frame sits at the origin)."""
    n = len(xyz)
    extent = float(np.diff(column_bounds(xyz)[:2], axis=1).max()) if n else 0.0
    if n < config.min_points or extent < config.min_extent_m:
        nan = float("nan")
        return KindEvidence(
            points=n,
            extent_m=extent,
            density_per_m2=nan,
            coverage=nan,
            dense_share=nan,
            understorey_share=nan,
            ground_share=nan,
            crowding=nan,
            station=False,
        )
    pts = xyz[sample(n, config.sample_points, rng)]
    cells, inverse, counts = occupied_cells(pts[:, :2], config.cell)
    understorey, ground = column_shares(pts[:, 2], inverse, len(cells), config)
    crowded = crowding(xyz, viewpoint, rng)
    return KindEvidence(
        points=n,
        extent_m=extent,
        density_per_m2=float(n / (len(cells) * config.cell**2)),
        coverage=row_coverage(cells),
        dense_share=dense_share(counts),
        understorey_share=understorey,
        ground_share=ground,
        crowding=crowded,
        station=crowded >= viewpoint.min_crowding,
    )


def decide(e: KindEvidence, config: KindConfig) -> KindDetection:
    """The kind `e` points to, and the figures that decided it."""
    if np.isnan(e.coverage):
        why = (
            f"{e.points} points over {e.extent_m:.1f} m: too small to tell, {DEFAULT_KIND} assumed"
        )
        return KindDetection(kind=DEFAULT_KIND, reason=why, evidence=e)
    even = e.dense_share <= config.max_airborne_dense_share
    hidden = e.understorey_share <= config.max_airborne_understorey  # NaN (no canopy): False
    under = "no canopy" if np.isnan(e.understorey_share) else f"{e.understorey_share:.3f}"
    figures = (
        f"top-down coverage {e.coverage:.2f}, densest 5 % of cells hold {e.dense_share:.2f}, "
        f"understorey share {under}"
    )
    if e.coverage >= config.min_airborne_coverage and (even or hidden):
        kind = "uls" if e.density_per_m2 >= config.min_uls_density else "als"
        seen = "an even, scan-line density" if even else "the understorey hidden by the canopy"
        cmp = ">=" if kind == "uls" else "<"
        why = (
            f"airborne ({figures}: every cell seen from above, {seen}); "
            f"{e.density_per_m2:.0f} pts/m2 {cmp} {config.min_uls_density:g}"
        )
        return KindDetection(kind=kind, reason=why, evidence=e)
    station = "one station at the origin" if e.station else "no single station at the origin"
    base = f"ground-based ({figures}; {station}); ground share {e.ground_share:.3f}"
    if e.ground_share <= config.max_mls_ground_share:
        why = (
            f" (<= {config.max_mls_ground_share:g}: the ground grazed, as a mobile scanner sees it)"
        )
        return KindDetection(kind="mls", reason=base + why, evidence=e)
    why = (
        f" (> {config.max_mls_ground_share:g}: the ground seen all round, as from tripod stations)"
    )
    return KindDetection(kind="tls", reason=base + why, evidence=e)


def detect_kind(
    xyz: np.ndarray, config: KindConfig, viewpoint: ViewpointConfig, seed: int = 0
) -> KindDetection:
    """The sensor kind of the cloud `xyz` (file coordinates), seeded."""
    return decide(kind_evidence(xyz, config, viewpoint, np.random.default_rng(seed)), config)

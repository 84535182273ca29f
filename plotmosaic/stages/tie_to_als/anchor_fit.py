"""How well one plot -> ALS registration is known: the ALS points against the plot's surfaces.

A plot has one anchor, so no loop shows its error, and its ICP information (J^T J / sigma^2 over
thousands of spatially correlated points) is far too confident. Each ALS return is matched to the
merged TLS cloud's local plane at the registered pose (TLS is dense: its planes are good where the
ALS is sparse); the linearised point-to-plane problem is then solved again with one block of ground
(a square of at most `anchor_block` metres) left out at a time. The spread of those solutions (a delete-one
block jackknife) is the anchor's covariance: it holds whatever the blocks disagree on (terrain or
canopy seen differently from the air), not only the point noise that averages away.

The anchor's own ICP and this fit are two estimates of one pose: where they disagree (the step
the fit would take from the anchor), the anchor is off by about that much, so the disagreement is
added to the covariance in its own direction. Blocks capture errors shorter than a block; the
disagreement, those that move the whole plot.

The same residuals are the anchor's profile against the ALS: their median (the ALS above or below
the TLS surfaces) and robust spread.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.align.icp import point_to_plane_jacobian
from plotmosaic.config.register import TieConfig
from plotmosaic.graph.jobs import PairJob
from plotmosaic.io.bounded import read_scan_points

NEIGHBOURS = 12  # TLS points a plane is fitted to (at the plot voxel, a few decimetres across)
MAX_CURVATURE = 0.02  # smallest / summed eigenvalue: a plane; above it, twigs and leaves
MIN_BLOCK_POINTS = 20  # a block with fewer matched ALS points is merged into no solve of its own
MIN_BLOCKS = 4
# blocks shrink below `anchor_block` until about this many cover the plot: a jackknife over a
# handful of blocks swings with whichever edge block is left out
TARGET_BLOCKS = 16


@dataclass(frozen=True, kw_only=True)
class AnchorFit:
    """The ALS against one registered plot (lengths in metres, tangent order rx ry rz tx ty tz on
    the right of the plot -> ALS transform, i.e. in the plot frame)."""

    points: int  # ALS returns matched to a TLS plane
    blocks: int  # jackknife blocks
    covariance: np.ndarray  # 6x6, the anchor's: jackknife + the disagreement's outer product
    disagreement: np.ndarray  # 6, the fit's step from the anchor's pose (rx ry rz in rad, t in m)
    offset_median: float  # median of ALS minus TLS along the plane normals (m)
    offset_nmad: float  # 1.4826 x median absolute deviation of the same (m)

    @property
    def sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    def as_dict(self) -> dict:
        return {
            "als_points": self.points,
            "jackknife_blocks": self.blocks,
            "sigma": self.sigma.tolist(),
            "disagreement_m": float(np.linalg.norm(self.disagreement[3:])),
            "disagreement_deg": float(np.degrees(np.linalg.norm(self.disagreement[:3]))),
            "als_offset_median_m": self.offset_median,
            "als_offset_nmad_m": self.offset_nmad,
        }


def _planes(P: np.ndarray, Q: np.ndarray, max_distance: float):
    """(kept ALS points, plane centres, unit normals) of the ALS points Q near planar TLS P."""
    d, idx = cKDTree(P).query(Q, k=NEIGHBOURS, distance_upper_bound=max_distance)
    ok = np.isfinite(d).all(axis=1)
    Q, nb = Q[ok], P[idx[ok]]
    m = nb.mean(axis=1)
    X = nb - m[:, None, :]
    w, V = np.linalg.eigh(np.einsum("nki,nkj->nij", X, X))
    n = V[:, :, 0]
    planar = w[:, 0] <= MAX_CURVATURE * np.maximum(w.sum(axis=1), 1e-12)
    r = np.einsum("ij,ij->i", n, Q - m)
    keep = planar & (np.abs(r) < max_distance)
    return Q[keep], m[keep], n[keep]


def anchor_fit(
    plot_xyz: np.ndarray, als_xyz: np.ndarray, T: np.ndarray, block: float, max_distance: float
) -> AnchorFit | None:
    """The fit of the ALS points `als_xyz` (ALS CRS) to the plot cloud `plot_xyz` (plot frame) at
    T (plot frame -> ALS CRS); None when too few blocks see both."""
    R, t = T[:3, :3], T[:3, 3]
    c = np.mean(als_xyz, axis=0) if len(als_xyz) else t  # local coordinates: UTM-sized values
    Q, m, n = _planes(plot_xyz @ R.T + (t - c), np.asarray(als_xyz) - c, max_distance)
    if not len(Q):
        return None
    # residual of an ALS point against the plane through m, as the plot moves by T Exp(xi)
    r = np.einsum("ij,ij->i", n, Q - m)
    J = point_to_plane_jacobian((m + c - t) @ R, n, R)
    lo, hi = Q[:, :2].min(axis=0), Q[:, :2].max(axis=0)
    block = min(block, float(np.sqrt(np.prod(hi - lo) / TARGET_BLOCKS)))  # small plots: smaller
    cells = np.floor((Q[:, :2] - lo) / max(block, 1e-3)).astype(np.int64)
    _, label = np.unique(cells, axis=0, return_inverse=True)
    label = label.ravel()
    H, g = J.T @ J, J.T @ r
    full = np.linalg.lstsq(H, g, rcond=None)[0]  # r ~ r0 - J xi: the fit's pose is T Exp(full)
    steps = []
    for b in np.unique(label):
        s = label == b
        if s.sum() >= MIN_BLOCK_POINTS:
            steps.append(np.linalg.lstsq(H - J[s].T @ J[s], g - J[s].T @ r[s], rcond=None)[0])
    if len(steps) < MIN_BLOCKS:
        return None
    X = np.array(steps) - np.mean(steps, axis=0)
    B = len(steps)
    # the signed offset along normals turned upwards: ALS above the TLS surface > 0
    up = np.where(n[:, 2] < 0, -1.0, 1.0) * r
    med = float(np.median(up))
    return AnchorFit(
        points=len(r),
        blocks=B,
        covariance=(B - 1) / B * X.T @ X + np.outer(full, full),
        disagreement=full,
        offset_median=med,
        offset_nmad=float(1.4826 * np.median(np.abs(up - med))),
    )


def fit_anchors(
    jobs: list[PairJob], records: dict[str, dict], config: TieConfig
) -> dict[str, AnchorFit]:
    """Plot id -> the fit of its registered plot cloud to its ALS crop (the pair's two files)."""
    fits = {}
    for job in jobs:
        rec = records[job.key]
        if rec.get("status") != "ok":
            continue
        fit = anchor_fit(
            read_scan_points(job.source_path, config.read, config.align).xyz,
            read_scan_points(job.target_path, config.read, config.align).xyz,
            np.asarray(rec["transform"], dtype=float),
            config.anchor_block,
            config.anchor_max_distance,
        )
        if fit is not None:
            fits[job.source] = fit
    return fits

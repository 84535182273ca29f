"""Levelling: vertical hypotheses of a cloud from its normals and points, and the rotation upright.

Forests give several cues, none of which is always right. Ground and other near-horizontal
surfaces put their normals near the vertical (biased on slopes: the terrain normal is not the
vertical); stems put theirs in the horizontal plane (a leaf-on canopy has few stems and a scatter of
leaf normals that can pull the estimate 10 deg off); the lowest points per cell lie on the terrain;
a georeferenced airborne cloud has z up. So several hypotheses are produced and each is carried
into the search: the verification, not the levelling, decides.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.align.rasters import height_above_ground
from plotmosaic.align.voxel import occupied_groups
from plotmosaic.config.coarse import CoarseConfig

Z = np.array([0.0, 0.0, 1.0])


def fibonacci_hemisphere(n: int) -> np.ndarray:
    """Unit vectors spread evenly over the upper hemisphere (z >= 0)."""
    i = np.arange(n) + 0.5
    z = 1.0 - i / n  # uniform in z over (0, 1]
    r = np.sqrt(1.0 - z**2)
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector a onto unit vector b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def rotate(points: np.ndarray, R: np.ndarray) -> np.ndarray:
    """points @ R.T, column by column: numpy's (N, 3) @ (3, 3) goes through BLAS and is ~50x slower."""
    return np.column_stack(
        [points[:, 0] * R[i, 0] + points[:, 1] * R[i, 1] + points[:, 2] * R[i, 2] for i in range(3)]
    )


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (deg) between two unit vectors."""
    return float(np.degrees(np.arccos(np.clip(float(np.dot(a, b)), -1.0, 1.0))))


def _upper(v: np.ndarray) -> np.ndarray:
    v = v / np.linalg.norm(v)
    return v if v[2] >= 0 else -v


def _refine(
    n: np.ndarray, up: np.ndarray, c: CoarseConfig, use_stems: bool, use_ground: bool
) -> tuple[np.ndarray, float]:
    """Refine `up` over shrinking bands on stem normals (perpendicular to up) and/or the ground cluster."""
    stem_share = 0.0
    for band in c.refine_bands_deg:
        d = np.abs(n @ up)
        stems = n[d < np.sin(np.radians(band))]
        stem_share = len(stems) / max(len(n), 1)
        if use_stems and stem_share > c.min_stem_share and len(stems) > c.min_stem_normals:
            cand = np.linalg.eigh(stems.T @ stems)[1][:, 0]
        elif use_ground:
            ground = n[d > np.cos(np.radians(band))]
            if len(ground) < c.min_ground_normals:
                break
            cand = np.linalg.eigh(ground.T @ ground)[1][:, -1]
        else:
            break
        cand = _upper(cand)
        if angle_deg(cand, up) < 2 * band:
            up = cand
    return up, stem_share


def _votes(n: np.ndarray, c: CoarseConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cands = fibonacci_hemisphere(c.up_candidates)
    cands = cands[cands[:, 2] >= np.cos(np.radians(c.max_tilt_deg))]
    dots = np.abs(n @ cands.T)  # axial normals: n and -n are the same plane
    flat = (dots > np.cos(np.radians(c.flat_deg))).mean(axis=0)
    upright = (dots < np.sin(np.radians(c.upright_deg))).mean(axis=0)
    return cands, flat, upright


def estimate_up(
    normals: np.ndarray,
    max_tilt_deg: float = 75.0,
    n_candidates: int = 1000,
    config: CoarseConfig | None = None,
) -> tuple[np.ndarray, dict]:
    """The cloud's up direction from ground and stem normals together (z-component positive) and its figures.

    Up is taken on the side of the file's +z: a scan is never mounted upside down, and the
    search allows tilts up to `max_tilt_deg`.
    """
    c = (config or CoarseConfig()).model_copy(
        update={"max_tilt_deg": max_tilt_deg, "up_candidates": n_candidates}
    )
    n = np.asarray(normals, dtype=np.float64)
    cands, flat, upright = _votes(n, c)
    up, stem_share = _refine(n, cands[np.argmax(flat + c.upright_weight * upright)], c, True, True)
    return up, {"tilt_deg": angle_deg(up, Z), "stem_share": float(stem_share)}


def ground_fit_up(points: np.ndarray, c: CoarseConfig) -> np.ndarray | None:
    """Normal of a robust plane through the lowest point per cell, in the frame tilted so `points` are ~level.

    Works on the points (not normals): under a leaf-on canopy the few ground returns are still the lowest.
    """
    xy, z = points[:, :2], points[:, 2]
    ij = np.floor((xy - xy.min(axis=0)) / c.ground_fit_cell).astype(np.int64)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    order = np.lexsort((z, key))
    first = order[np.r_[True, key[order][1:] != key[order][:-1]]]
    if len(first) < c.ground_fit_min_cells:
        return None
    low = points[first]
    keep = np.ones(len(low), bool)
    normal = Z
    for _ in range(
        5
    ):  # least squares, dropping points well above the plane (crowns seen from below)
        if keep.sum() < c.ground_fit_min_cells:
            return None
        centre = low[keep].mean(axis=0)
        normal = _upper(np.linalg.eigh(np.cov((low[keep] - centre).T))[1][:, 0])
        r = (low - centre) @ normal
        keep = np.abs(r) < max(c.ground_fit_inlier_m, 2.5 * float(np.median(np.abs(r[keep]))))
    # a strip a few cells wide fits any plane through its long axis: a fit far from level is no ground
    return normal if angle_deg(normal, Z) <= c.ground_fit_max_deg else None


def trunk_axes_up(
    points: np.ndarray, normals: np.ndarray, up: np.ndarray, c: CoarseConfig
) -> tuple[np.ndarray | None, dict]:
    """The median axis of the trunks, found near `up`: on a slope the ground is not level, trunks stand upright.

    Each pass levels the cloud by the current estimate, cuts the stem band above the rough DTM,
    groups its vertical-surface points in xy and takes each elongated group's main axis (PCA of its
    points); the median of the axes' slopes is robust to leaning stems, branches and bushes.
    """
    info: dict = {"trunks": 0}
    lo, hi = c.trunk_hag
    for _ in range(c.trunk_passes):
        R = rotation_between(up, Z)
        p, n = rotate(points, R), rotate(normals, R)
        hag = height_above_ground(p, c.feature_cell, c)
        sel = (hag >= lo) & (hag <= hi) & (np.abs(n[:, 2]) < np.sin(np.radians(c.trunk_normal_deg)))
        q = p[sel]
        if len(q) < c.trunk_min_points:
            return None, info
        slopes = []
        for idx in occupied_groups(q[:, :2], c.stem_cluster_m):
            if len(idx) < c.trunk_min_points or np.ptp(q[idx, 2]) < c.trunk_min_span:
                continue
            w, V = np.linalg.eigh(np.cov(q[idx].T))
            axis = _upper(V[:, -1])
            # a trunk is long and thin: main spread well above the width, width below a trunk's
            if w[-1] < c.trunk_elongation * w[-2] or 4.0 * np.sqrt(w[-2]) > c.stem_max_diameter:
                continue
            if angle_deg(axis, Z) > c.trunk_max_lean_deg:
                continue
            slopes.append(axis[:2] / axis[2])
        info = {"trunks": len(slopes)}
        if len(slopes) < c.trunk_min_count:
            return None, info
        s = np.asarray(slopes)
        m = np.median(s, axis=0)
        dev = np.degrees(np.arctan(np.linalg.norm(s - m, axis=1)))
        info["spread_deg"] = round(float(np.median(dev)), 2)
        up = _upper(R.T @ np.array([m[0], m[1], 1.0]))
    return up, info


@dataclass(frozen=True)
class Vertical:
    up: np.ndarray  # unit vector in the cloud's local frame
    name: str  # "normals" | "trunks" | "ground" | "ground-fit" | "z-up"

    @property
    def R(self) -> np.ndarray:
        return rotation_between(self.up, Z)


def vertical_hypotheses(
    points: np.ndarray,
    normals: np.ndarray,
    c: CoarseConfig,
    airborne: bool = False,
    limit: int | None = None,
    dense: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[list[Vertical], dict]:
    """Distinct vertical hypotheses, most trusted first, and the figures behind them.

    `airborne` (ALS/ULS, georeferenced): z-up first. z-up is also a candidate of any cloud where an
    estimate lies within `z_up_max_deg` of it. A tilt up to `max_tilt_deg` stays recoverable.
    `dense` (points, normals): the cloud the trunk axes are fitted on; without it no trunk vertical
    (a 10,000-point levelling sample leaves 1-7 trunk groups of a view: too few for a median).
    """
    n = np.asarray(normals, dtype=np.float64)
    cands, flat, upright = _votes(n, c)
    first = cands[np.argmax(flat + c.upright_weight * upright)]
    both, stem_share = _refine(n, first, c, True, True)
    ground, _ = _refine(n, cands[np.argmax(flat)], c, False, True)
    trunks, trunk_info = (None, {}) if dense is None else trunk_axes_up(*dense, both, c)
    fit = ground_fit_up(
        rotate(points, rotation_between(both, Z)), c
    )  # fit in the roughly levelled frame
    fit = None if fit is None else _upper(rotation_between(both, Z).T @ fit)
    found = [Vertical(both, "normals")]
    if trunks is not None:
        # ground-based views: trunks first, the kind two views of one plot agree on best
        # (docs/method.md#coarse-stage-settings)
        found.insert(0 if not airborne else 1, Vertical(trunks, "trunks"))
    found.append(Vertical(ground, "ground"))
    if fit is not None:
        found.append(Vertical(fit, "ground-fit"))
    near_z = any(angle_deg(v.up, Z) <= c.z_up_max_deg for v in found)
    ordered = ([Vertical(Z.copy(), "z-up")] if airborne else []) + found[:1]
    if near_z and not airborne:
        ordered.append(Vertical(Z.copy(), "z-up"))
    ordered += found[1:]
    out: list[Vertical] = []
    for v in ordered:
        # an estimate far from the joint one levels nothing (a boxed view's ground vote can pick a
        # trunk's side) and would take a search slot from a useful vertical
        far = v.name != "z-up" and angle_deg(v.up, both) > c.max_vertical_spread_deg
        if not far and all(angle_deg(v.up, o.up) > c.vertical_duplicate_deg for o in out):
            out.append(v)
    out = out[: limit or c.max_verticals]
    info = {
        "tilt_deg": angle_deg(out[0].up, Z),
        "stem_share": float(stem_share),
        "trunks": trunk_info,
        "candidates": {v.name: round(angle_deg(v.up, Z), 2) for v in found},
        "verticals": [
            {"name": v.name, "tilt_deg": round(angle_deg(v.up, Z), 3), "up": v.up.round(5).tolist()}
            for v in out
        ],
    }
    return out, info

"""The survey refined as one: every overlapping pair's point-to-plane residuals, all scans' poses
solved together (multi-view ICP), then one consistent edge for each pair.

Maps verify where each scan of a sparse survey stands, but a map measured against neighbours that
are themselves a little off inherits their errors, and rounds of maps remove long errors (a bend or
tilt across the plot) only slowly. Here each iteration matches every pair at the current poses and
takes one robust Gauss-Newton step of all poses at once (the reference fixed), so the survey
settles on its own surfaces in a few steps. Each pair's samples are drawn once, where the two scans
meet at the start, and kept: the same poses give the same correspondences.

Poses map each scan's local frame into the plot's local frame (the plot frame less an offset), so
UTM-sized coordinates never enter the normal equations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.align.icp import (
    exp_se3,
    facing,
    information_matrix,
    nearest,
    point_to_plane_jacobian,
)
from plotmosaic.align.prepare import PreparedCloud
from plotmosaic.align.sampling import sample
from plotmosaic.io.frame import inverse, translation

SEED = 11  # the pair samples' own stream: the same survey, the same samples


@dataclass(frozen=True, kw_only=True)
class SurveySettings:
    """What the refinement runs with (from MapConfig)."""

    lens_distance: float  # a point this near the other scan at the start is in their overlap
    points: int  # sample points per pair and direction
    schedule: tuple[tuple[float, int], ...]  # (correspondence distance m, iterations) stages
    kernel: float  # least Tukey width (m)
    min_points: int  # fewer matches: the pair gives no edge
    patch: float  # side (m) of the patches whose residuals err together


@dataclass(frozen=True, kw_only=True)
class SurveyEdge:
    """One pair at the refined poses: source file -> target file, and its information."""

    source: str
    target: str
    transform: np.ndarray
    information: np.ndarray
    points: int


def _jacobians(p, q, n, A_i, A_j):
    """Residuals n.(A_i p - A_j q) (in j's frame) and their rows for right perturbations of both."""
    R_i, t_i, R_j, t_j = A_i[:3, :3], A_i[:3, 3], A_j[:3, :3], A_j[:3, 3]
    into_j = R_j.T @ R_i
    moved = p @ into_j.T + R_j.T @ (t_i - t_j)  # i's points in j's local frame
    r = np.einsum("ij,ij->i", n, moved - q)
    J_i = point_to_plane_jacobian(p, n, into_j)
    J_j = -np.hstack([np.cross(q, n), n])
    return r, J_i, J_j


def refine_survey(
    clouds: dict[str, PreparedCloud],
    poses: dict[str, np.ndarray],
    pairs: list[tuple[str, str]],
    fixed: str,
    settings: SurveySettings,
) -> tuple[dict[str, np.ndarray], list[SurveyEdge]]:
    """(poses, edges): `poses` (scan file -> plot frame) of the scans in `pairs` refined together,
    `fixed` held; an edge for every pair with enough matches at the refined poses."""
    offset = np.mean([poses[s][:3, 3] for s in poses], axis=0)
    # scan local -> plot local
    A = {s: translation(-offset) @ poses[s] @ translation(clouds[s].frame.offset) for s in clouds}
    free = sorted({s for pair in pairs for s in pair} - {fixed})
    index = {s: k for k, s in enumerate(free)}
    samples = {pair: _lens(clouds, A, pair, settings) for pair in pairs}
    for distance, iterations in settings.schedule:
        kernel = max(settings.kernel, distance / 2)
        for _ in range(iterations):
            H = np.zeros((6 * len(free), 6 * len(free)))
            g = np.zeros(6 * len(free))
            for (i, j), p in samples.items():
                got = _matches(clouds, A, i, j, p, distance)
                if got is None:
                    continue
                p_m, q, n = got
                r, J_i, J_j = _jacobians(p_m, q, n, A[i], A[j])
                w = np.where(np.abs(r) < kernel, (1 - (r / kernel) ** 2) ** 2, 0.0)
                blocks = [(index.get(i), J_i), (index.get(j), J_j)]
                for a, Ja in blocks:
                    if a is None:
                        continue
                    g[6 * a : 6 * a + 6] += (Ja * w[:, None]).T @ r
                    for b, Jb in blocks:
                        if b is not None:
                            H[6 * a : 6 * a + 6, 6 * b : 6 * b + 6] += (Ja * w[:, None]).T @ Jb
            if not len(free) or not np.any(H):
                break
            step = np.linalg.solve(H + 1e-9 * np.trace(H) / len(H) * np.eye(len(H)), -g)
            for s, k in index.items():
                A[s] = A[s] @ exp_se3(step[6 * k : 6 * k + 6])
            if np.abs(step).max() < 1e-7:
                break
    refined = {s: translation(offset) @ A[s] @ translation(-clouds[s].frame.offset) for s in clouds}
    edges = []
    for (i, j), p in samples.items():
        got = _matches(clouds, A, i, j, p, settings.schedule[-1][0])
        if got is None or len(got[0]) < settings.min_points:
            continue
        p_m, q, n = got
        E = inverse(refined[j]) @ refined[i]
        info, _ = information_matrix(
            clouds[i].frame.to_global(p_m), clouds[j].frame.to_global(q), n, E
        )
        # neighbouring points err together (the same twig, the same patch of bark): the pair
        # holds about as many independent residuals as the patches its matches cover
        info = info * _patches(q, settings.patch) / len(q)
        edges.append(SurveyEdge(source=i, target=j, transform=E, information=info, points=len(q)))
    return {s: refined[s] for s in free}, edges


def _patches(points: np.ndarray, size: float) -> int:
    """Occupied `size` cubes among the points."""
    return len(np.unique(np.floor(points / size).astype(np.int64), axis=0))


def _lens(clouds, A, pair, settings: SurveySettings) -> np.ndarray:
    """Points of pair[0] (its local frame) within the lens distance of pair[1] at the start."""
    i, j = pair
    M = inverse(A[j]) @ A[i]
    grid = clouds[i].points
    d, _ = nearest(clouds[j].tree, grid @ M[:3, :3].T + M[:3, 3], settings.lens_distance)
    near = grid[np.isfinite(d)]
    return near[sample(len(near), settings.points, np.random.default_rng(SEED))]


def _matches(clouds, A, i, j, p, distance):
    """(i's points, j's matched points, j's normals) within `distance`, all in their local frames;
    where both scanners are known, only matches whose plane both saw from the same side (the two
    faces of a stem seen from opposite sides pull a baseline short: align/icp.facing)."""
    if len(p) == 0:
        return None
    M = inverse(A[j]) @ A[i]
    d, idx = nearest(clouds[j].tree, p @ M[:3, :3].T + M[:3, 3], distance)
    ok = np.flatnonzero(np.isfinite(d))
    q, n = clouds[j].points[idx[ok]], clouds[j].target_normals(idx[ok])
    views = clouds[i].viewpoint, clouds[j].viewpoint
    if views[0] is not None and views[1] is not None:
        seen = facing(n, q, M[:3, :3] @ views[0] + M[:3, 3], views[1])
        ok, q, n = ok[seen], q[seen], n[seen]
    if len(ok) < 12:
        return None
    return p[ok], q, n

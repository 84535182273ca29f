"""Point-to-plane ICP (numpy Gauss-Newton on a scipy KD-tree), quality figures and the information matrix."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.config.align import IcpStage
from plotmosaic.parallel import inner_workers

# a query of fewer points runs in the calling thread: cKDTree's split of a small query (an ICP
# iteration's) across threads costs more CPU than it saves time; each point's answer is the same
SPLIT_QUERY_POINTS = 50_000


def _workers(points: np.ndarray) -> int:
    return inner_workers() if len(points) >= SPLIT_QUERY_POINTS else 1


def nearest(tree: cKDTree, points: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """(distances, indices) of each point's nearest tree point; inf / len(tree) beyond `distance`."""
    return tree.query(points, distance_upper_bound=distance, workers=_workers(points))


# a correspondence search looks this many times its distance far: a point with no neighbour within
# the distance learns how far its nearest is, and keeps that answer while it moves less than its margin
REACH = 1.5


class MovingNearest:
    """`nearest` for points that move a little between calls (one ICP run's iterations): a point
    keeps its nearest tree point while it has moved less than that point's lead over every other
    one at its last query (the second nearest, or REACH x the search distance), and only the rest
    are queried again. The same neighbours and distances as a full query within the distance: the
    kept distances use cKDTree's own formula; a tie or a nearest point on the search distance is
    queried again."""

    def __init__(self, tree: cKDTree):
        self.tree = tree
        self.at: np.ndarray | None = None  # each point where it was last queried
        self.index = np.zeros(0, np.int64)  # its nearest there, len(tree) if none in reach
        self.floor = np.zeros(0)  # no other tree point was closer than this to it there

    def __call__(self, points: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
        n = self.tree.n
        if self.at is None or len(points) != len(self.at):
            self.at = points.copy()
            self.index, self.floor = np.full(len(points), n), np.zeros(len(points))
            return self._query(points, distance, np.arange(len(points)))
        lower = self.floor - _distance(points, self.at) - 1e-9  # rounding of the two distances
        has = self.index < n
        d = np.full(len(points), np.inf)
        d[has] = _distance(points[has], self.tree.data[self.index[has]])
        # still the nearest, and plainly inside or beyond the search distance
        kept = np.where(has, (d < lower) & (np.abs(d - distance) > 1e-9), lower > distance)
        out = np.where(kept & (d < distance), self.index, n)
        d[out == n] = np.inf
        again = np.flatnonzero(~kept)
        if len(again):
            d[again], out[again] = self._query(points[again], distance, again)
        return d, out

    def _query(self, points: np.ndarray, distance: float, rows: np.ndarray):
        """The two nearest of `points` within REACH x `distance` (rows `rows` of the cache), kept
        for the next call; returned as a query within `distance` gives them."""
        reach = REACH * distance
        d, j = self.tree.query(points, k=2, distance_upper_bound=reach, workers=_workers(points))
        self.at[rows], self.index[rows] = points, j[:, 0]
        self.floor[rows] = np.where(np.isfinite(d[:, 1]), d[:, 1], reach)
        beyond = d[:, 0] >= distance
        found, index = np.where(beyond, np.inf, d[:, 0]), np.where(beyond, self.tree.n, j[:, 0])
        # the tree's own answer where these do not make it plain: two equally near (the first of
        # two need not be the one a single-neighbour query picks), or a nearest on the distance
        ask = np.flatnonzero(
            np.isfinite(d[:, 0]) & ((d[:, 0] == d[:, 1]) | (np.abs(d[:, 0] - distance) <= 1e-9))
        )
        if len(ask):
            found[ask], index[ask] = nearest(self.tree, points[ask], distance)
        return found, index


def _distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row distances summed in cKDTree's order (x, then y, then z), so a kept neighbour's distance
    has the bits a query would give it."""
    diff = a - b
    return np.sqrt((diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1]) + diff[:, 2] * diff[:, 2])


def evaluate(
    source: np.ndarray, tree: cKDTree, T: np.ndarray, distance: float
) -> tuple[float, float, int]:
    """(fitness, inlier RMSE, inliers) of source points under T against the tree's points within `distance`."""
    if len(source) == 0:
        return 0.0, float("nan"), 0
    d, _ = nearest(tree, source @ T[:3, :3].T + T[:3, 3], distance)
    ok = np.isfinite(d)
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else float("nan")
    return float(ok.mean()), rmse, int(ok.sum())


def point_to_plane_jacobian(p: np.ndarray, n: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rows d r_i / d xi for r_i = n_i.(T Exp(xi) p_i - q_i), xi = (w, v) (GTSAM Pose3 order)."""
    m = n @ R  # rows R^T n_i
    return np.hstack([np.cross(p, m), m])


def information_matrix(
    p: np.ndarray, q: np.ndarray, n: np.ndarray, T: np.ndarray
) -> tuple[np.ndarray, float]:
    """J^T J / sigma^2 for the point-to-plane problem, sigma^2 = inlier residual variance.

    p: source points, q and n: matched target points and normals, all in the coordinates T maps
    between (file coordinates for the stored result). Returns (information 6x6, sigma).
    """
    R, t = T[:3, :3], T[:3, 3]
    r = np.einsum("ij,ij->i", n, p @ R.T + t - q)
    sigma2 = float(np.mean(r**2)) if len(r) else float("nan")
    sigma2 = max(sigma2, 1e-8)
    J = point_to_plane_jacobian(p, n, R)
    return J.T @ J / sigma2, float(np.sqrt(sigma2))


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential, xi = (w, v)."""
    w, v = xi[:3], xi[3:]
    th = np.linalg.norm(w)
    K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        R, V = np.eye(3) + K, np.eye(3)
    else:
        a, b, c = np.sin(th) / th, (1 - np.cos(th)) / th**2, (th - np.sin(th)) / th**3
        R = np.eye(3) + a * K + b * K @ K
        V = np.eye(3) + b * K + c * K @ K
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, V @ v
    return T


def facing(n: np.ndarray, x: np.ndarray, view_a: np.ndarray, view_b: np.ndarray) -> np.ndarray:
    """Rows whose plane (point x, normal n) has both viewpoints on the same side: two scanners can
    only have seen the same side of a surface; opposite sides are the two faces of a stem or branch."""
    return np.einsum("ij,ij->i", n, view_a - x) * np.einsum("ij,ij->i", n, view_b - x) > 0


@dataclass(frozen=True)
class Mirror:
    """The reverse correspondences of a symmetric ICP: `points` (a target sample) matched to the
    source cloud (`tree` over `source`, normals by row from `normals_of`)."""

    points: np.ndarray
    source: np.ndarray
    tree: cKDTree
    normals_of: Callable[[np.ndarray], np.ndarray]

    def stacked(self, T: np.ndarray, distance: float, a, b, n, views=None, search=None):
        """Forward (a = T p, b = q, n) with the reverse rows appended, all in target coordinates:
        a source point under T, the target sample point it was matched from, its plane turned by T.
        `views`: both scanners in target coordinates; reverse rows seen from opposite sides are left out.
        `search`: a MovingNearest over `tree` kept across one ICP run's iterations."""
        R, t = T[:3, :3], T[:3, 3]
        back = (self.points - t) @ R  # target sample in source coordinates
        d, j = (search or MovingNearest(self.tree))(back, distance)
        ok = np.flatnonzero(np.isfinite(d))
        a2 = self.source[j[ok]] @ R.T + t
        n2 = self.normals_of(j[ok]) @ R.T
        if views is not None:
            seen = facing(n2, a2, *views)
            ok, a2, n2 = ok[seen], a2[seen], n2[seen]
        if not len(ok):
            return a, b, n
        return np.vstack([a, a2]), np.vstack([b, self.points[ok]]), np.vstack([n, n2])


@dataclass(frozen=True)
class IcpResult:
    T: np.ndarray
    fitness: float  # share of source points with a correspondence in the last iteration
    rmse: float  # of their point-to-point distances
    rank: int  # directions the last step was allowed to move along (6 = all; 4 with an axis)
    source_index: np.ndarray  # last correspondences (source row, target row)
    target_index: np.ndarray
    iterations: int


@dataclass(frozen=True, kw_only=True, eq=False)
class IcpOptions:
    """How one point_to_plane_icp run steps: its stages and the solver's constants."""

    stages: tuple[IcpStage, ...]  # coarse to fine, each run to its iterations or to `tol`
    min_eig_ratio: float = 0.0  # directions weaker than this x the strongest wait (0: all six move)
    kernel_floor: float = 0.05  # Tukey's width never below this (m)
    kernel_ratio: float = 0.5  # Tukey's width, x the stage's correspondence distance
    tol: float = 1e-5  # a stage ends when a step moves points by less (m)
    # turn only about this axis (target coordinates; None: all three): a start levelled under a
    # vertical keeps its tilt while thin overlap (mostly ground) cannot yet decide it
    axis: np.ndarray | None = None


def point_to_plane_icp(
    source: np.ndarray,
    target: np.ndarray,
    target_normals,
    init: np.ndarray,
    options: IcpOptions,
    search: MovingNearest | None = None,
    mirror: Mirror | None = None,
    viewpoints: tuple[np.ndarray, np.ndarray] | None = None,
) -> IcpResult:
    """Point-to-plane ICP (Tukey-weighted Gauss-Newton) that moves only along well-constrained directions.

    `target_normals`: an (M, 3) array, or a callable giving the normals of target rows on demand
    (so a dense target needs normals only where it is matched). A level such as ground alone
    constrains height, roll and pitch but hardly x, y and yaw; a plain solver lets noise and the
    uneven overlap slide it there (we saw tens of degrees of yaw on sloped ground). Each step is
    solved in the eigenbasis of the (scaled) normal matrix and directions whose eigenvalue is below
    `min_eig_ratio` x the largest are left for the next, richer level (degeneracy-aware ICP,
    Zhang et al. 2016); 0 moves along all six. Tukey's width is `kernel_ratio` x the stage's
    correspondence distance, never below `kernel_floor` (`options`).

    `search`: the target's nearest points, a MovingNearest over its KD-tree (None: a tree built
    here); one kept from an earlier run on the same source rows (one start refined stage by stage)
    holds its neighbours whatever the distance, so the run's first iteration queries only the
    points that moved too far.

    `mirror`: the other direction too (symmetric ICP): a sample of the target matched to the
    source's planes, its residuals stacked with the forward ones in one solve. One direction leaves
    sparse scans' pairs biased by the side whose planes it uses; the result's correspondences
    (and so the information matrix) stay the forward ones.

    `viewpoints`: (source scanner in source coordinates, target scanner in target coordinates);
    a match whose plane has the two scanners on opposite sides is left out (see `facing`).
    """
    forward = search if search is not None else MovingNearest(cKDTree(target))
    backward = MovingNearest(mirror.tree) if mirror is not None else None
    normals_of = target_normals if callable(target_normals) else (lambda j: target_normals[j])
    T = np.asarray(init, dtype=np.float64).copy()
    centre = source.mean(axis=0)
    # work about the source centroid so rotation and translation are on comparable scales
    p0 = source - centre
    scale = max(np.sqrt((p0**2).sum(axis=1).mean()), 1e-3)
    result = IcpResult(T, 0.0, float("nan"), 0, np.zeros(0, np.int64), np.zeros(0, np.int64), 0)
    iterations = 0
    for st in options.stages:
        k = max(st.max_distance * options.kernel_ratio, options.kernel_floor)
        for _ in range(st.iterations):
            iterations += 1
            moved = source @ T[:3, :3].T + T[:3, 3]
            d, j = forward(moved, st.max_distance)
            ok = np.flatnonzero(np.isfinite(d))
            if len(ok) < 12:
                return IcpResult(T, 0.0, float("nan"), 0, ok, j[ok], iterations)
            n = normals_of(j[ok])
            a, b = moved[ok], target[j[ok]]
            views = None
            if viewpoints is not None:
                views = (T[:3, :3] @ viewpoints[0] + T[:3, 3], viewpoints[1])
                seen = facing(n, b, *views)
                ok, a, b, n = ok[seen], a[seen], b[seen], n[seen]
            if mirror is not None:
                a, b, n = mirror.stacked(T, st.max_distance, a, b, n, views, backward)
            T, step, rank = _gauss_newton_step(T, a, b, n, centre, scale, k, options)
            result = IcpResult(
                T,
                float(len(ok) / len(source)),
                float(np.sqrt(np.mean(d[ok] ** 2))),
                rank,
                ok,
                j[ok],
                iterations,
            )
            if np.linalg.norm(step[:3]) * scale + np.linalg.norm(step[3:]) < options.tol:
                break
    return result


def _gauss_newton_step(
    T: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    n: np.ndarray,
    centre: np.ndarray,
    scale: float,
    k: float,
    options: IcpOptions,
) -> tuple[np.ndarray, np.ndarray, int]:
    """One Tukey-weighted point-to-plane step from T (moved source `a` on target planes (b, n)):
    (the new T, the step, how many directions it moved along)."""
    r = np.einsum("ij,ij->i", n, a - b)
    wgt = np.where(np.abs(r) < k, (1 - (r / k) ** 2) ** 2, 0.0)  # Tukey
    # residual as a function of a left perturbation about the moved centroid
    c = T[:3, :3] @ centre + T[:3, 3]
    J = np.hstack([np.cross(a - c, n) / scale, n])
    # with an axis a step moves along its turn and the translation only (columns: twists)
    basis = None
    if options.axis is not None:
        basis = np.zeros((6, 4))
        basis[:3, 0], basis[3:, 1:] = options.axis, np.eye(3)
        J = J @ basis
    Jw = J * wgt[:, None]
    H, g = Jw.T @ J, Jw.T @ r
    vals, vecs = np.linalg.eigh(H)
    keep = vals > max(options.min_eig_ratio, 1e-9) * vals[-1]
    step = -(vecs[:, keep] @ ((vecs[:, keep].T @ g) / vals[keep]))
    if basis is not None:
        step = basis @ step
    step[:3] /= scale
    Tc = np.eye(4)
    Tc[:3, 3] = c
    return Tc @ exp_se3(step) @ np.linalg.inv(Tc) @ T, step, int(keep.sum())

"""Pose hypotheses from 3D local features: FPFH on forest-scale voxels, mutual matches, robust estimators.

Independent of rasters: FPFH (Rusu et al. 2009; Open3D's definition, in numpy) describes each thinned point's neighbourhood
(~2 m: a trunk and its base, a crown edge); mutual nearest neighbours in descriptor space give
putative correspondences, mostly wrong in a forest. With a vertical hypothesis per cloud only
4 DoF remain (yaw + xyz): an exhaustive heading sweep bins every correspondence's translation and
the fullest bins are the poses; a 6-DoF RANSAC (3 correspondences, Kabsch) trusts no vertical at all.
Everything is seeded and bounded (points, samples), so the same inputs give the same hypotheses.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.spatial import cKDTree

from plotmosaic.align.levelling import rotate
from plotmosaic.align.normals import local_shape
from plotmosaic.align.voxel import voxel_centroids
from plotmosaic.config.coarse import CoarseConfig

CHUNK = 256  # hypotheses scored per batch: bounds memory at CHUNK x correspondences
PRE_COUNT = 400  # correspondences every sample is first scored on (evenly spaced: deterministic)
PRE_KEEP = 64  # samples scored on all correspondences
BINS = 11  # FPFH bins per angle feature (Rusu et al.; Open3D, PCL)
NORMAL_NN = (
    30  # neighbours of an FPFH point's normal (within fpfh_normal_radius), as Open3D's default
)


@dataclass(frozen=True)
class Features:
    points: np.ndarray  # (N, 3) local frame
    descriptors: np.ndarray  # (N, 33)


def voxel_count(points: np.ndarray) -> Callable[[float], int]:
    """The points left of `points` at a voxel size: what `shared_voxel` asks of a cloud."""
    return lambda voxel: len(voxel_centroids(points, voxel))


def shared_voxel(counts: list[Callable[[float], int]], config: CoarseConfig) -> float:
    """One FPFH voxel for both clouds: descriptors compare only at the same scale.

    Grown from `fpfh_voxel` until the smaller cloud holds at most `fpfh_max_points` and the larger
    at most `fpfh_max_points_larger` (a 6 m boxed view against a 30 m one: 2,600 and 11,000 points
    at 0.3 m; each capped on its own, the larger grew to 0.5 m and no descriptor matched).
    `counts`: each cloud's points at a voxel size (`voxel_count`, or one kept in the cloud's memo).
    """
    c = config
    voxel = c.fpfh_voxel
    for _ in range(64):  # bounded: each step removes ~30 % of the points
        n = sorted(count(voxel) for count in counts)
        if n[0] <= c.fpfh_max_points and n[-1] <= c.fpfh_max_points_larger:
            break
        voxel *= 1.2
    return voxel


def fpfh_features(points: np.ndarray, config: CoarseConfig, voxel: float | None = None) -> Features:
    """FPFH of a voxel-thinned copy of `points` (local frame) at `voxel` (default: `shared_voxel` of it alone)."""
    c = config
    # a common voxel, not a random subset: a subset would put the two clouds' points in different
    # places and leave almost no repeatable descriptors (8 right matches of 1,900 on MLS views)
    voxel = shared_voxel([voxel_count(points)], c) if voxel is None else voxel
    pts = voxel_centroids(points, voxel)
    scale = voxel / c.fpfh_voxel  # neighbourhoods keep their size in voxels
    desc = fpfh(pts, c.fpfh_normal_radius * scale, c.fpfh_radius * scale, c.fpfh_max_nn)
    ok = desc.sum(axis=1) > 0  # a point without neighbours has no descriptor
    return Features(pts[ok], desc[ok])


def fpfh(pts: np.ndarray, normal_radius: float, radius: float, max_nn: int) -> np.ndarray:
    """(N, 33) FPFH descriptors (Rusu et al. 2009, with Open3D's pair features and binning).

    numpy/scipy instead of Open3D: the same descriptors at a similar cost, without Open3D's slow import
    on every align. Normals keep the eigen-solver's sign, as in Open3D: orienting them towards the
    cloud's centre lost the truth of boxed-in views.
    """
    n_pts = len(pts)
    out = np.zeros((n_pts, 3 * BINS), np.float32)
    if n_pts < 2:
        return out
    tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
    n = local_shape(pts, tree, pts, normal_radius, NORMAL_NN)[0]
    d, idx = tree.query(pts, k=min(max_nn, n_pts), distance_upper_bound=radius)
    d, idx = d.reshape(n_pts, -1), idx.reshape(n_pts, -1)
    rows = np.broadcast_to(np.arange(n_pts)[:, None], idx.shape)
    ok = (idx < n_pts) & (idx != rows)
    i, j, dist = rows[ok], idx[ok], d[ok]
    # pair features (Open3D's ComputePairFeatures): the Darboux frame at the point whose normal is
    # closer to the line joining them
    n1, n2, dp = n[i], n[j], pts[j] - pts[i]
    f4 = np.linalg.norm(dp, axis=1)
    safe = np.where(f4 > 0, f4, 1.0)
    a1 = np.einsum("ij,ij->i", n1, dp) / safe
    a2 = np.einsum("ij,ij->i", n2, dp) / safe
    swap = (np.abs(a1) < np.abs(a2))[:, None]
    na, nb = np.where(swap, n2, n1), np.where(swap, n1, n2)
    dp = np.where(swap, -dp, dp)
    f3 = np.where(swap[:, 0], -a2, a1)
    v = np.cross(dp, na)
    vn = np.linalg.norm(v, axis=1)
    good = (vn > 0) & (f4 > 0)
    v /= np.where(vn > 0, vn, 1.0)[:, None]
    w = np.cross(na, v)
    f2 = np.einsum("ij,ij->i", v, nb)
    f1 = np.arctan2(np.einsum("ij,ij->i", w, nb), np.einsum("ij,ij->i", na, nb))
    f1, f2, f3 = (np.where(good, f, 0.0) for f in (f1, f2, f3))
    bins = (
        np.clip(np.floor(BINS * (f1 + np.pi) / (2 * np.pi)), 0, BINS - 1),
        np.clip(np.floor(BINS * (f2 + 1.0) * 0.5), 0, BINS - 1),
        np.clip(np.floor(BINS * (f3 + 1.0) * 0.5), 0, BINS - 1),
    )
    # SPFH: each point's three histograms of its own pairs, 100 in all per histogram
    count = np.bincount(i, minlength=n_pts)
    incr = 100.0 / np.maximum(count[i], 1)
    spfh = np.zeros(n_pts * 3 * BINS)
    for k, b in enumerate(bins):
        spfh += np.bincount(
            i * 3 * BINS + k * BINS + b.astype(np.int64), weights=incr, minlength=len(spfh)
        )
    spfh = spfh.reshape(n_pts, 3 * BINS)
    # FPFH: the neighbours' SPFH weighted by 1 / squared distance, each histogram scaled to 100, plus its own
    wgt = np.where(dist > 0, 1.0 / np.where(dist > 0, dist, 1.0) ** 2, 0.0)
    acc = (sparse.csr_matrix((wgt, (i, j)), shape=(n_pts, n_pts)) @ spfh).reshape(n_pts, 3, BINS)
    sums = acc.sum(axis=2, keepdims=True)
    acc *= np.where(sums > 0, 100.0 / np.where(sums > 0, sums, 1.0), 0.0)
    out[:] = acc.reshape(n_pts, 3 * BINS) + spfh
    out[count == 0] = 0.0
    return out


def mutual_matches(a: Features, b: Features) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i in a, j in b) that are each other's nearest descriptor."""
    if len(a.points) < 3 or len(b.points) < 3:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    ab, ba = _nearest_both(a.descriptors, b.descriptors)
    i = np.flatnonzero(ba[ab] == np.arange(len(a.points)))
    return i, ab[i]


def _nearest_both(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest row of b for each row of a and vice versa, brute force in float32 blocks.

    A KD-tree in 33 dimensions visits nearly every node (20 s for 12k x 12k); blocked matrix
    products do the same work in a fraction of a second, in bounded memory. argmin |x - y|^2 over y
    is argmax x.y - |y|^2 / 2, one product of augmented rows: no elementwise pass over the block.
    """
    return _nearest_rows(a, b), _nearest_rows(b, a)


def _nearest_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each row of a, the index of its nearest row of b."""
    a1 = np.hstack([a, np.ones((len(a), 1), a.dtype)])
    b1 = np.hstack([b, -0.5 * (b * b).sum(axis=1, keepdims=True)]).T.copy()
    out = np.empty(len(a), np.int64)
    step = max(1, (CHUNK * 8 * 16_000) // max(len(b), 1))  # blocks of ~32M floats
    for s in range(0, len(a), step):
        out[s : s + step] = (a1[s : s + step] @ b1).argmax(axis=1)
    return out


def _count(R: np.ndarray, t: np.ndarray, p: np.ndarray, q: np.ndarray, inlier: float) -> np.ndarray:
    """Inliers of each of K poses (R (K,3,3), t (K,3)) over correspondences p -> q, in bounded batches."""
    out = np.empty(len(R), np.int64)
    for s in range(0, len(R), CHUNK):
        moved = np.matmul(p[None], np.swapaxes(R[s : s + CHUNK], 1, 2)) + t[s : s + CHUNK, None, :]
        out[s : s + CHUNK] = (((moved - q[None]) ** 2).sum(axis=-1) < inlier**2).sum(axis=1)
    return out


def _rigid(p: np.ndarray, q: np.ndarray, four_dof: bool) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares pose q ~ R p + t (rotation about z only when `four_dof`)."""
    cp, cq = p.mean(axis=0), q.mean(axis=0)
    P, Q = p - cp, q - cq
    if four_dof:
        yaw = np.arctan2(
            (P[:, 0] * Q[:, 1] - P[:, 1] * Q[:, 0]).sum(),
            (P[:, 0] * Q[:, 0] + P[:, 1] * Q[:, 1]).sum(),
        )
        R = _rz(np.array([yaw]))[0]
    else:
        U, _, Vt = np.linalg.svd(P.T @ Q)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T
    return R, cq - R @ cp


def _rz(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros((len(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


def _sample_sets(n: int, k: int, draws: int, rng: np.random.Generator) -> np.ndarray:
    idx = rng.integers(0, n, size=(draws, k))
    distinct = np.all(np.diff(np.sort(idx, axis=1), axis=1) > 0, axis=1)
    return idx[distinct]


def vote_4dof(p: np.ndarray, q: np.ndarray, config: CoarseConfig) -> list[tuple[np.ndarray, int]]:
    """Poses (4x4, levelled p -> levelled q) of an exhaustive heading sweep, best first, with inlier counts.

    With the vertical known, a heading fixes every correspondence's translation q - R p; the right
    ones agree within the inlier distance. Each heading's translations are binned (two grids half a
    bin apart, so a cluster cut by one grid's border is whole in the other) and the fullest bins
    become poses. Exhaustive and seeded by nothing: random pair sampling draws only a handful of
    right samples when few matches are right (sparse views metres apart).
    """
    c = config
    if len(p) < 2:
        return []
    centre = p.mean(axis=0)
    rel = p - centre
    yaws = np.radians(np.arange(0.0, 360.0, c.fpfh_vote_yaw_deg))
    cell = c.fpfh_inlier_m
    best_R, best_t, best_n = [], [], []
    for yaw in yaws:
        cs, sn = np.cos(yaw), np.sin(yaw)
        t = q - np.column_stack(
            [cs * rel[:, 0] - sn * rel[:, 1], sn * rel[:, 0] + cs * rel[:, 1], rel[:, 2]]
        )
        for shift in (0.0, 0.5):
            ijk = np.floor(t / cell + shift).astype(np.int64)
            lo = ijk.min(axis=0)
            span = ijk.max(axis=0) - lo + 1
            key = ((ijk[:, 0] - lo[0]) * span[1] + (ijk[:, 1] - lo[1])) * span[2] + (
                ijk[:, 2] - lo[2]
            )
            u, inv, n = np.unique(key, return_inverse=True, return_counts=True)
            for k in np.argsort(-n, kind="stable")[: c.fpfh_vote_cells]:
                if n[k] < 2:
                    break
                best_R.append(yaw)
                best_t.append(t[inv.ravel() == k].mean(axis=0))
                best_n.append(n[k])
    if not best_n:
        return []
    # ranked by their bins' counts over all matches: a pre-count on a subset holds too few right
    # ones and lost the pose among hundreds of chance bins
    order = np.argsort(-np.asarray(best_n), kind="stable")[:PRE_KEEP]
    R = _rz(np.asarray(best_R)[order])
    t = np.asarray(best_t)[order] - np.einsum("kij,j->ki", R, centre)
    return _best(R, t, p, q, c, four_dof=True, ranked=True)


def ransac_6dof(
    p: np.ndarray, q: np.ndarray, config: CoarseConfig, rng: np.random.Generator
) -> list[tuple[np.ndarray, int]]:
    """Poses (4x4, p -> q) from 3-correspondence samples (Kabsch), for when no vertical is trusted."""
    c = config
    if len(p) < 3:
        return []
    ijk = _sample_sets(len(p), 3, 2 * c.fpfh_draws, rng)
    ok = np.ones(len(ijk), bool)
    for a, b in ((0, 1), (0, 2), (1, 2)):  # edge lengths are kept by any rigid motion
        lp = np.linalg.norm(p[ijk[:, a]] - p[ijk[:, b]], axis=1)
        lq = np.linalg.norm(q[ijk[:, a]] - q[ijk[:, b]], axis=1)
        ok &= (np.abs(lp - lq) < c.fpfh_inlier_m) & (lp > 2 * c.fpfh_inlier_m)
    ijk = ijk[ok][: c.fpfh_iterations]
    if not len(ijk):
        return []
    P, Q = p[ijk], q[ijk]  # (K, 3, 3)
    cp, cq = P.mean(axis=1), Q.mean(axis=1)
    U, _, Vt = np.linalg.svd(np.einsum("kni,knj->kij", P - cp[:, None], Q - cq[:, None]))
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    d = np.sign(np.linalg.det(V @ Ut))
    V[:, :, 2] *= d[:, None]
    R = V @ Ut
    t = cq - np.einsum("kij,kj->ki", R, cp)
    return _best(R, t, p, q, c, four_dof=False)


def _best(
    R: np.ndarray,
    t: np.ndarray,
    p: np.ndarray,
    q: np.ndarray,
    c: CoarseConfig,
    four_dof: bool,
    ranked: bool = False,
) -> list[tuple[np.ndarray, int]]:
    """The `fpfh_hypotheses` best distinct sample poses, each re-fitted on its inliers (`ranked`: the
    poses come best first, counted already; else a first count on a subset of the matches ranks them)."""
    if not ranked:
        sub = np.linspace(0, len(p) - 1, min(len(p), PRE_COUNT)).astype(np.int64)
        pre = _count(R, t, p[sub], q[sub], c.fpfh_inlier_m)
        top = np.argsort(-pre, kind="stable")[:PRE_KEEP]
        R, t = R[top], t[top]
    counts = _count(R, t, p, q, c.fpfh_inlier_m)
    out: list[tuple[np.ndarray, int]] = []
    for k in np.argsort(-counts, kind="stable"):
        if counts[k] < c.fpfh_min_inliers or len(out) >= c.fpfh_hypotheses:
            break
        Rk, tk = R[k], t[k]
        for f in (
            2.0,
            1.5,
            1.0,
            1.0,
        ):  # re-fit on the inliers of a shrinking radius (a 3-point pose is rough)
            inl = ((rotate(p, Rk) + tk - q) ** 2).sum(axis=1) < (f * c.fpfh_inlier_m) ** 2
            if inl.sum() < 3:
                break
            Rk, tk = _rigid(p[inl], q[inl], four_dof)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rk, tk
        if all(not _close(T, o, c) for o, _ in out):
            out.append((T, int(counts[k])))
    return out


def _close(A: np.ndarray, B: np.ndarray, c: CoarseConfig) -> bool:
    D = np.linalg.inv(B) @ A
    deg = np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    return bool(np.linalg.norm(A[:3, 3] - B[:3, 3]) < c.distinct_m and deg < c.distinct_deg)

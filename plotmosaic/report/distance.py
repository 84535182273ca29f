"""Cloud-to-cloud distances of registered scans: each source point to the target's local surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.align.voxel import groups
from plotmosaic.config.report import DistanceConfig
from plotmosaic.parallel import inner_workers
from plotmosaic.report.slice import flat_keys


def thin(xyz: np.ndarray, voxel: float, cap: int, rng: np.random.Generator) -> np.ndarray:
    """One random point per `voxel` cube (not a centroid, which would smooth a surface), at most `cap`.

    The random point is the cube's first in a seeded permutation: the cube keys are computed once on
    the points as they are and permuted as integers, then one plain sort groups them."""
    if not len(xyz):
        return xyz
    perm = rng.permutation(len(xyz))
    ij = np.empty((len(xyz), 3), np.int64)
    for k in range(3):
        ij[:, k] = np.floor((xyz[:, k] - xyz[:, k].min()) / voxel)
    order, starts = groups(flat_keys(ij)[perm])
    idx = np.sort(perm[order[starts]])
    if len(idx) > cap:
        idx = np.sort(rng.choice(idx, cap, replace=False))
    return xyz[idx]


def spacing(tree: cKDTree, xyz: np.ndarray, k: int, sample: int = 2000) -> float:
    """Median distance from a point of the cloud to its k-th neighbour (over an even sample):
    how far the local plane's points reach in this cloud (an airborne cloud's is decimetres)."""
    if len(xyz) <= k:
        return 0.0
    d, _ = tree.query(xyz[:: max(1, len(xyz) // sample)], k=k + 1)
    return float(np.median(d[:, -1]))


def local_normals(nb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre, unit normal) of the plane through each row's neighbours (n, k, 3): the
    eigenvector of their scatter's smallest eigenvalue."""
    centre = nb.mean(axis=1)
    q = nb - centre[:, None, :]
    s = {
        (i, j): np.einsum("nk,nk->n", q[:, :, i], q[:, :, j]) for i in range(3) for j in range(i, 3)
    }
    return centre, _smallest_eigenvector(s)


def _smallest_eigenvector(s: dict) -> np.ndarray:
    """Per row of a symmetric 3 x 3 matrix given by its six entries s[(i, j)], i <= j: the
    smallest eigenvalue in closed form (the trigonometric solution of the characteristic cubic),
    its eigenvector as the longest cross product of two rows of (S - lambda I). A batched eigh
    pays a LAPACK call per matrix. Rows where that eigenvalue is (nearly) double, whose
    eigenvector the cross products do not fix, go to eigh."""
    a00, a11, a22, a01, a02, a12 = (s[k] for k in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)))
    mean = (a00 + a11 + a22) / 3
    b00, b11, b22 = a00 - mean, a11 - mean, a22 - mean
    p = np.sqrt((b00**2 + b11**2 + b22**2 + 2 * (a01**2 + a02**2 + a12**2)) / 6)
    det = b00 * (b11 * b22 - a12**2) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02)
    with np.errstate(invalid="ignore", divide="ignore"):
        half = np.clip(det / (2 * p**3), -1, 1)
    lam = mean + 2 * p * np.cos(np.arccos(np.nan_to_num(half)) / 3 + 2 * np.pi / 3)
    rows = (
        np.stack([a00 - lam, a01, a02], 1),
        np.stack([a01, a11 - lam, a12], 1),
        np.stack([a02, a12, a22 - lam], 1),
    )
    cross = np.stack(
        [np.cross(rows[0], rows[1]), np.cross(rows[0], rows[2]), np.cross(rows[1], rows[2])], 1
    )
    size = np.einsum("nki,nki->nk", cross, cross)
    pick = size.argmax(axis=1)
    best = cross[np.arange(len(cross)), pick]
    norm = np.sqrt(size[np.arange(len(cross)), pick])
    weak = norm <= 1e-9 * (3 * mean) ** 2
    out = best / np.where(weak, 1.0, norm)[:, None]
    if weak.any():
        full = np.empty((int(weak.sum()), 3, 3))
        for (i, j), v in s.items():
            full[:, i, j] = full[:, j, i] = v[weak]
        out[weak] = np.linalg.eigh(full)[1][:, :, 0]
    return out


@dataclass(frozen=True, eq=False)
class TargetIndex:
    """A target cloud's KD-tree and how far its local planes reach (built once per target)."""

    points: np.ndarray
    tree: cKDTree
    radius: float


def target_index(tgt: np.ndarray, cfg: DistanceConfig) -> TargetIndex:
    """The index edge_distances measures against: within `neighbourhood`, or the target's own
    spacing where it is sparser (an ALS tile)."""
    tree = cKDTree(tgt, balanced_tree=False, compact_nodes=False)  # builds faster, same answers
    reach = max(cfg.neighbourhood, cfg.spacing_factor * spacing(tree, tgt, cfg.neighbours))
    return TargetIndex(points=tgt, tree=tree, radius=reach)


def edge_distances(
    source: str,
    target: str,
    src: np.ndarray,
    index: TargetIndex,
    cfg: DistanceConfig,
    rng: np.random.Generator,
) -> dict:
    """Distance of each source point to the plane through its nearest target points, in the overlap.

    The overlap is where the target is dense around the source point (all `neighbours` within
    the index's reach): elsewhere a nearest-neighbour distance measures the other scan's point
    spacing (foliage, far ground), not the registration. The local plane (CloudCompare's C2C with a
    local model) takes the target's sampling out of the figure, so a few millimetres mean aligned.
    At most `cfg.sample` source points are measured, a seeded random subset: the overlap still holds
    thousands of them, whose median and 90 % stay within their sampling noise of all points'.
    """
    tgt, tree, radius = index.points, index.tree, index.radius
    if len(src) > cfg.sample:
        src = src[np.sort(rng.choice(len(src), cfg.sample, replace=False))]
    # split across the thread budget: the same answers
    _, idx = tree.query(src, k=cfg.neighbours, distance_upper_bound=radius, workers=inner_workers())
    ok = (idx < len(tgt)).all(axis=1)
    p = src[ok]
    centre, normal = local_normals(tgt[idx[ok]])
    d = np.abs(np.einsum("ni,ni->n", p - centre, normal))
    return {
        "source": source,
        "target": target,
        "distances": d,
        "points": p,
        "max_distance": 2 * cfg.colour_max,
        "median": float(np.median(d)) if len(d) else float("nan"),
        "p90": float(np.quantile(d, 0.9)) if len(d) else float("nan"),
        "share": float(ok.mean()) if len(ok) else 0.0,
    }


def scan_medians(edges: list[dict]) -> dict[str, float]:
    """Per scan, the median distance pooled over its kept edges (both ends of an edge share its distances)."""
    pooled: dict[str, list[np.ndarray]] = {}
    for e in edges:
        for s in (e["source"], e["target"]):
            pooled.setdefault(s, []).append(e["distances"])
    return {
        s: float(np.median(np.concatenate(v)))
        for s, v in sorted(pooled.items())
        if sum(map(len, v))
    }

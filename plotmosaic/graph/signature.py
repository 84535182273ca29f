"""Cheap per-scan signatures that rank which scans of a big plot overlap, before any registration.

Without positions and without an ALS tile (or for scans the ALS step could not place), a plot of N
scans would try N(N-1)/2 pairs. Instead each scan gets a stem map (trunk centres at breast height,
the coarse stage's own detector) and its rotation- and translation-invariant triangles: the sorted
side lengths of every stem triple with all sides in [`min_side_m`, `max_side_m`]. Two scans that see
the same trees share many such triangles; two that do not share only chance ones. All triangles of
all scans go into one KD-tree; each scan's triangles are looked up once, and the matches vote for
the scan that owns them (O(T log T) in the triangles, no loop over scan pairs). The score divides the
votes by what chance alone would give (votes expected from the two triangle counts), so a scan with
many stems does not win everything.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.align.levelling import rotate, vertical_hypotheses
from plotmosaic.align.normals import local_shape
from plotmosaic.align.rasters import height_above_ground
from plotmosaic.align.sampling import sample
from plotmosaic.align.stemmap import stem_map
from plotmosaic.align.voxel import voxel_centroids
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.config.scale import SignatureConfig
from plotmosaic.graph.prepared import PrepareJob, entry, load_points, run_prepare_job


@dataclass(frozen=True)
class Signature:
    stems: np.ndarray  # (S, 2) stem centres in the levelled scan frame
    diameters: np.ndarray  # (S,)
    triangles: np.ndarray  # (T, 3) sorted side lengths (m), rotation- and translation-invariant
    corners: np.ndarray  # (T, 3) stem indices opposite the shortest, middle and longest side


_EMPTY = (np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3), np.int64))


def stem_triangles(
    xy: np.ndarray, min_side: float, max_side: float, cap: int
) -> tuple[np.ndarray, np.ndarray]:
    """(sorted side lengths, corners) of the stem triples whose sides all lie in [min_side, max_side];
    at most `cap`, the most compact first (small triangles are the least hit by occlusion)."""
    xy = np.asarray(xy, dtype=np.float64)
    if len(xy) < 3:
        return _EMPTY[2], _EMPTY[3]
    pairs = cKDTree(xy).query_pairs(max_side, output_type="ndarray")
    d = np.linalg.norm(xy[pairs[:, 0]] - xy[pairs[:, 1]], axis=1) if len(pairs) else np.zeros(0)
    pairs = pairs[d >= min_side]
    if not len(pairs):
        return _EMPTY[2], _EMPTY[3]
    # triples i < j < k whose three sides are all kept: neighbour sets intersected (stems are few)
    nbrs: list[set[int]] = [set() for _ in range(len(xy))]
    for i, j in pairs.tolist():
        nbrs[i].add(j)
    tris = [(i, j, k) for i in range(len(xy)) for j in nbrs[i] for k in nbrs[i] & nbrs[j]]
    if not tris:
        return _EMPTY[2], _EMPTY[3]
    t = np.asarray(sorted(tris))
    # side opposite each corner: corner 0 <-> side (1, 2), ...
    opp = np.stack(
        [
            np.linalg.norm(xy[t[:, 1]] - xy[t[:, 2]], axis=1),
            np.linalg.norm(xy[t[:, 0]] - xy[t[:, 2]], axis=1),
            np.linalg.norm(xy[t[:, 0]] - xy[t[:, 1]], axis=1),
        ],
        axis=1,
    )
    order = np.argsort(opp, axis=1, kind="stable")
    sides = np.take_along_axis(opp, order, axis=1)
    corners = np.take_along_axis(t, order, axis=1)
    keep = np.sort(np.argsort(sides[:, 2], kind="stable")[:cap])
    return sides[keep], corners[keep]


def scan_signature(points: np.ndarray, config: SignatureConfig, seed: int = 0) -> Signature:
    """The signature of one scan from its points (any frame: the vertical is estimated as the coarse stage does)."""
    coarse = CoarseConfig()
    rng = np.random.default_rng(seed)
    pts = voxel_centroids(np.asarray(points, dtype=np.float64), config.voxel)
    pts = pts[sample(len(pts), config.max_points, rng)]
    if len(pts) < 50:
        return Signature(*_EMPTY)
    tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
    nrm = local_shape(pts, tree, pts, config.normal_radius, config.normal_neighbours)[0]
    few = sample(len(nrm), coarse.levelling_normals, rng)
    verticals, _ = vertical_hypotheses(pts[few], nrm[few], coarse, limit=1)
    R = verticals[0].R
    pts_l, nrm_l = rotate(pts, R), rotate(nrm, R)
    hag = height_above_ground(pts_l, coarse.feature_cell, coarse)
    stems = stem_map(pts_l, nrm_l, hag, coarse)
    sides, corners = stem_triangles(
        stems.xy, config.min_side_m, config.max_side_m, config.max_triangles
    )
    return Signature(stems.xy, stems.diameter, sides, corners)


def _rigid_2d(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rotations + shifts taking (M, 3, 2) corners `a` onto `b`; (yaw, t, rms)."""
    ca, cb = a.mean(axis=1, keepdims=True), b.mean(axis=1, keepdims=True)
    p, q = a - ca, b - cb
    dot = (p * q).sum(axis=(1, 2))
    cross = (p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]).sum(axis=1)
    yaw = np.arctan2(cross, dot)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (M, 2, 2)
    moved = np.einsum("mij,mkj->mki", rot, p)
    rms = np.sqrt(((moved - q) ** 2).sum(axis=2).mean(axis=1))
    t = cb[:, 0] - np.einsum("mij,mj->mi", rot, ca[:, 0])
    return yaw, t, rms


def _best_pose(
    yaw: np.ndarray, t: np.ndarray, src: np.ndarray, dst: np.ndarray, config: SignatureConfig
) -> tuple[int, float, np.ndarray]:
    """(stems matched, soft count, share of the stems inside the other map matched) under the
    triangle-match pose that the most other matches agree with."""
    # votes in (yaw, x, y) cells of the agreement size, on two grids half a cell apart (a cluster
    # cut by a cell border is whole in the other): O(m log m) in the triangle matches
    cells = np.column_stack(
        [np.mod(yaw, 2 * np.pi) / np.radians(config.agree_deg), t / config.agree_m]
    )
    best, k = -1, 0
    for shift in (0.0, 0.5):
        keys = np.floor(cells + shift).astype(np.int64)
        _, inverse, votes = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
        top = int(np.argmax(votes))
        if votes[top] > best:
            members = np.flatnonzero(inverse.ravel() == top)
            best, k = (
                int(votes[top]),
                int(members[np.argmin(np.abs(yaw[members] - np.median(yaw[members])))]),
            )
    c, s = np.cos(yaw[k]), np.sin(yaw[k])
    moved = src @ np.array([[c, -s], [s, c]]).T + t[k]
    d, _ = cKDTree(dst).query(moved, distance_upper_bound=config.footprint_m)
    inside = int(np.isfinite(d).sum())  # moved stems among the other scan's stems at all
    d = d[d <= config.stem_match_m]
    # a near stem counts more than a far one: chance matches scatter over the whole tolerance;
    # and a pose that matches few of the stems it brings into the other map is chance
    soft = float(np.sum(1.0 - (d / config.stem_match_m) ** 2))
    return len(d), soft, len(d) / max(inside, 1)


def similarity(
    signatures: list[Signature], config: SignatureConfig
) -> dict[tuple[int, int], float]:
    """(i, j) with i < j -> stems of scan i that land on stems of scan j under the best triangle pose.

    One KD-tree over every scan's triangles, one ball query per triangle (near-linear in the
    total); only scan pairs sharing triangles are looked at, and only pairs whose best pose matches
    at least `min_stems` stems are kept: chance triangle matches do not agree on one pose."""
    counts = np.array([len(s.triangles) for s in signatures])
    if counts.sum() == 0:
        return {}
    allt = np.concatenate([s.triangles for s in signatures if len(s.triangles)])
    corners = np.concatenate([s.corners for s in signatures if len(s.corners)])
    owner = np.repeat(np.arange(len(signatures)), counts)
    hits = cKDTree(allt).query_ball_point(allt, config.tolerance_m, workers=1)
    a = np.repeat(np.arange(len(allt)), [len(h) for h in hits])
    b = np.concatenate([np.asarray(h, dtype=np.int64) for h in hits])
    ok = owner[a] < owner[b]  # each match once, never within a scan
    a, b = a[ok], b[ok]
    if not len(a):
        return {}
    n = len(signatures)
    code = owner[a] * n + owner[b]
    order = np.argsort(code, kind="stable")
    a, b, code = a[order], b[order], code[order]
    groups, first = np.unique(code, return_index=True)
    bounds = np.append(first, len(code))
    votes = np.diff(bounds)
    # only each scan's `shortlist` scans with the most shared triangles (over chance: the geometric
    # mean of the two triangle counts) get the pose check: O(N shortlist), not one per voted pair
    gi, gj = np.divmod(groups, n)
    rate = votes / np.sqrt(np.maximum(counts[gi], 1) * np.maximum(counts[gj], 1))
    keep = np.zeros(len(groups), bool)
    for side in (gi, gj):
        order = np.lexsort((-rate, side))  # by scan, best rate first
        rank = np.arange(len(order)) - np.searchsorted(side[order], side[order])
        keep[order[rank < config.shortlist]] = True
    out = {}
    for g, lo, hi, kept in zip(
        groups.tolist(), bounds[:-1].tolist(), bounds[1:].tolist(), keep.tolist()
    ):
        if hi - lo < config.min_votes or not kept:
            continue
        i, j = divmod(g, n)
        ga, gb = a[lo:hi][: config.max_matches], b[lo:hi][: config.max_matches]
        pa = signatures[i].stems[corners[ga]]
        pb = signatures[j].stems[corners[gb]]
        yaw, t, rms = _rigid_2d(pa, pb)
        good = rms <= config.tolerance_m
        if good.sum() < config.min_votes:
            continue
        matched, soft, share = _best_pose(
            yaw[good], t[good], signatures[i].stems, signatures[j].stems, config
        )
        if matched >= config.min_stems and share >= config.min_share:
            out[(i, j)] = soft * share
    return out


def ranked_partners(scores: dict[tuple[int, int], float], n: int) -> list[list[int]]:
    """Per scan, the other scans by decreasing score (only those with a vote), ties by index."""
    lists: list[list[tuple[float, int]]] = [[] for _ in range(n)]
    for (i, j), s in scores.items():
        lists[i].append((-s, j))
        lists[j].append((-s, i))
    return [[j for _, j in sorted(row)] for row in lists]


def signature_pairs(
    scores: dict[tuple[int, int], float], n: int, partners: int, max_per_scan: int
) -> list[tuple[int, int]]:
    """Index pairs (i < j): each scan with its `partners` best-scored scans (at most `max_per_scan`
    pairs a scan), then the best-scored links that join what is still apart. Linear in the scans
    (at most `partners` + joins per scan); a scan no signature links stays alone (the caller pairs it
    otherwise)."""
    ranks = ranked_partners(scores, n)
    degree = np.zeros(n, dtype=int)
    chosen: set[tuple[int, int]] = set()
    parent = list(range(n))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def add(i: int, j: int) -> None:
        chosen.add((min(i, j), max(i, j)))
        degree[i] += 1
        degree[j] += 1
        parent[max(find(i), find(j))] = min(find(i), find(j))

    for depth in range(partners):  # round-robin: every scan gets its best before any its 2nd
        for i in range(n):
            if depth < len(ranks[i]):
                j = ranks[i][depth]
                if (min(i, j), max(i, j)) not in chosen and max(
                    degree[i], degree[j]
                ) < max_per_scan:
                    add(i, j)
    for (i, j), _ in sorted(scores.items(), key=lambda e: (-e[1], e[0])):  # maximum spanning joins
        if find(i) != find(j) and max(degree[i], degree[j]) < max_per_scan + 1:
            add(i, j)
    return sorted(chosen)


def grow_candidates(
    ranks: dict[str, list[str]],
    tried: set[frozenset],
    components: list[set[str]],
    degree: dict[str, int],
    per_scan: int,
    max_per_scan: int,
) -> list[tuple[str, str]]:
    """More pairs where the verified graph is still apart: scans outside the largest component, each
    with its next `per_scan` ranked partners not tried yet (ranked partners in another component
    first), at most `max_per_scan` pairs a scan in all."""
    if len(components) < 2:
        return []
    comps = sorted(components, key=lambda c: (-len(c), sorted(c)))
    where = {s: k for k, c in enumerate(comps) for s in c}
    out: list[tuple[str, str]] = []
    degree = dict(degree)
    for comp in comps[1:]:
        for s in sorted(comp):
            fresh = [
                p
                for p in ranks.get(s, [])
                if p in where and frozenset((s, p)) not in tried and where[p] != where[s]
            ]
            for p in fresh[:per_scan]:
                if degree.get(s, 0) >= max_per_scan or degree.get(p, 0) >= max_per_scan:
                    continue
                out.append((s, p))
                tried = tried | {frozenset((s, p))}
                degree[s] = degree.get(s, 0) + 1
                degree[p] = degree.get(p, 0) + 1
    return out


@dataclass(frozen=True)
class SignatureJob(PrepareJob):
    """One scan's signature, from its prepared cloud (prepared here when not cached yet): a prepare
    job with the signature settings, so every executor handles it as one."""

    signature: SignatureConfig = field(default_factory=SignatureConfig)

    @classmethod
    def of(cls, prepare: PrepareJob, signature: SignatureConfig) -> SignatureJob:
        return cls(**_fields(prepare), signature=signature)

    @property
    def prepare(self) -> PrepareJob:
        return PrepareJob(**_fields(self))


def _fields(job: PrepareJob) -> dict:
    return {f.name: getattr(job, f.name) for f in fields(PrepareJob)}


def run_signature_job(job: SignatureJob) -> dict:
    """Worker: prepare the scan if needed (the same cache entry its pairs load), then its signature."""
    record = run_prepare_job(job.prepare)
    record.update(kind="signature", scan=job.prepare.scan)
    if record["status"] != "ok":
        return record
    try:
        config = job.signature
        points = load_points(entry(job.prepare.folder, job.prepare.key))
        sig = scan_signature(points - points.mean(axis=0), config, job.prepare.seed)
        record.update(
            stems=sig.stems.tolist(),
            diameters=sig.diameters.tolist(),
            sides=sig.triangles.tolist(),
            corners=sig.corners.tolist(),
        )
    except Exception as exc:  # a scan without stems is no error: it is paired otherwise
        record.update(status="failed", error=f"{type(exc).__name__}: {exc}")
    return record


def from_record(record: dict) -> Signature:
    if record.get("status") != "ok":
        return Signature(*_EMPTY)
    return Signature(
        np.asarray(record["stems"], dtype=np.float64).reshape(-1, 2),
        np.asarray(record["diameters"], dtype=np.float64),
        np.asarray(record["sides"], dtype=np.float64).reshape(-1, 3),
        np.asarray(record["corners"], dtype=np.int64).reshape(-1, 3),
    )

"""Candidate pairs within a plot: all pairs of a small plot, neighbours only in a big one.

A small plot (at most `all_pairs_up_to` scans) tries every pair, or with approximate positions every
pair whose scanners stood at most `max_distance` apart. A bigger plot with positions (from the
manifest or from placing each scan on the ALS) registers each scan with its nearest neighbours
only: at most `max_per_scan` pairs a scan, so the pairs grow linearly with the scans, and the
graph is kept connected (loops come from the neighbours: each scan has several). A scan without a
position is paired with the scans its signature matches (graph/signature.py), else with its
neighbours in the manifest's order (the order of acquisition). Positions known to centimetres (ALS
placements, or the pose graph of verified pairs) pair scans at most `reach` times the plot's scan
spacing apart: farther pairs share too little to verify, and each costs a full search.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import combinations

import numpy as np
from scipy.spatial import cKDTree

from plotmosaic.config.register import PairSelection
from plotmosaic.manifest import Plot, Scan


def manifest_positions(plot: Plot) -> dict[str, np.ndarray] | None:
    """Approximate positions of every scan, when all are given in one frame; else None."""
    frames = {s.approx_position_frame for s in plot.scans}
    if len(frames) != 1 or any(s.approx_position is None for s in plot.scans):
        return None
    return {s.id: np.asarray(s.approx_position, dtype=np.float64) for s in plot.scans}


class _Components:
    def __init__(self, n: int):
        self.parent = list(range(n))

    def find(self, i: int) -> int:
        while self.parent[i] != i:
            self.parent[i] = self.parent[self.parent[i]]
            i = self.parent[i]
        return i

    def join(self, i: int, j: int) -> bool:
        a, b = self.find(i), self.find(j)
        if a == b:
            return False
        self.parent[max(a, b)] = min(a, b)
        return True


def scan_spacing(xy: np.ndarray) -> float:
    """The plot's scan spacing: the median distance (m, in plan) from a scan to its nearest other scan."""
    xy = np.asarray(xy, dtype=np.float64)[:, :2]
    if len(xy) < 2:
        return float("inf")
    d, _ = cKDTree(xy).query(xy, k=2)
    return float(np.median(d[:, 1]))


def reach_distance(xy: np.ndarray, reach: float | None, max_distance: float | None) -> float | None:
    """The farthest pair to plan between scans at these exact positions: `reach` x their spacing,
    never beyond `max_distance`."""
    if reach is None:
        return max_distance
    d = reach * scan_spacing(xy)
    return d if max_distance is None else min(d, max_distance)


def neighbour_pairs(
    xy: np.ndarray, neighbours: int = 6, max_per_scan: int = 8, max_distance: float | None = None
) -> list[tuple[int, int]]:
    """Index pairs (i < j): each point's nearest neighbours, shortest first, at most `max_per_scan` per point,
    then the shortest links that join what is still apart. O(N log N) with a KD-tree."""
    xy = np.asarray(xy, dtype=np.float64)[:, :2]
    n = len(xy)
    if n < 2:
        return []
    tree = cKDTree(xy)
    k = min(n, neighbours + 1)
    dist, idx = tree.query(xy, k=k)
    candidates = sorted(
        {
            (float(d), min(i, int(j)), max(i, int(j)))
            for i in range(n)
            for d, j in zip(dist[i, 1:], idx[i, 1:])
            if max_distance is None or d <= max_distance
        }
    )
    degree = np.zeros(n, dtype=int)
    chosen: set[tuple[int, int]] = set()
    comps = _Components(n)
    for _, i, j in candidates:
        if degree[i] < max_per_scan and degree[j] < max_per_scan:
            chosen.add((i, j))
            degree[i] += 1
            degree[j] += 1
            comps.join(i, j)
    # what the caps (or max_distance) left apart: join components by their closest scans
    while True:
        roots = np.array([comps.find(i) for i in range(n)])
        groups = np.unique(roots)
        if len(groups) == 1:
            break
        best = None
        members = np.flatnonzero(
            roots == groups[0]
        )  # the first component to its nearest other scan
        others = np.flatnonzero(roots != groups[0])
        d, j = cKDTree(xy[others]).query(xy[members], k=1)
        m = int(np.argmin(d))
        best = (int(members[m]), int(others[j[m]]))
        if max_distance is not None and d[m] > max_distance:
            break  # truly apart (another plot, a wrong position): the pose graph reports them unplaced
        i, j2 = min(best), max(best)
        chosen.add((i, j2))
        comps.join(i, j2)
    return sorted(chosen)


def spanning_first(
    pairs: Sequence[tuple[str, str]], joined: Sequence[tuple[str, str]] = ()
) -> list[int]:
    """Indices of `pairs` (scan ids) forming a spanning forest, taken in the order given (Kruskal):
    each joins two scans not yet joined by an earlier one or by `joined`."""
    ids = sorted({i for pair in (*pairs, *joined) for i in pair})
    index = {i: k for k, i in enumerate(ids)}
    comps = _Components(len(ids))
    for a, b in joined:
        comps.join(index[a], index[b])
    return [k for k, (a, b) in enumerate(pairs) if comps.join(index[a], index[b])]


def candidate_pairs(
    plot: Plot,
    max_distance: float | None = None,
    positions: dict[str, np.ndarray] | None = None,
    selection: PairSelection | None = None,
    linked: list[tuple[str, str]] | None = None,
    reach: float | None = None,
) -> list[tuple[Scan, Scan]]:
    """(source, target) pairs; the later scan in the manifest is the source.

    `positions`: scan id -> position in one frame (default: the manifest's approximate positions).
    `linked`: pairs of scans whose signatures match (graph/signature.py): in a big plot they pair
    the scans that have no position. `reach`: `positions` are exact (ALS placements): a big plot's
    placed scans are paired at most `reach` x their spacing apart (reach_distance).
    """
    selection = selection or PairSelection()
    scans = plot.scans
    positions = positions if positions is not None else manifest_positions(plot)
    placed = [s for s in scans if positions is not None and s.id in positions]
    if len(scans) > selection.all_pairs_up_to and (len(placed) >= 3 or linked is not None):
        return _big_plot_pairs(plot, positions, selection, linked, max_distance, reach)
    known = positions is not None and len(placed) == len(scans)
    pairs = []
    for target, source in combinations(scans, 2):
        if known and max_distance is not None:
            d = np.linalg.norm(np.subtract(positions[source.id], positions[target.id])[:2])
            if d > max_distance:
                continue
        pairs.append((source, target))
    return pairs


def _big_plot_pairs(
    plot: Plot,
    positions: dict[str, np.ndarray] | None,
    selection: PairSelection,
    linked: list[tuple[str, str]] | None,
    max_distance: float | None,
    reach: float | None,
) -> list[tuple[Scan, Scan]]:
    """A big plot's pairs: placed scans with their neighbours, the others by signature or by
    their neighbours in the manifest."""
    scans = plot.scans
    placed = [s for s in scans if positions is not None and s.id in positions]
    order = {s.id: k for k, s in enumerate(scans)}
    chosen: set[tuple[str, str]] = set()
    if len(placed) >= 3:
        xy = np.array([positions[s.id][:2] for s in placed])
        far = reach_distance(xy, reach, max_distance)
        chosen = {
            (placed[i].id, placed[j].id)
            for i, j in neighbour_pairs(xy, selection.neighbours, selection.max_per_scan, far)
        }
    else:
        placed = []
    has_position = {s.id for s in placed}
    degree = {s.id: 0 for s in scans}
    for a, b in chosen:
        degree[a] += 1
        degree[b] += 1
    matched = _signature_links(linked or [], has_position, order, chosen, degree, selection)
    _list_neighbours(scans, has_position | matched, chosen, degree, selection)
    by_id = {s.id: s for s in scans}
    return [
        (by_id[j], by_id[i])
        for i, j in sorted(chosen, key=lambda e: (order[e[0]], order[e[1]]))
        if order[i] < order[j]
    ]


def _signature_links(
    linked: list[tuple[str, str]],
    has_position: set[str],
    order: dict[str, int],
    chosen: set[tuple[str, str]],
    degree: dict[str, int],
    selection: PairSelection,
) -> set[str]:
    """No position: the scans its signature matches, best first (added to `chosen`); the scans matched."""
    matched: set[str] = set()
    for a, b in linked:
        if a in has_position and b in has_position:
            continue
        pair = (a, b) if order[a] < order[b] else (b, a)
        if (
            a in order
            and b in order
            and pair not in chosen
            and max(degree[a], degree[b]) < selection.max_per_scan
        ):
            chosen.add(pair)
            degree[a] += 1
            degree[b] += 1
            matched.update(pair)
    return matched


def _list_neighbours(
    scans: list[Scan],
    paired: set[str],
    chosen: set[tuple[str, str]],
    degree: dict[str, int],
    selection: PairSelection,
) -> None:
    """Scans not in `paired`: their neighbours in the manifest, which lists scans as they were taken
    (a walk through the plot), so pairs stay bounded; an unconfirmed scan is reported unplaced."""
    span = min(len(scans), selection.max_per_scan + 1)  # not beyond the scans taken around it
    for k, s in enumerate(scans):
        if s.id in paired:
            continue
        near = (m for d in range(1, span) for m in (k - d, k + d) if 0 <= m < len(scans))
        for m in near:  # nearest in the list first
            if degree[s.id] >= selection.max_per_scan:
                break
            a, b = sorted((k, m))
            pair = (scans[a].id, scans[b].id)
            if m != k and pair not in chosen and degree[scans[m].id] < selection.max_per_scan:
                chosen.add(pair)
                degree[s.id] += 1
                degree[scans[m].id] += 1

"""The pose graph's initialisation and cycle consistency: the kept edges' strongest spanning tree
chained into poses, and the vote on triangles that finds a wrong edge before any solve (one that
is inconsistent in most triangles it closes), and the low-confidence edges no consistent triangle
confirms (graph/posegraph.py solves what they leave)."""

from __future__ import annotations

import networkx as nx
import numpy as np

from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.io.frame import inverse, rotation_deg


def edge_transform(G: nx.Graph, a: str, b: str) -> np.ndarray:
    """The measured X_a^-1 X_b (maps b's coordinates into a's) from the edge between a and b."""
    e = G.edges[a, b]
    T = e["transform"]
    return T if (e["source"], e["target"]) == (b, a) else inverse(T)


def kept(G: nx.Graph) -> nx.Graph:
    """View of the edges still in use."""
    return nx.subgraph_view(G, filter_edge=lambda u, v: not G.edges[u, v].get("dropped", False))


def spanning_tree_poses(G: nx.Graph, reference: str) -> dict[str, np.ndarray]:
    """Poses of every scan connected to `reference` by chaining the strongest edges (max spanning tree)."""
    H = kept(G)
    component = nx.node_connected_component(H, reference)
    tree = nx.maximum_spanning_tree(H.subgraph(component), weight="weight")
    poses = {reference: np.eye(4)}
    for u, v in nx.bfs_edges(tree, reference):
        poses[v] = poses[u] @ edge_transform(G, u, v)
    return poses


def triangles(H: nx.Graph) -> list[tuple[str, str, str]]:
    """Every triangle of `H` once, by neighbour-set intersection: O(edges x degree), not all cliques."""
    order = {n: k for k, n in enumerate(sorted(H.nodes))}
    higher = {n: {m for m in H.adj[n] if order[m] > order[n]} for n in H.nodes}
    out = []
    for a in sorted(H.nodes):
        for b in sorted(higher[a], key=order.get):
            for c in sorted(higher[a] & higher[b], key=order.get):
                out.append((a, b, c))
    return out


def cycle_errors(G: nx.Graph) -> list[dict]:
    """Every triangle of kept edges with how far composing its three edges is from identity."""
    out = []
    for a, b, c in triangles(kept(G)):
        loop = edge_transform(G, a, b) @ edge_transform(G, b, c) @ edge_transform(G, c, a)
        out.append(
            {
                "nodes": (a, b, c),
                "rotation_deg": rotation_deg(loop),
                "translation": float(np.linalg.norm(loop[:3, 3])),
            }
        )
    return out


def _edge_id(u: str, v: str) -> tuple[str, str]:
    return (u, v) if u <= v else (v, u)


def _tri_edges(tri: dict) -> tuple[tuple[str, str], ...]:
    a, b, c = tri["nodes"]
    return _edge_id(a, b), _edge_id(b, c), _edge_id(a, c)


def _inconsistent(tri: dict, config: PoseGraphConfig) -> bool:
    return (
        tri["rotation_deg"] > config.cycle_rotation_deg
        or tri["translation"] > config.cycle_translation
    )


def _count(tris: list[dict], config: PoseGraphConfig) -> dict[tuple[str, str], tuple[int, int]]:
    votes: dict[tuple[str, str], list[int]] = {}
    for tri in tris:
        wrong = _inconsistent(tri, config)
        for e in _tri_edges(tri):
            n = votes.setdefault(e, [0, 0])
            n[0] += int(wrong)
            n[1] += 1
    return {e: (bad, total) for e, (bad, total) in votes.items()}


def _outliers(votes: dict[tuple[str, str], tuple[int, int]]) -> list[tuple[str, str]]:
    return sorted(e for e, (bad, total) in votes.items() if bad >= 2 and bad > total / 2)


def _explain(tris: list[dict], config: PoseGraphConfig) -> list[tuple[str, str]]:
    """Outliers of the vote, the most certain first: a bad triangle blamed on one edge no longer counts
    against its two other edges (else a good edge next to two wrong ones is dropped with them)."""
    out: list[tuple[str, str]] = []
    active = tris
    while True:
        votes = _count(active, config)
        candidates = _outliers(votes)
        if not candidates:
            return sorted(out)
        top = max(votes[e][0] / votes[e][1] for e in candidates)
        worst = {e for e in candidates if votes[e][0] / votes[e][1] == top}
        out += sorted(worst)
        active = [t for t in active if not worst.intersection(_tri_edges(t))]


def _unsure(G: nx.Graph, config: PoseGraphConfig) -> set[tuple[str, str]]:
    return {
        _edge_id(u, v)
        for u, v, e in kept(G).edges(data=True)
        if e.get("confidence") is not None and e["confidence"] < config.sure_edge_confidence
    }


def _unconfirmed(unsure: set, votes: dict) -> list[tuple[str, str]]:
    return sorted(e for e in unsure if (lambda bt: bt[1] - bt[0])(votes.get(e, (0, 0))) == 0)


def vote(
    G: nx.Graph, config: PoseGraphConfig
) -> tuple[list[tuple[str, str]], list[tuple[str, str]]]:
    """(cycle outliers, unverified unsure edges) from one pass over the triangles of the kept edges.

    Low-confidence edges stay out of the outlier vote: otherwise a plot with several wrong (and
    unsure) pairs outvotes its correct edges. An unsure edge is confirmed by a consistent triangle
    whose other edges are not cycle outliers.
    """
    tris = cycle_errors(G)
    unsure = _unsure(G, config)
    trusted = [t for t in tris if not unsure.intersection(_tri_edges(t))]
    gone = set(_explain(trusted, config))
    outliers = sorted(gone)
    rest = _count([t for t in tris if not gone.intersection(_tri_edges(t))], config)
    return outliers, _unconfirmed(unsure, rest)

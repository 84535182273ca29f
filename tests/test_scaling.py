"""Issue 16: nothing in register-plot grows faster than the work (pose graph, pair selection)."""

import time

import networkx as nx
import numpy as np

from plotmosaic.graph.posegraph import _edge_id, build_graph, optimise, pose_error, triangles
from plotmosaic.graph.synthetic import grid_graph
from tests.test_graph_posegraph import synthetic_plot


def test_triangles_are_networkx_triangles():
    G = nx.gnp_random_graph(40, 0.3, seed=1)
    G = nx.relabel_nodes(G, {n: f"n{n:02d}" for n in G})
    ours = {frozenset(t) for t in triangles(G)}
    assert len(ours) == len(triangles(G)) == sum(nx.triangles(G).values()) // 3
    assert ours == {frozenset(c) for c in nx.enumerate_all_cliques(G) if len(c) == 3}


def test_complete_graph_of_30_scans_optimises_in_seconds():
    # all pairs of 30 scans: the clique enumeration took about a day here
    truth, nodes, edges = synthetic_plot(30, seed=3, outlier=("s7", "s2"))
    G = build_graph(nodes, edges)
    start = time.perf_counter()
    sol = optimise(G, "s0")
    assert time.perf_counter() - start < 10
    assert [(d["source"], d["target"]) for d in sol.dropped] == [("s7", "s2")]
    for name, T in truth.items():
        dt, dr = pose_error(sol.poses[name], T)
        assert dt < 0.01 and dr < 0.01


def test_grid_of_150_scans_with_wrong_edges_drops_every_wrong_edge():
    truth, nodes, edges, wrong = grid_graph(150, wrong_share=0.05, seed=4)
    G = build_graph(nodes, edges)
    start = time.perf_counter()
    sol = optimise(G, "s0000")
    assert time.perf_counter() - start < 10
    dropped = {_edge_id(d["source"], d["target"]) for d in sol.dropped}
    assert len(wrong) >= 20 and {_edge_id(*e) for e in wrong} <= dropped
    assert not sol.unplaced and set(sol.sigmas) == set(truth)
    assert max(pose_error(sol.poses[k], truth[k])[0] for k in truth) < 0.02
    assert np.isfinite(np.concatenate(list(sol.sigmas.values()))).all()

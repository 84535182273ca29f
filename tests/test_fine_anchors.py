"""ALS placements as anchors of a plot's pose graph (graph/pipeline.solve_plot): a chain of scan pairs
that each come out a little short drifts; unbiased placements on the ALS hold its far end."""

from __future__ import annotations

import networkx as nx
import numpy as np

from plotmosaic.config.align import AlignConfig
from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.jobs import PairJob
from plotmosaic.graph.posegraph import build_graph
from plotmosaic.io.frame import inverse, translation
from plotmosaic.manifest import Plot, Scan
from plotmosaic.stages.register_plot import als_anchor_edges, anchor_id, solve_plot

N, SPACING, SHORT = 7, 18.0, 0.01  # scans in a row 18 m apart, each pair 1 cm short
UTM = np.array([470_000.0, 3_810_000.0, 2_100.0])
INFO = np.diag([1e7] * 3 + [1e4] * 3)  # ~0.02 deg, 1 cm


def _case(rng: np.random.Generator):
    names = [f"S{k}" for k in range(N)]
    truth = {n: translation([k * SPACING, 0.0, 0.0]) for k, n in enumerate(names)}  # in S0's frame
    edges = []
    for a, b in zip(names[1:], names[:-1], strict=True):
        T = inverse(truth[b]) @ truth[a]
        T[0, 3] -= SHORT  # the source scanner pulled toward the target one
        edges.append({"source": a, "target": b, "transform": T, "information": INFO, "fitness": 0.5,
                      "overlap": 0.4, "confidence": 0.9, "status": "ok"})  # fmt: skip
    # the last scan has no scan-to-scan pair at all: only its placement can place it
    edges = [e for e in edges if names[-1] not in (e["source"], e["target"])]
    plot = Plot(id="P1", scans=[Scan(id=n, path=f"{n}.laz", reference=n == "S0") for n in names])
    jobs, records = [], {}
    for n in names:
        key = f"place-{n}"
        jobs.append(
            PairJob(key, n, "ALS", f"{n}.laz", "als.laz", "tls", "als", 3, 2, AlignConfig(), 0)
        )
        T = translation(UTM + rng.normal(0, 0.003, 3)) @ truth[n]  # unbiased, 3 mm noise
        records[key] = {"status": "ok", "transform": T.tolist(), "information": INFO.tolist(),
                        "fitness": 0.3, "overlap": 0.2, "confidence": 0.8}  # fmt: skip
    G = build_graph({n: {"kind": "tls"} for n in names}, edges)
    return plot, G, jobs, records, truth


def _worst_cm(sol, truth) -> float:
    return max(100 * np.linalg.norm(sol.poses[n][:3, 3] - truth[n][:3, 3]) for n in sol.poses)


def test_anchors_hold_a_drifting_chain_and_place_a_scan_without_pairs():
    plot, G, jobs, records, truth = _case(np.random.default_rng(0))
    cfg = RegisterConfig()
    ref, plain = solve_plot(G, plot, [], cfg)
    assert ref == "S0" and plain.unplaced == ["S6"]
    assert _worst_cm(plain, truth) > 4.5  # five short pairs: 5 cm
    anchors = als_anchor_edges(plot, jobs, records, {j.source for j in jobs})
    assert len(anchors) == N and all(e["target"] == anchor_id(plot) for e in anchors)
    # the local ALS frame: translations of tens of metres, not UTM's millions
    assert max(np.abs(np.asarray(e["transform"])[:3, 3]).max() for e in anchors) < 100
    ref, sol = solve_plot(G, plot, anchors, cfg)
    assert anchor_id(plot) not in sol.poses and anchor_id(plot) not in sol.sigmas
    assert sol.unplaced == [] and set(sol.poses) == set(truth)
    assert _worst_cm(sol, truth) < 0.5 * _worst_cm(plain, truth)
    # what the solve marks on the scan edges is on the plot's own graph, the ALS node is not
    assert anchor_id(plot) not in G
    assert all(e.get("residual_after") is not None for _, _, e in G.edges(data=True))
    # the placements' noise is scaled on their own residuals, apart from the pairs'
    factors = G.graph["calibration"]["P1"]
    als = factors["als-tls/translation"]
    assert als["redundancy"] + factors["als-tls/rotation"]["redundancy"] > 6, factors
    pairs = factors["tls-tls/translation"]
    # its own estimate from its own residuals (the factors themselves may meet at the floor)
    assert als["redundancy"] != pairs["redundancy"], factors


def test_only_kept_placements_become_anchors():
    plot, G, jobs, records, _ = _case(np.random.default_rng(1))
    anchors = als_anchor_edges(plot, jobs, records, {"S0", "S3"})
    assert sorted(e["source"] for e in anchors) == ["S0", "S3"]
    assert als_anchor_edges(plot, jobs, records, set()) == []
    assert isinstance(G, nx.Graph)

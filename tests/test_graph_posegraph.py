"""The pose graph on synthetic edges: recovery, outlier rejection, disconnected scans, JSON round trip,
sigmas calibrated on the residuals."""

import gtsam
import numpy as np
import pytest
from builders import random_pose, synthetic_pose_graph

from plotmosaic.bench.synthetic import grid_graph
from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.graph.covariance import REPORT_FLOOR
from plotmosaic.graph.cycles import vote
from plotmosaic.graph.posegraph import (
    build_graph,
    condition_information,
    graph_from_json,
    graph_to_json,
    inverse,
    optimise,
    pose_error,
)


def test_recovers_poses_with_small_noise():
    truth, nodes, edges = synthetic_pose_graph()
    G = build_graph(nodes, edges)
    sol = optimise(G, "s0")
    assert sol.unplaced == [] and sol.dropped == []
    for name, T in truth.items():
        r, t = pose_error(sol.poses[name], T)
        assert r < 0.01 and t < 0.001, (name, r, t)
        assert sol.sigmas[name].shape == (6,) and np.isfinite(sol.sigmas[name]).all()
    assert np.all(sol.sigmas["s0"] < 1e-5)  # the reference is fixed
    assert sol.error_after <= sol.error_before + 1e-9


@pytest.mark.parametrize("outlier", [("s3", "s1"), ("s1", "s0")])
def test_wrong_edge_is_dropped(outlier):
    truth, nodes, edges = synthetic_pose_graph(outlier=outlier, seed=1)
    G = build_graph(nodes, edges)
    # no edge is unsure here: the cycle outliers are the vote's whole answer
    assert vote(G, PoseGraphConfig()) == ([tuple(sorted(outlier))], [])
    sol = optimise(G, "s0")
    assert [(d["source"], d["target"]) for d in sol.dropped] == [outlier]
    assert G.edges[outlier]["dropped"] and G.edges[outlier]["residual_after"]["translation"] > 1.5
    for name, T in truth.items():
        r, t = pose_error(sol.poses[name], T)
        assert r < 0.01 and t < 0.001, (name, r, t)


def test_wrong_edge_found_by_residual_when_cycle_check_is_off():
    truth, nodes, edges = synthetic_pose_graph(outlier=("s4", "s2"), seed=2)
    G = build_graph(nodes, edges)
    config = PoseGraphConfig(
        cycle_translation=1e9, cycle_rotation_deg=1e9
    )  # only the residual test
    sol = optimise(G, "s0", config)
    assert [(d["source"], d["target"], d["reason"]) for d in sol.dropped] == [
        ("s4", "s2", "residual")
    ]
    for name, T in truth.items():
        r, t = pose_error(sol.poses[name], T)
        assert r < 0.01 and t < 0.002, (name, r, t)


def test_disconnected_scan_reported_others_placed():
    truth, nodes, edges = synthetic_pose_graph(n_scans=5, seed=3)
    nodes["lonely"] = {"kind": "tls", "plot": "P1"}
    edges.append({"source": "lonely", "target": "s0", "status": "failed", "error": "no overlap"})
    G = build_graph(nodes, edges)
    sol = optimise(G, "s0")
    assert sol.unplaced == ["lonely"]
    assert G.graph["failed"][0]["source"] == "lonely"
    for name, T in truth.items():
        r, t = pose_error(sol.poses[name], T)
        assert r < 0.01 and t < 0.001


def test_all_edges_of_a_scan_dropped_makes_it_unplaced():
    # s4 has only one edge, and it is wrong in a way no cycle can show; dropping it leaves s4 alone
    truth, nodes, edges = synthetic_pose_graph(n_scans=4, seed=4)
    T = inverse(truth["s0"]) @ random_pose(np.random.default_rng(9))
    nodes["s4"] = {"kind": "tls", "plot": "P1"}
    G = build_graph(
        nodes,
        edges + [{"source": "s4", "target": "s0", "transform": T, "fitness": 0.1, "overlap": 0.1}],
    )
    G.edges["s4", "s0"]["dropped"] = True
    sol = optimise(G, "s0")
    assert sol.unplaced == ["s4"] and set(sol.poses) == {"s0", "s1", "s2", "s3"}


def test_information_conditioning_floors_sigmas():
    config = PoseGraphConfig()
    info = condition_information(np.diag([1e12] * 3 + [1e10] * 3), 0.01, config)
    sig = np.sqrt(np.diag(np.linalg.inv(info)))
    assert np.allclose(sig[:3], np.radians(config.min_sigma_rotation_deg)) and np.allclose(
        sig[3:], config.min_sigma_translation
    )
    degenerate = np.diag([1e6, 1e6, 1e6, 1e6, 1e6, 0.0])  # e.g. no constraint along z
    sig = np.sqrt(np.diag(np.linalg.inv(condition_information(degenerate, 0.01, config))))
    assert np.isfinite(sig).all() and sig[5] > 10 * sig[3]
    fallback = condition_information(None, 0.03, config)
    assert np.isclose(np.sqrt(1 / fallback[3, 3]), 0.03)


def test_graph_json_round_trip():
    _, nodes, edges = synthetic_pose_graph(n_scans=3)
    G = build_graph(nodes, edges)
    optimise(G, "s0")
    import json

    H = graph_from_json(json.loads(json.dumps(graph_to_json(G))))
    assert set(H.nodes) == set(G.nodes) and H.number_of_edges() == 3
    for u, v in G.edges:
        assert np.allclose(H.edges[u, v]["transform"], G.edges[u, v]["transform"])
        assert (H.edges[u, v]["source"], H.edges[u, v]["target"]) == (
            G.edges[u, v]["source"],
            G.edges[u, v]["target"],
        )
        assert H.edges[u, v]["residual_after"]["chi2"] == pytest.approx(
            G.edges[u, v]["residual_after"]["chi2"]
        )


def test_unconfirmed_low_confidence_bridge_is_dropped():
    # s4 hangs on one edge whose coarse stage was unsure: nothing confirms it, so s4 is not placed
    truth, nodes, edges = synthetic_pose_graph(n_scans=4, seed=5)
    nodes["s4"] = {"kind": "tls", "plot": "P1"}
    wrong = inverse(truth["s0"]) @ random_pose(np.random.default_rng(7))
    edges.append(
        {
            "source": "s4",
            "target": "s0",
            "transform": wrong,
            "fitness": 0.4,
            "overlap": 0.3,
            "confidence": 0.05,
        }
    )
    for e in edges[:-1]:
        e["confidence"] = 0.05  # low too, but every one of them closes consistent triangles
    G = build_graph(nodes, edges)
    sol = optimise(G, "s0")
    assert [(d["source"], d["target"], d["reason"]) for d in sol.dropped] == [
        ("s4", "s0", "unverified")
    ]
    assert sol.unplaced == ["s4"]
    for name, T in truth.items():
        r, t = pose_error(sol.poses[name], T)
        assert r < 0.01 and t < 0.0015  # edges of 0.5 mm noise a component: ~2 sigma of the chain


def test_many_unsure_wrong_corner_edges_do_not_outvote_the_right_ones():
    # the region-preset failure: corner-to-corner pairs 30 m apart came back wrong with low coarse
    # confidence (4 of a plot's 10 edges); they must be dropped without taking the good edges along
    truth, nodes, edges = synthetic_pose_graph(n_scans=5, seed=11)
    rng = np.random.default_rng(3)
    bad = {("s2", "s1"), ("s3", "s1"), ("s4", "s2"), ("s4", "s3")}
    for e in edges:
        e["confidence"] = 0.7
        if (e["source"], e["target"]) in bad:
            e["transform"] = inverse(truth[e["target"]]) @ random_pose(rng)
            e["confidence"] = 0.03
    sol = optimise(build_graph(nodes, edges), "s0")
    assert sorted((d["source"], d["target"]) for d in sol.dropped) == sorted(bad)
    assert sol.unplaced == []
    for name, T in truth.items():
        r, t = pose_error(sol.poses[name], T)
        assert r < 0.01 and t < 0.002  # six edges left, 0.5 mm noise each


def _errors(rounds: int, rot_noise_deg: float, trans_noise: float) -> tuple[np.ndarray, list]:
    """(per-axis pose errors / sigmas, each grid's calibration) over a few noisy grids."""
    z, scales = [], []
    for seed in range(3):
        truth, nodes, edges, _ = grid_graph(
            16, wrong_share=0, seed=seed, rot_noise_deg=rot_noise_deg, trans_noise=trans_noise
        )
        sol = optimise(
            build_graph(nodes, edges), "s0000", PoseGraphConfig(calibration_rounds=rounds)
        )
        scales.append(sol.scales)
        for name, T in truth.items():
            if name != "s0000":  # the reference is the frame: no error
                xi = gtsam.Pose3.Logmap(gtsam.Pose3(inverse(T) @ sol.poses[name]))
                z.append(np.abs(xi) / sol.sigmas[name])
    return np.array(z), scales


def _coverage(rounds: int, rot_noise_deg: float, trans_noise: float) -> tuple[float, float]:
    """(share of per-axis pose errors within 1 sigma, within 2 sigma) over a few noisy grids."""
    z, _ = _errors(rounds, rot_noise_deg, trans_noise)
    return float(np.mean(z < 1)), float(np.mean(z < 2))


@pytest.mark.parametrize("rot_noise_deg, trans_noise", [(0.05, 0.01), (0.005, 0.00125)])
def test_calibrated_sigmas_cover_the_true_error(rot_noise_deg, trans_noise):
    # edges 5x noisier, then 1.6x less noisy, than their floored information says
    within_1, within_2 = _coverage(0, rot_noise_deg, trans_noise)
    assert within_1 < 0.4 or within_1 > 0.95  # as the ICP information has it: off either way
    within_1, within_2 = _coverage(3, rot_noise_deg, trans_noise)
    assert 0.55 < within_1 < 0.85 and within_2 > 0.9, (within_1, within_2)


def test_loops_shrink_sigmas_a_bounded_factor():
    # edges 4-5x less noisy than their information: loops cannot tell independent noise from
    # errors shared by neighbouring pairs, so the translation sigmas shrink at most ~1.6x and
    # cover more than they claim; rotation's may shrink further, the solve's weights only 2x
    z, scales = _errors(3, 0.002, 0.0005)
    assert np.mean(z[:, 3:] < 1) > 0.85
    assert np.mean(z[:, :3] < 1) < np.mean(z[:, 3:] < 1)
    for s in scales:
        rot, trans = s["tls-tls/rotation"], s["tls-tls/translation"]
        assert rot["observed"] < 0.25 and rot["solve_factor"] == 0.25
        assert rot["factor"] == max(rot["observed"], REPORT_FLOOR["rotation"])
        assert trans["factor"] == REPORT_FLOOR["translation"]


def test_no_loop_no_calibration():
    truth, nodes, edges = synthetic_pose_graph(n_scans=4, seed=5)
    tree = [e for e in edges if e["target"] == "s0"]  # a star: nothing observes the edges' noise
    sol = optimise(build_graph(nodes, tree), "s0")
    assert sol.scales == {}
    assert all(
        np.isfinite(s).all() and s[3:].min() > 1e-4 for n, s in sol.sigmas.items() if n != "s0"
    )


def test_sigmas_about_the_plot_free_the_reference():
    truth, nodes, edges = synthetic_pose_graph(n_scans=5, seed=6)
    sol = optimise(build_graph(nodes, edges), "s0")
    assert sol.sigmas["s0"].max() < 1e-5  # the plot frame is the reference's
    assert set(sol.about_plot) == set(sol.poses)
    assert all(s.min() > 1e-6 for s in sol.about_plot.values())  # about the plot, none is exact

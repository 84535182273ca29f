"""The pose graph: scans are nodes, pairwise registrations are edges; GTSAM places every scan.

Conventions (shared with plotmosaic.align): an edge stores `source`, `target` and `transform`, the
4x4 mapping source file coordinates into target file coordinates, with a 6x6 `information` for
T·Exp(xi), xi = (wx, wy, wz, vx, vy, vz) (GTSAM's Pose3 tangent order). Poses X_k map scan k into
the graph frame, so an edge says X_source = X_target · T.

Outliers are found in three ways, because each alone misses cases: a cycle-consistency vote on
triangles (before any solve, so a wrong edge cannot drag the initialisation), low-confidence edges
that no consistent triangle confirms (graph/cycles.py), then a residual test after a robust solve
(drop the worst offender, re-solve, repeat).

The scans' covariances come last: the kept edges' information scaled by their own residuals
where loops observe them (graph/covariance.py), then one set of marginals.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import gtsam
import networkx as nx
import numpy as np

from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.graph.covariance import (  # noqa: F401  (condition_information, residual re-exported)
    EdgeInformation,
    JointCovariance,
    condition_information,
    noise_model,
    redundancy_dof,
    residual,
    scan_covariances,
    update_scales,
    variance_components,
)
from plotmosaic.graph.cycles import kept, spanning_tree_poses, vote
from plotmosaic.io.frame import inverse, pose_error, rotation_deg  # noqa: F401  (re-exported)

# what the graph keeps of a failed pair
_FAILED_FIELDS = ("source", "target", "error", "key", "overlap", "confidence")


def _pose3(T: np.ndarray) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(T, dtype=np.float64))


# --- graph construction and I/O --------------------------------------------------------------------


def build_graph(nodes: dict[str, dict], edges: list[dict]) -> nx.Graph:
    """Scans as nodes (any attributes), successful pair results as edges.

    Each edge dict has at least source, target, transform; optional fitness, inlier_rmse, overlap,
    confidence, information. Failed pairs (status "failed") are kept in G.graph["failed"].
    """
    G = nx.Graph()
    G.graph["failed"] = []
    for name, attrs in nodes.items():
        G.add_node(name, **attrs)
    add_edges(G, edges)
    return G


def add_edges(G: nx.Graph, edges: list[dict]) -> nx.Graph:
    """Add successful pair results as edges (arrays made numpy); failed ones go to G.graph["failed"]."""
    for e in edges:
        if e.get("status", "ok") != "ok":
            failed = {k: v for k, v in e.items() if k in _FAILED_FIELDS}
            G.graph.setdefault("failed", []).append(failed)
            continue
        attrs = dict(e)
        attrs["transform"] = np.asarray(e["transform"], dtype=np.float64)
        if e.get("information") is not None:
            attrs["information"] = np.asarray(e["information"], dtype=np.float64)
        attrs.setdefault("status", "ok")
        attrs.setdefault("dropped", False)
        attrs["weight"] = edge_strength(attrs)
        G.add_edge(e["source"], e["target"], **attrs)
    return G


def edge_strength(e: dict) -> float:
    """How much to trust an edge when choosing the initialisation tree (bigger is better)."""
    fitness = e.get("fitness") or 0.0
    overlap = e.get("overlap")
    return float(fitness * overlap) if overlap is not None else float(fitness)


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


# Link ends are "a"/"b" so the edges' own "source"/"target" (the direction of the pair) survive.
_LINK = {"edges": "edges", "source": "a", "target": "b"}


def graph_to_json(G: nx.Graph) -> dict:
    """Node-link form with plain lists instead of arrays."""
    data = nx.node_link_data(G, **_LINK)
    return _jsonable(data)


def graph_from_json(data: dict) -> nx.Graph:
    G = nx.node_link_graph(data, **_LINK)
    for _, _, attrs in G.edges(data=True):
        for name in ("transform", "information"):
            if attrs.get(name) is not None:
                attrs[name] = np.asarray(attrs[name], dtype=np.float64)
    G.graph.setdefault("failed", [])
    return G


# --- the solve ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Solution:
    poses: dict[str, np.ndarray]  # placed scans only
    # sqrt(diag(marginal covariance)): rx, ry, rz (rad), tx, ty, tz (m), in the scan's own frame
    sigmas: dict[str, np.ndarray]
    unplaced: list[str]  # scans with no kept edge path to the reference
    iterations: int = 0
    error_before: float = 0.0
    error_after: float = 0.0
    dropped: list[dict] = field(default_factory=list)  # {"source", "target", "reason"}
    covariances: dict[str, np.ndarray] = field(default_factory=dict)  # 6x6, same order as sigmas
    scales: dict = field(default_factory=dict)  # the edge groups' variance factors (Scales.as_dict)
    about_plot: dict[str, np.ndarray] = field(default_factory=dict)  # sigmas about the mean frame


@dataclass(frozen=True)
class _Solve:
    """One LM solve: the placed scans' poses, the scans it leaves out, its figures and factors."""

    poses: dict[str, np.ndarray]
    unplaced: list[str]
    iterations: int
    error_before: float
    error_after: float
    graph: gtsam.NonlinearFactorGraph
    result: gtsam.Values
    keys: dict[str, int]


def _solve(
    G: nx.Graph, reference: str, config: PoseGraphConfig, information: EdgeInformation
) -> _Solve:
    """One robust LM solve."""
    init = spanning_tree_poses(G, reference)
    placed = sorted(init)
    keys = {name: gtsam.symbol("x", n) for n, name in enumerate(placed)}
    values = gtsam.Values()
    for name in placed:
        values.insert(keys[name], _pose3(init[name]))
    graph = _factor_graph(G, reference, keys, config, information)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    before = graph.error(values)
    result = optimizer.optimize()
    poses = {name: result.atPose3(keys[name]).matrix() for name in placed}
    unplaced = sorted(n for n in G.nodes if n not in keys)
    after = float(graph.error(result))
    return _Solve(
        poses, unplaced, optimizer.iterations(), float(before), after, graph, result, keys
    )


def _factor_graph(
    G: nx.Graph, reference: str, keys: dict[str, int], config: PoseGraphConfig, information
):
    """The reference fixed at the identity and one between-factor per kept edge."""
    graph = gtsam.NonlinearFactorGraph()
    graph.add(
        gtsam.PriorFactorPose3(
            keys[reference], gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)
        )
    )
    for u, v, e in kept(G).edges(data=True):
        if u not in keys or v not in keys:
            continue
        graph.add(
            gtsam.BetweenFactorPose3(
                keys[e["target"]],
                keys[e["source"]],
                _pose3(e["transform"]),
                noise_model(information.of(u, v), config),
            )
        )
    return graph


def _calibrated(
    G: nx.Graph, reference: str, config: PoseGraphConfig, information, solved: _Solve
) -> tuple[_Solve, EdgeInformation]:
    """The last solve again with each edge group's information scaled by its residuals (rounds of
    variance components), and the information so scaled."""
    if config.calibration_rounds and redundancy_dof(kept(G), set(solved.keys)) > 0:
        # plain least squares while calibrating: a robust kernel discounts the very residuals
        # that show an edge group's noise too small (kept edges passed the outlier tests)
        plain = config.model_copy(update={"robust": "none"})
        for _ in range(config.calibration_rounds):
            s = _solve(G, reference, plain, information)
            edges = [(u, v) for u, v in kept(G).edges() if u in s.keys and v in s.keys]
            joint = JointCovariance(s.graph, s.result, s.keys)
            quad, red = variance_components(G, edges, s.poses, s.keys, joint, information)
            scales = update_scales(information.scales, quad, red)
            information = dataclasses.replace(information, scales=scales)
        solved = _solve(G, reference, config, information)
    return solved, information


def _drop(G: nx.Graph, u: str, v: str, reason: str, dropped: list[dict]) -> None:
    e = G.edges[u, v]
    e["dropped"] = True
    e["drop_reason"] = reason
    dropped.append({"source": e["source"], "target": e["target"], "reason": reason})


def _mark_residuals(G: nx.Graph, name: str, poses: dict, information: EdgeInformation) -> None:
    """Each edge's residual at `poses` as its attribute `name` (None where a scan is not placed)."""
    for u, v, e in G.edges(data=True):
        e[name] = residual(G, u, v, poses, information) if u in poses and v in poses else None


def optimise(G: nx.Graph, reference: str, config: PoseGraphConfig | None = None) -> Solution:
    """Cycle check, robust solve, drop the worst residual outlier and re-solve until none is left.

    Edge attributes are updated in place: dropped, drop_reason, residual_before (at the
    spanning-tree initialisation), residual_after (at the final poses, chi2 with the calibrated
    information). The triangle vote runs once; the edge noise is calibrated after the last drop.
    """
    config = config or PoseGraphConfig()
    dropped: list[dict] = []
    outliers, unconfirmed = vote(G, config)
    for u, v in outliers:
        _drop(G, u, v, "cycle", dropped)
    for u, v in unconfirmed:
        _drop(G, u, v, "unverified", dropped)
    initial = spanning_tree_poses(G, reference)
    information = EdgeInformation(G, config)
    _mark_residuals(G, "residual_before", initial, information)
    residual_drops = 0
    while True:
        sol = _solve(G, reference, config, information)
        worst, worst_chi2 = None, 0.0
        for u, v in kept(G).edges():
            if u not in sol.poses or v not in sol.poses:
                continue
            r = residual(G, u, v, sol.poses, information)
            metric = (
                r["rotation_deg"] > config.outlier_rotation_deg
                or r["translation"] > config.outlier_translation
            )
            if metric and r["chi2"] > config.outlier_chi2 and r["chi2"] > worst_chi2:
                worst, worst_chi2 = (u, v), r["chi2"]
        if worst is None or residual_drops >= config.max_drops:
            break
        _drop(G, *worst, "residual", dropped)
        residual_drops += 1
    sol, information = _calibrated(G, reference, config, information, sol)
    # every placed scan's marginal covariance, once, at the calibrated poses with the factors
    # floored for reporting (covariance.REPORT_FLOOR)
    reported = _factor_graph(G, reference, sol.keys, config, information.reporting())
    covariances, sigmas, about_plot = scan_covariances(G, reported, sol.result, sol.keys, sol.poses)
    scales = information.scales.as_dict()
    _mark_residuals(G, "residual_after", sol.poses, information)
    return Solution(
        sol.poses,
        sigmas,
        sol.unplaced,
        sol.iterations,
        sol.error_before,
        sol.error_after,
        dropped,
        covariances,
        scales,
        about_plot,
    )

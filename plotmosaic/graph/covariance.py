"""Edge noise calibrated on the solve's own residuals, and the scans' marginal covariances.

An ICP information matrix (J^T J / sigma^2 over thousands of correlated points) says how a pose is
constrained, not how far off it is: floored and capped it is a shape, not a scale. Where the graph
has loops, the edges' residuals measure that scale. Variance components (Förstner): the edges fall
in groups (the kinds of the two scans, rotation or translation block), and each group's information
is divided by its variance factor

    s_g^2 = sum over the group's residual components of xi_k (P xi)_k / its redundancy r_g,
    r_g   = sum over the same components of (P Q_vv)_kk,   Q_vv = P^-1 - C_pred,

where C_pred is the covariance of the relative pose the solution predicts for that edge (the joint
marginal of its two scans). Iterated a few times (each factor changes the others' redundancy), then
the marginals at the last solve's poses are the scans' covariances. The loops' factors are floored
twice: for the solve's weights and, lower in rotation, for the reported sigmas (see the floors
below). A group without redundancy (a tree, or one anchor a plot) keeps its information: nothing
observes its scale.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import networkx as nx
import numpy as np

from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.io.frame import inverse, rotation_deg

ROTATION, TRANSLATION = slice(0, 3), slice(3, 6)
BLOCKS = {"rotation": ROTATION, "translation": TRANSLATION}
# a variance factor is estimated only from this much redundancy (scalar dof): fewer leave it
# a guess (its relative error is sqrt(2 / dof))
MIN_REDUNDANCY = 6.0
# one edge's squared whitened residual counts at most this much (chi2, 6 dof, p = 0.999): a wrong
# edge the robust kernel already discounts must not inflate its whole group
MAX_EDGE_CHI2 = 22.46
# Loop residuals see only the part of a pair's error that differs between pairs; what neighbouring
# pairs share (same stems, same sampling) cancels around a loop yet moves every scan. So the loops'
# variance factors are trusted only so far below 1, differently for the two uses:
# the solve's weights shrink a group's sigmas at most 2x: trusting the loops' relative weighting of
# rotation and translation further makes the poses worse;
SOLVE_FLOOR = {"rotation": 0.25, "translation": 0.25}
# the reported sigmas shrink at most ~4.5x in rotation and ~1.6x in translation, where the shared
# error mostly lies: so they cover the true errors as often as they claim (results/uncertainty.md).
REPORT_FLOOR = {"rotation": 0.05, "translation": 0.4}
MAX_FACTOR = 1e6  # a group's sigmas grow at most 1000x
MAP_FLOOR = 1.0  # map edges (graph/maps.py) never shrink below their information


def edge_group(G: nx.Graph, u: str, v: str) -> str:
    """The kinds of an edge's two ends, sorted: "tls-tls", "als-tls", ...; an edge measured on a
    map ("tls-tls map") is a group of its own: its noise is not a pair's."""
    kinds = "-".join(sorted(str(G.nodes[n].get("kind", "unknown")) for n in (u, v)))
    return f"{kinds} map" if G.edges[u, v].get("via") == "map" else kinds


@dataclass(frozen=True)
class Scales:
    """The loops' variance factor of each (group, block), as observed; the information of its edges
    is divided by it, floored for the solve (`SOLVE_FLOOR`) or for the reported sigmas
    (`REPORT_FLOOR`)."""

    observed: dict[tuple[str, str], float] = field(default_factory=dict)
    redundancy: dict[tuple[str, str], float] = field(default_factory=dict)

    def factor(self, key: tuple[str, str], floor: dict[str, float]) -> float:
        group, block = key
        low = floor[block]
        if group.endswith(" map"):
            # a survey's edges are measured at the poses the graph then keeps: their loops close
            # by construction and cannot show them surer than their information
            low = MAP_FLOOR
        return float(np.clip(self.observed.get(key, 1.0), low, MAX_FACTOR))

    def apply(self, group: str, info: np.ndarray, floor: dict[str, float]) -> np.ndarray:
        d = np.ones(6)
        for block, sl in BLOCKS.items():
            d[sl] = 1.0 / np.sqrt(self.factor((group, block), floor))
        return info * np.outer(d, d)

    def as_dict(self) -> dict:
        """JSON form: "group/block" -> {"factor" (the reported sigmas'), "solve_factor",
        "observed" (the loops'), "redundancy"}."""
        return {
            f"{g}/{b}": {
                "factor": self.factor((g, b), REPORT_FLOOR),
                "solve_factor": self.factor((g, b), SOLVE_FLOOR),
                "observed": f,
                "redundancy": self.redundancy.get((g, b), 0.0),
            }
            for (g, b), f in sorted(self.observed.items())
        }


def condition_information(
    info: np.ndarray | None, rmse: float | None, config: PoseGraphConfig, via: str | None = None
) -> np.ndarray:
    """A well-conditioned 6x6 information: sigmas floored (an ALS placement's, `via` "als", at
    what a scan's placement on the ALS is known to), strongest/weakest ratio capped."""
    rot, trans = (
        (config.anchor_min_sigma_rotation_deg, config.anchor_min_sigma_translation)
        if via == "als"
        else (config.min_sigma_rotation_deg, config.min_sigma_translation)
    )
    floors = np.array([np.radians(rot)] * 3 + [trans] * 3)
    S = np.diag(floors)
    A = None
    if info is not None:
        info = np.asarray(info, dtype=np.float64)
        if info.shape == (6, 6) and np.isfinite(info).all():
            # in floor units: eigenvalue 1 <=> sigma at the floor
            A = S @ ((info + info.T) / 2.0) @ S
    if A is not None:
        w, V = np.linalg.eigh(A)
        if w.max() <= 0:
            A = None
    if A is None:  # no usable information: a loose isotropic guess from the pair's RMSE
        sigma_t = max(rmse or 0.0, 0.01)
        sigma_r = np.radians(config.fallback_sigma_rotation_deg)
        return np.diag([1 / sigma_r**2] * 3 + [1 / sigma_t**2] * 3)
    cap = min(w.max(), 1.0)
    w = np.clip(w, cap / config.max_information_ratio, cap)
    Sinv = np.diag(1.0 / floors)
    return Sinv @ (V * w) @ V.T @ Sinv


@dataclass(frozen=True)
class EdgeInformation:
    """The information of a graph's edges as solved, owned by one optimisation: an ICP information
    conditioned once per edge (however often it is solved and tested), then scaled by its group's
    variance factor. An edge marked `posterior` (a covariance already estimated, e.g. a pose from an
    earlier solve) is used as it is."""

    G: nx.Graph
    config: PoseGraphConfig
    scales: Scales = field(default_factory=Scales)
    held: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)
    floor: dict[str, float] = field(default_factory=lambda: SOLVE_FLOOR)

    def reporting(self) -> EdgeInformation:
        """The same edges and factors, floored for the reported sigmas."""
        return EdgeInformation(self.G, self.config, self.scales, self.held, REPORT_FLOOR)

    def of(self, u: str, v: str) -> np.ndarray:
        key = (u, v) if u <= v else (v, u)
        if key not in self.held:
            e = self.G.edges[u, v]
            self.held[key] = (
                np.asarray(e["information"], dtype=np.float64)
                if e.get("posterior")
                else condition_information(
                    e.get("information"), e.get("inlier_rmse"), self.config, e.get("via")
                )
            )
        return self.scales.apply(edge_group(self.G, u, v), self.held[key], self.floor)


def noise_model(info: np.ndarray, config: PoseGraphConfig):
    """GTSAM noise of an edge: Gaussian with this information, in the configured robust kernel."""
    base = gtsam.noiseModel.Gaussian.Information(info)
    if config.robust == "none":
        return base
    est = gtsam.noiseModel.mEstimator
    kernel = (
        est.Cauchy.Create(config.robust_k)
        if config.robust == "cauchy"
        else est.Huber.Create(config.robust_k)
    )
    return gtsam.noiseModel.Robust.Create(kernel, base)


def residual(
    G: nx.Graph, u: str, v: str, poses: dict[str, np.ndarray], information: EdgeInformation
) -> dict:
    """Residual of one edge at the given poses: rotation (deg), translation (m) and chi2 (conditioned info)."""
    e = G.edges[u, v]
    i, j = e["source"], e["target"]
    # identity when the edge is satisfied
    E = inverse(e["transform"]) @ inverse(poses[j]) @ poses[i]
    xi = gtsam.Pose3.Logmap(gtsam.Pose3(E))
    info = information.of(u, v)
    return {
        "rotation_deg": rotation_deg(E),
        "translation": float(np.linalg.norm(E[:3, 3])),
        "chi2": float(xi @ info @ xi),
    }


def redundancy_dof(G: nx.Graph, placed: set[str]) -> int:
    """6 x (edges - spanning-tree edges) among the placed scans: zero when no loop observes a scale."""
    H = G.subgraph(placed)
    return 6 * (H.number_of_edges() - H.number_of_nodes() + nx.number_connected_components(H))


class JointCovariance:
    """The covariance of every placed pose at once: the inverse of the solve's dense Hessian (a
    plot's graph: tens to hundreds of scans), read two scans at a time."""

    def __init__(self, graph, result, keys: dict[str, int]):
        ordering = gtsam.Ordering()
        for k in keys.values():
            ordering.push_back(k)
        H, _ = graph.linearize(result).hessian(ordering)
        self.C = np.linalg.inv(H)
        self.at = {k: 6 * n for n, k in enumerate(keys.values())}

    def block(self, a: int, b: int) -> np.ndarray:
        i, j = self.at[a], self.at[b]
        return self.C[i : i + 6, j : j + 6]

    def relative(self, ki: int, kj: int, Z: np.ndarray) -> np.ndarray:
        """Covariance of the right perturbation of Z = X_j^-1 X_i: delta_i - Ad(Z^-1) delta_j."""
        A = np.hstack([np.eye(6), -gtsam.Pose3(inverse(Z)).AdjointMap()])
        C = np.block(
            [[self.block(ki, ki), self.block(ki, kj)], [self.block(kj, ki), self.block(kj, kj)]]
        )
        return A @ C @ A.T


def variance_components(
    G: nx.Graph,
    edges: list[tuple[str, str]],
    poses: dict[str, np.ndarray],
    keys: dict[str, int],
    joint: JointCovariance,
    information,
) -> tuple[dict, dict]:
    """(quadratic form, redundancy) per (group, block) over `edges` at the solution `poses`;
    `information.of(u, v)` is each edge's information as solved."""
    quad: dict[tuple[str, str], float] = {}
    red: dict[tuple[str, str], float] = {}
    for u, v in edges:
        e = G.edges[u, v]
        i, j = e["source"], e["target"]
        Z = inverse(poses[j]) @ poses[i]
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(inverse(e["transform"]) @ Z))
        P = information.of(u, v)
        chi2 = float(xi @ P @ xi)
        if chi2 > MAX_EDGE_CHI2:
            xi = xi * np.sqrt(MAX_EDGE_CHI2 / chi2)
        Qvv = np.linalg.inv(P) - joint.relative(keys[i], keys[j], Z)
        PQ = np.diag(P @ Qvv)
        Pxi = P @ xi
        g = edge_group(G, u, v)
        for block, sl in BLOCKS.items():
            quad[g, block] = quad.get((g, block), 0.0) + float(xi[sl] @ Pxi[sl])
            red[g, block] = red.get((g, block), 0.0) + float(PQ[sl].sum())
    return quad, red


def update_scales(scales: Scales, quad: dict, red: dict) -> Scales:
    """Each group's observed factors: the factors the solve used times their newly observed
    variance factors; a factor per block where each block has the redundancy, one for the whole
    group where only both together have it, none where the group has not (its information kept)."""
    observed, redundancy = dict(scales.observed), dict(scales.redundancy)
    redundancy.update(red)
    for group in sorted({g for g, _ in red}):
        keys = [(group, b) for b in BLOCKS]
        r = [red.get(k, 0.0) for k in keys]
        q = [quad.get(k, 0.0) for k in keys]
        if min(r) >= MIN_REDUNDANCY:
            s2 = [qi / ri for qi, ri in zip(q, r, strict=True)]
        elif sum(r) >= MIN_REDUNDANCY:
            s2 = [sum(q) / sum(r)] * len(keys)
        else:
            continue
        for k, s2k in zip(keys, s2, strict=True):
            observed[k] = scales.factor(k, SOLVE_FLOOR) * s2k
    return Scales(observed=observed, redundancy=redundancy)


def marginal_covariances(graph, result, keys: dict[str, int]) -> dict[str, np.ndarray]:
    """6x6 marginal covariance of every placed scan (rx, ry, rz, tx, ty, tz in its own frame)."""
    marginals = gtsam.Marginals(graph, result)
    return {name: np.asarray(marginals.marginalCovariance(k)) for name, k in keys.items()}


def about_the_plot(
    joint: JointCovariance, poses: dict[str, np.ndarray], keys: dict[str, int], skip: set[str]
) -> dict[str, np.ndarray]:
    """Each pose's covariance about the mean frame of the poses not in `skip` (a plot registered to
    the ALS as one cloud is placed by all its scans, not by its reference): the right perturbation
    less the scans' mean left perturbation carried to it."""
    names = [n for n in keys if n not in skip]
    index = {n: k for k, n in enumerate(keys)}
    Ad = {n: gtsam.Pose3(poses[n]).AdjointMap() for n in names}
    M = np.zeros((6, 6 * len(keys)))
    for n in names:
        M[:, 6 * index[n] : 6 * index[n] + 6] = Ad[n] / len(names)
    out = {}
    for n in names:
        A = -np.linalg.solve(Ad[n], M)
        A[:, 6 * index[n] : 6 * index[n] + 6] += np.eye(6)
        out[n] = A @ joint.C @ A.T
    return out


def sigmas_of(covariances: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {n: np.sqrt(np.clip(np.diag(C), 0, None)) for n, C in covariances.items()}


def scan_covariances(G: nx.Graph, graph, result, keys: dict[str, int], poses: dict) -> tuple:
    """(marginal covariance, sigmas, sigmas about the mean frame of the scans) of every placed
    node; an ALS node (kind "als") is no part of the plot's mean frame."""
    covariances = marginal_covariances(graph, result, keys)
    als = {n for n in keys if G.nodes[n].get("kind") == "als"}
    about = about_the_plot(JointCovariance(graph, result, keys), poses, keys, als)
    return covariances, sigmas_of(covariances), sigmas_of(about)

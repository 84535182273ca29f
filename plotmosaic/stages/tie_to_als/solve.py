"""tie-to-als solve: one graph of every plot as register-plot placed it, each plot anchored to the ALS."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import networkx as nx
import numpy as np

from plotmosaic.config.register import TieConfig
from plotmosaic.errors import RegistrationFailed
from plotmosaic.graph.compute import EDGE_FIELDS
from plotmosaic.graph.jobs import PairJob
from plotmosaic.graph.posegraph import Solution, build_graph, inverse, optimise
from plotmosaic.io.frame import Frame, translation
from plotmosaic.manifest import Manifest, Plot
from plotmosaic.poses import Poses
from plotmosaic.stages.tie_to_als.anchor_fit import AnchorFit

ALS_NODE = "ALS"
# added to a jackknife covariance before it is inverted (rad x 3, m x 3): blocks that agree exactly
# must not make an anchor infinitely sure
COVARIANCE_FLOOR = np.array([1e-6] * 3 + [1e-5] * 3)


@dataclass(frozen=True)
class Anchor:
    plot: str
    reference: str
    status: str  # "ok" | "failed"
    transform: np.ndarray | None = None  # plot frame -> ALS CRS
    fitness: float | None = None
    inlier_rmse: float | None = None
    overlap: float | None = None
    confidence: float | None = None
    error: str | None = None
    crop: str = "whole tile"
    # the ALS against the registered plot (AnchorFit.as_dict) and the pair's judge fine margin: what
    # says how well the anchor holds (its edge residual is zero by construction: one anchor a plot)
    fit: dict | None = None
    fine_margin: float | None = None


@dataclass(frozen=True, kw_only=True)
class Tied:
    """Each plot's pair to the ALS: the jobs, their records, each plot's anchor and reference scan."""

    jobs: list[PairJob]
    records: dict[str, dict]
    computed: int
    anchors: dict[str, Anchor]  # plot id -> its anchor
    refs: dict[str, str]  # plot id -> its reference scan (plots with a placed scan)
    fits: dict[str, AnchorFit]  # plot id -> the ALS against its registered plot (where measured)


def _plot_reference(plot: Plot, poses: Poses, G: nx.Graph | None) -> str:
    """The scan whose frame is the plot frame (identity pose); the manifest's reference otherwise."""
    placed = [s.id for s in plot.scans if s.id in poses.scans]
    recorded = poses.extra.get("plots", {}).get(plot.id, {}).get("reference")
    if recorded in placed:
        return recorded
    for sid in placed:
        if np.allclose(poses.transform(sid), np.eye(4), atol=1e-9):
            return sid
    return plot.reference.id if plot.reference.id in placed else placed[0]


def _plot_edges(plot: Plot, poses: Poses, G: nx.Graph | None, ref: str) -> tuple[dict, list[dict]]:
    """Within-plot edges: each placed scan to the reference as register-plot placed it, its sigmas as
    information. Not the pairs again: register-plot's solve also held them by the ALS placements
    (and confirmed unsure pairs through them), which a re-solve without them would lose (3 cm on
    the `large` preset at 60k); pairs never cross plots, so one anchor moves a plot as one piece."""
    ids = [s.id for s in plot.scans]
    if G is not None and all(s in G for s in ids):
        nodes = {n: dict(G.nodes[n]) for n in ids}  # the scans' files, for `plotmosaic report`
    else:
        nodes = {s.id: {"plot": plot.id, "kind": s.kind.value} for s in plot.scans}
    edges = []
    P_ref = poses.transform(ref)
    for sid in ids:
        if sid == ref or sid not in poses.scans:
            continue
        sp = poses.scans[sid]
        info = (
            None
            if sp.sigma is None
            else np.diag(1.0 / np.maximum(np.asarray(sp.sigma, float), 1e-6) ** 2)
        )
        edges.append(
            {
                "source": sid,
                "target": ref,
                "transform": inverse(P_ref) @ sp.transform,
                "information": info,
                "fitness": 1.0,
                "overlap": 1.0,
                "status": "ok",
                "from_poses": True,
                "posterior": sp.sigma is not None,  # register-plot's marginals: used as they are
            }
        )
    return nodes, edges


def anchor_of(plot: str, reference: str, crop: str, rec: dict, fit: AnchorFit | None) -> Anchor:
    """A plot's anchor from its pair to the ALS: ok with the pair's figures (and the ALS against
    the registered plot, where measured), else failed with the pair's error."""
    if rec.get("status") != "ok":
        return Anchor(plot, reference, "failed", error=rec.get("error"), crop=crop)
    return Anchor(
        plot,
        reference,
        "ok",
        np.asarray(rec["transform"], float),  # plot frame -> ALS CRS
        rec.get("fitness"),
        rec.get("inlier_rmse"),
        rec.get("overlap"),
        rec.get("confidence"),
        crop=crop,
        fit=None if fit is None else fit.as_dict(),
        fine_margin=(rec.get("judge") or {}).get("fine_margin"),
    )


def _anchor_dict(a: Anchor) -> dict:
    """The anchor as poses.json records it (keyed by its plot): its figures, the fit's beside them."""
    figures = {k: v for k, v in vars(a).items() if k not in ("plot", "transform", "fit")}
    return {**figures, **(a.fit or {})}


def _anchor_edge(
    rec: dict, anchor: Anchor, fit: AnchorFit | None, poses: Poses, als_frame: Frame
) -> dict:
    """The edge reference scan file -> ALS local frame of one plot's ALS result; its information the
    inverse of the anchor's jackknife covariance where measured (else the pair's ICP information,
    floored like any pair's)."""
    T = np.asarray(rec["transform"], float)  # plot frame -> ALS CRS
    P_ref = poses.transform(anchor.reference)
    info = (
        np.asarray(rec["information"], float)
        if fit is None
        else np.linalg.inv(fit.covariance + np.diag(COVARIANCE_FLOOR**2))
    )
    Ad = gtsam.Pose3(P_ref).AdjointMap()  # information moved onto the reference scan's tangent
    edge = {k: rec.get(k) for k in EDGE_FIELDS}
    edge.update(
        source=anchor.reference,
        target=ALS_NODE,
        anchor=anchor.plot,
        transform=translation(-als_frame.offset) @ T @ P_ref,
        information=Ad.T @ info @ Ad,
        posterior=fit is not None,
    )
    return edge


def region_graph(
    manifest: Manifest, poses: Poses, G_plot: nx.Graph | None, als_frame: Frame, tied: Tied
) -> nx.Graph:
    """One graph: every plot's pairwise edges + an anchor edge per plot to the fixed ALS node.

    Raises RegistrationFailed when no plot is tied to the ALS."""
    nodes, edges = {ALS_NODE: {"kind": "als", "plot": None}}, []
    for plot in manifest.plots:
        if plot.id in tied.refs:
            n, e = _plot_edges(plot, poses, G_plot, tied.refs[plot.id])
            nodes.update(n)
            edges += e
    for job in tied.jobs:
        rec, anchor = tied.records[job.key], tied.anchors[job.source]
        if anchor.status != "ok":
            continue
        edges.append(_anchor_edge(rec, anchor, tied.fits.get(job.source), poses, als_frame))
    if not any(a.status == "ok" for a in tied.anchors.values()):
        raise RegistrationFailed(
            "no plot could be registered to the ALS: "
            + "; ".join(f"{a.plot}: {a.error}" for a in tied.anchors.values())
        )
    return build_graph(nodes, edges)


def solve_region(G: nx.Graph, config: TieConfig) -> Solution:
    """The region solved with the ALS node fixed: each scan's covariance its plot-frame one plus
    its plot's anchor's, carried to the scan."""
    for _u, _v, e in G.edges(data=True):  # register-plot decisions stand; the rest is re-checked
        e["dropped"] = bool(e.get("dropped"))
    return optimise(G, ALS_NODE, config.graph)


def georeferenced_sigmas(poses: Poses, tied: Tied) -> dict[str, np.ndarray]:
    """Sigmas of the scans of each plot with a measured anchor: the anchor's covariance carried to
    the scan plus the scan's own about its plot's mean frame (register-plot's `sigma_about_plot`).
    The anchor is fitted on the whole plot cloud, so it places the plot's mean frame, not its
    reference scan; the region graph's marginals would hang every scan on the reference."""
    out = {}
    for plot, fit in tied.fits.items():
        for sid, sp in poses.scans.items():
            about = sp.extra.get("sigma_about_plot")
            if sp.plot != plot or about is None:
                continue
            Ad = gtsam.Pose3(inverse(sp.transform)).AdjointMap()  # plot frame -> the scan's tangent
            C = Ad @ fit.covariance @ Ad.T + np.diag(np.square(np.asarray(about, dtype=float)))
            out[sid] = np.sqrt(np.diag(C))
    return out

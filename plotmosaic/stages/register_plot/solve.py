"""Solve: the pose graph of the run's pairs, each plot optimised in its reference scan's frame."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import networkx as nx

from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.posegraph import Solution, add_edges, build_graph, optimise
from plotmosaic.io.las import read_header_info
from plotmosaic.manifest import Plot
from plotmosaic.poses import ScanPose
from plotmosaic.stages.register_plot.pairs import Pairs, Run, anchor_id
from plotmosaic.stages.register_plot.place import Priors


@dataclass(frozen=True)
class PlotResult:
    plot: str
    reference: str
    solution: Solution
    scans: list[str]

    @property
    def unplaced(self) -> list[str]:
        return self.solution.unplaced


@dataclass(frozen=True, kw_only=True)
class Solved:
    """The pose graph of every pair, each plot's solution and every placed scan's pose."""

    graph: nx.Graph
    plots: list[PlotResult]
    scans: dict[str, ScanPose]


def solve_plot(
    G: nx.Graph, plot: Plot, anchors: list[dict], config: RegisterConfig
) -> tuple[str, Solution]:
    """(reference, solution) of one plot: its scans' subgraph, plus the ALS node when there are anchors.

    The ALS node and its edges live only in the solve; what the solve marks on the scan-to-scan
    edges (dropped, residuals) is written back to G, and the ALS node is no pose of the result.
    The edge groups' variance factors go to G.graph["calibration"][plot id]."""
    sub = H = G.subgraph([s.id for s in plot.scans])
    node = anchor_id(plot)
    if anchors:
        H = sub.copy()
        H.add_node(node, kind="als", plot=plot.id)  # its edges are a noise group of their own
        add_edges(H, anchors)
    ref = _choose_reference(H, plot)  # a scan held by its ALS placement alone is connected too
    sol = optimise(H, ref, config.graph)
    G.graph.setdefault("calibration", {})[plot.id] = sol.scales
    if not anchors:
        return ref, sol
    for u, v in sub.edges():
        G.edges[u, v].update(H.edges[u, v])
    return ref, dataclasses.replace(
        sol,
        poses=_without(sol.poses, node),
        sigmas=_without(sol.sigmas, node),
        covariances=_without(sol.covariances, node),
        unplaced=[n for n in sol.unplaced if n != node],
    )


def _without(values: dict, node: str) -> dict:
    return {k: v for k, v in values.items() if k != node}


def _choose_reference(G: nx.Graph, plot: Plot) -> str:
    """The manifest's reference, unless it has no successful pair: then the best-connected scan
    (never the plot's ALS node)."""
    ref = plot.reference.id
    if G.degree(ref) > 0 or G.number_of_edges() == 0:
        return ref
    scans = {s.id for s in plot.scans}
    biggest = max(nx.connected_components(G), key=lambda c: len(c & scans)) & scans
    return max(sorted(biggest), key=lambda n: G.degree(n, weight="weight"))


def solve(run: Run, priors: Priors, pairs: Pairs) -> Solved:
    """Every pair an edge of one graph (every scan a node), then each plot solved on its own."""
    manifest = run.manifest
    nodes = {}
    for plot in manifest.plots:
        for scan in plot.scans:
            path = manifest.resolve(scan.path)
            nodes[scan.id] = {
                "plot": plot.id,
                "kind": scan.kind.value,
                "path": str(path),
                "points": read_header_info(path).point_count,
            }
    G = build_graph(nodes, pairs.edges())
    results, scans = [], {}
    for plot in manifest.plots:
        ref, sol = solve_plot(G, plot, priors.anchors[plot.id], run.config)
        results.append(PlotResult(plot.id, ref, sol, [s.id for s in plot.scans]))
        for name, T in sol.poses.items():
            about = {"sigma_about_plot": sol.about_plot[name].tolist()}  # for tie-to-als
            scans[name] = ScanPose(T, plot.id, sol.sigmas[name], about)
    return Solved(graph=G, plots=results, scans=scans)

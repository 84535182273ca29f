"""Do the scans' sigmas cover their true error? Per-axis errors against the sigmas on simulated plots.

    python benchmarks/bench_uncertainty.py SIM:REG[:GEO] [SIM:REG[:GEO] ...] [--resolve]

SIM is a simulated plot (ground_truth.json, manifest.toml), REG its register-plot folder, GEO its
tie-to-als folder. Each placed scan's error is taken in its own frame, xi = Log(T_true^-1 T_est)
(rx ry rz tx ty tz, GTSAM's tangent, the order of the poses' `sigma`), and each component is
divided by that axis's sigma. Printed per run and over all runs: the share of translation and of
rotation components within 1 and 2 sigma (68 % and 95 % if the sigmas are right), in the plot
frame (truth in the reference scan's true frame; the reference itself, the frame, left out) and
georeferenced (truth in UTM), then the share within 1 sigma of each axis over all runs.

--resolve: the poses are solved again with the current code instead of read from the folders:
each plot's pose graph from REG's stored edges (graph.json, the placement/ cache), then the region
from GEO's anchor pair and plot clouds (not registered again): what a change of the pose graph or
of the covariances does, without registering anything.
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

import gtsam
import numpy as np

from plotmosaic.config.align import AlignConfig
from plotmosaic.config.register import RegisterConfig, TieConfig
from plotmosaic.graph.jobs import PairJob
from plotmosaic.graph.placement import placed_poses
from plotmosaic.graph.posegraph import graph_from_json, inverse
from plotmosaic.io.frame import Frame
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import Poses, ScanPose, load_poses
from plotmosaic.stages.register_plot import als_anchor_edges, solve_plot
from plotmosaic.stages.tie_to_als.anchor_fit import fit_anchors
from plotmosaic.stages.tie_to_als.solve import (
    Tied,
    anchor_of,
    georeferenced_sigmas,
    region_graph,
    solve_region,
)


def _truth(sim: Path) -> dict[str, np.ndarray]:
    data = json.loads((sim / "ground_truth.json").read_text())["scans"]
    return {k: np.asarray(v["transform"], dtype=float) for k, v in data.items()}


def normalised_errors(poses: Poses, truth: dict[str, np.ndarray]) -> np.ndarray:
    """Rows |xi| / sigma (6 a scan) of every placed scan with a sigma; plot frame (poses.frame
    "plot"): truth moved into each plot's reference scan's true frame, the reference left out."""
    rows = []
    refs = {p: d.get("reference") for p, d in (poses.extra.get("plots") or {}).items()}
    for sid, sp in poses.scans.items():
        if sp.sigma is None:
            continue
        true = truth[sid]
        if poses.frame == "plot":
            ref = refs.get(sp.plot) or next(
                k for k, s in poses.scans.items() if np.allclose(s.transform, np.eye(4))
            )
            if sid == ref:
                continue
            true = inverse(truth[ref]) @ true
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(inverse(true) @ sp.transform))
        rows.append(np.abs(xi) / np.maximum(sp.sigma, 1e-12))
    return np.array(rows).reshape(-1, 6)


def _placement_anchors(reg: Path, manifest) -> dict[str, list[dict]]:
    """Each plot's scan -> ALS edges as register-plot built them, from its placement cache."""
    records, jobs = {}, []
    for f in sorted(glob.glob(str(reg / "placement" / "*.json"))):
        rec = json.loads(Path(f).read_text())
        records[rec["key"]] = rec
        jobs.append(_job(rec["key"], rec["source"], rec["target"]))
    config = RegisterConfig()
    placed = set(placed_poses(jobs, records, config.placement_min_confidence))
    return {p.id: als_anchor_edges(p, jobs, records, placed) for p in manifest.plots}


def _job(key: str, source: str, target: str, src: str = "", tgt: str = "") -> PairJob:
    return PairJob(key, source, target, src, tgt, "tls", "als", None, None, AlignConfig(), 0)


def resolve_register(sim: Path, reg: Path) -> Poses:
    """register-plot's poses solved again from its stored edges (its drop decisions made again)."""
    manifest = load_manifest(sim / "manifest.toml")
    G = graph_from_json(json.loads((reg / "graph.json").read_text()))
    for _u, _v, e in G.edges(data=True):
        e["dropped"] = False
    anchors = _placement_anchors(reg, manifest) if RegisterConfig().als_anchors else {}
    scans, plots = {}, {}
    for plot in manifest.plots:
        ref, sol = solve_plot(G, plot, anchors.get(plot.id, []), RegisterConfig())
        plots[plot.id] = {"reference": ref}
        for sid, T in sol.poses.items():
            about = {"sigma_about_plot": sol.about_plot[sid].tolist()}
            scans[sid] = ScanPose(T, plot.id, sol.sigmas[sid], about)
    return Poses(scans, "plot", extra={"plots": plots})


def resolve_tie(sim: Path, geo: Path, plot_poses: Poses) -> Poses:
    """The region solved again on `plot_poses` from GEO's anchor pairs and plot clouds."""
    manifest = load_manifest(sim / "manifest.toml")
    earlier = load_poses(geo / "poses.json")
    config = TieConfig()
    jobs, records, anchors, refs = [], {}, {}, {}
    for f in sorted(glob.glob(str(geo / "pairs" / "*.json"))):
        rec = json.loads(Path(f).read_text())
        plot = rec["source"]
        src, tgt = geo / "plots" / f"{plot}.laz", geo / "plots" / f"{plot}_als.laz"
        jobs.append(_job(rec["key"], plot, "ALS", str(src), str(tgt)))
        records[rec["key"]] = rec
        refs[plot] = plot_poses.extra["plots"][plot]["reference"]
    fits = fit_anchors(jobs, records, config)
    for job in jobs:
        plot = job.source
        anchors[plot] = anchor_of(plot, refs[plot], "whole tile", records[job.key], fits.get(plot))
    tied = Tied(jobs=jobs, records=records, computed=0, anchors=anchors, refs=refs, fits=fits)
    frame = Frame(np.asarray(earlier.extra["offset"], dtype=float))
    G = region_graph(manifest, plot_poses, None, frame, tied)
    sol = solve_region(G, config)
    sigmas = {**sol.sigmas, **georeferenced_sigmas(plot_poses, tied)}
    E = np.eye(4)
    E[:3, 3] = frame.offset
    scans = {
        sid: ScanPose(E @ X, G.nodes[sid].get("plot"), sigmas[sid])
        for sid, X in sol.poses.items()
        if sid != "ALS"
    }
    return Poses(scans, "crs", extra={"anchors": {p: vars(a) for p, a in anchors.items()}})


def _share(z: np.ndarray) -> str:
    if not z.size:
        return "-"
    return f"{100 * np.mean(z < 1):.0f} % / {100 * np.mean(z < 2):.0f} %"


def row(label: str, frame: str, z: np.ndarray) -> str:
    return (
        f"| {label} | {frame} | {len(z)} | {_share(z[:, 3:])} | {_share(z[:, :3])} |"
        f" {np.max(z[:, 3:], initial=0):.1f} / {np.max(z[:, :3], initial=0):.1f} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="SIM:REG[:GEO]")
    ap.add_argument("--resolve", action="store_true", help="solve again from the stored edges")
    a = ap.parse_args()
    print(
        "| run | frame | scans | translation within 1 / 2 sigma | rotation within 1 / 2 sigma"
        " | worst (sigmas): translation / rotation |"
    )
    print("|---|---|---|---|---|---|")
    every: dict[str, list[np.ndarray]] = {"plot": [], "georeferenced": []}
    for spec in a.runs:
        sim, reg, *geo = (Path(p) for p in spec.split(":"))
        truth = _truth(sim)
        plot_poses = resolve_register(sim, reg) if a.resolve else load_poses(reg / "poses.json")
        cases = [("plot", plot_poses)]
        if geo:
            cases.append(
                (
                    "georeferenced",
                    resolve_tie(sim, geo[0], plot_poses)
                    if a.resolve
                    else load_poses(geo[0] / "poses.json"),
                )
            )
        for frame, poses in cases:
            z = normalised_errors(poses, truth)
            every[frame].append(z)
            print(row(sim.name if sim.name != "sim" else sim.parent.name, frame, z))
    for frame, zs in every.items():
        if zs:
            print(row("**all**", frame, np.vstack(zs)))
    for frame, zs in every.items():
        if zs:
            z = np.vstack(zs)
            within = " ".join(f"{100 * np.mean(z[:, k] < 1):.0f}" for k in range(6))
            print(f"{frame}: share within 1 sigma by axis (rx ry rz tx ty tz): {within} %")


if __name__ == "__main__":
    main()

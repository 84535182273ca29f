"""Plot and region registration against the simulator's ground truth.

    python benchmarks/bench_register.py --preset paper --workdir /tmp/bench_register
    python benchmarks/bench_register.py --preset region --workdir /tmp/bench_register
    python benchmarks/bench_register.py --preset large --points-per-scan 60000 --jobs 2 --no-tie

Simulates the preset (once; reused when the folder exists), runs register-plot (pairs cached in
WORKDIR/<preset>/reg/pairs, so a re-run only re-does the pose graph), prints each scan's pose error
against ground truth in the plot frame (inv(GT_ref) @ GT_k), then injects a 2 m / 10 deg wrong edge
into the registered graph and re-optimises, then runs tie-to-als and prints each scan's error in
the ALS CRS. Timings per stage at the end.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gtsam
import numpy as np

from plotmosaic.graph.executor import Workers
from plotmosaic.graph.posegraph import graph_from_json, inverse, optimise, pose_error
from plotmosaic.poses import load_poses
from plotmosaic.simulate.run import simulate
from plotmosaic.stages.register_plot import register_plot
from plotmosaic.stages.tie_to_als import tie_to_als


def errors_in_plot_frame(poses, truth, plots) -> list[tuple]:
    rows = []
    for p in plots:
        for sid in p.scans:
            if sid not in poses.scans:
                rows.append((p.plot, sid, None, None))
                continue
            expected = inverse(truth.transform(p.reference)) @ truth.transform(sid)
            rows.append((p.plot, sid, *pose_error(poses.transform(sid), expected)))
    return rows


def show(title: str, rows: list[tuple], bound_cm: float, bound_deg: float) -> bool:
    print(f"\n{title}  (bound {bound_cm:g} cm / {bound_deg:g} deg)")
    print(f"{'plot':6} {'scan':10} {'rot (deg)':>10} {'trans (cm)':>11}")
    ok = True
    for plot, sid, rot, trans in rows:
        if rot is None:
            print(f"{plot:6} {sid:10} {'unplaced':>10}")
            ok = False
            continue
        within = rot <= bound_deg and trans * 100 <= bound_cm
        ok &= within
        print(
            f"{plot:6} {sid:10} {rot:10.4f} {trans * 100:11.2f}{'' if within else '  OUT OF BOUND'}"
        )
    print("all within bound" if ok else "NOT all within bound")
    return ok


def inject_wrong_edge(reg_dir: Path, truth, plots) -> None:
    """Perturb one kept edge of the first plot by 2 m / 10 deg, re-optimise, report what was dropped."""
    G = graph_from_json(json.loads((reg_dir / "graph.json").read_text()))
    p = plots[0]
    sub = G.subgraph(p.scans)
    for _, _, e in sub.edges(data=True):
        e["dropped"] = False
        e.pop("drop_reason", None)
    u, v, e = sorted(sub.edges(data=True), key=lambda t: -t[2]["weight"])[0]  # the strongest edge
    e["transform"] = (
        e["transform"]
        @ gtsam.Pose3(gtsam.Rot3.Rz(np.radians(10)), np.array([2.0, 0.0, 0.0])).matrix()
    )
    sol = optimise(sub, p.reference)
    wrong = (e["source"], e["target"])
    print(f"\ninjected a 2 m / 10 deg error into edge {wrong[0]} -> {wrong[1]} of plot {p.plot}")
    print(
        "dropped:",
        ", ".join(f"{d['source']} -> {d['target']} ({d['reason']})" for d in sol.dropped)
        or "nothing",
    )
    print(
        "wrong edge flagged and dropped:",
        any((d["source"], d["target"]) == wrong for d in sol.dropped),
    )
    rows = []
    for sid in p.scans:
        if sid not in sol.poses:
            rows.append((p.plot, sid, None, None))
            continue
        expected = inverse(truth.transform(p.reference)) @ truth.transform(sid)
        rows.append((p.plot, sid, *pose_error(sol.poses[sid], expected)))
    show("poses with the wrong edge injected (plot frame)", rows, 2.0, 0.1)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_register"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=None)
    ap.add_argument("--no-tie", action="store_true", help="skip tie-to-als")
    ap.add_argument(
        "--points-per-scan", type=int, default=None, help="simulate with this many points a scan"
    )
    args = ap.parse_args()

    root = args.workdir / args.preset
    timings = {}
    t = time.perf_counter()
    if (root / "sim" / "manifest.toml").is_file():
        sim_manifest, gt_path = root / "sim" / "manifest.toml", root / "sim" / "ground_truth.json"
    else:
        extra = {} if args.points_per_scan is None else {"points_per_scan": args.points_per_scan}
        sim = simulate(root / "sim", args.preset, seed=args.seed, **extra)
        sim_manifest, gt_path = sim.manifest_path, sim.ground_truth_path
    timings["simulate"] = time.perf_counter() - t
    truth = load_poses(gt_path)

    t = time.perf_counter()
    reg = register_plot(sim_manifest, root / "reg", workers=Workers(jobs=args.jobs), seed=args.seed)
    timings["register-plot"] = time.perf_counter() - t
    print(
        f"\nregister-plot: {reg.pairs} pairs ({reg.computed} registered now), {len(reg.failed)} failed, "
        f"dropped: {[d for p in reg.plots for d in p.solution.dropped]}, unplaced: {reg.unplaced}"
    )
    pair_seconds = [
        r["seconds"]
        for r in map(lambda f: json.loads(f.read_text()), (root / "reg" / "pairs").glob("*.json"))
        if "seconds" in r
    ]
    pairs_of = {}
    for u, v in reg.graph.edges():
        pairs_of[u] = pairs_of.get(u, 0) + 1
        pairs_of[v] = pairs_of.get(v, 0) + 1
    for f in reg.graph.graph.get("failed", []):
        pairs_of[f["source"]] = pairs_of.get(f["source"], 0) + 1
        pairs_of[f["target"]] = pairs_of.get(f["target"], 0) + 1
    n_scans = reg.graph.number_of_nodes()
    print(
        f"pairs per scan: {reg.pairs / max(1, n_scans):.2f} (at most {max(pairs_of.values(), default=0)} for one scan), "
        f"{n_scans} scans; all pairs would be {n_scans * (n_scans - 1) // 2}"
    )
    placement = reg.poses.extra.get("placement")
    if placement:
        print(
            f"placed on the ALS first: {sum(v == 'ok' for v in placement.values())} of {len(placement)} scans"
        )
    if pair_seconds:
        print(
            f"pair time: median {np.median(pair_seconds):.1f} s, total {np.sum(pair_seconds):.0f} s (CPU-side, as run)"
        )
    show(
        "register-plot poses vs ground truth (plot frame)",
        errors_in_plot_frame(reg.poses, truth, reg.plots),
        2.0,
        0.1,
    )
    inject_wrong_edge(root / "reg", truth, reg.plots)

    if not args.no_tie:
        t = time.perf_counter()
        tie = tie_to_als(
            sim_manifest,
            root / "reg" / "poses.json",
            root / "geo",
            seed=args.seed,
            workers=Workers(jobs=args.jobs),
        )
        timings["tie-to-als"] = time.perf_counter() - t
        for a in tie.anchors:
            fit = a.fit or {}
            print(
                f"anchor {a.plot}: {a.status} fitness {a.fitness} inlier RMSE {a.inlier_rmse} "
                f"fine margin {a.fine_margin} ALS - TLS median {fit.get('als_offset_median_m')} m ({a.crop})"
            )
        rows = []
        for sid in truth.scans:
            pose = tie.poses.scans.get(sid)
            rows.append(
                (
                    truth.scans[sid].plot,
                    sid,
                    *(pose_error(pose.transform, truth.transform(sid)) if pose else (None, None)),
                )
            )
        show("tie-to-als poses vs ground truth (ALS CRS)", rows, 5.0, 0.2)

    print(
        "\ntimings (wall): "
        + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items())
        + f", total {sum(timings.values()) - timings['simulate']:.1f} s without simulation"
    )


if __name__ == "__main__":
    main()

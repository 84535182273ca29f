"""Simulator speed and output figures.

    python benchmarks/bench_simulate.py            # small preset + one 8M-point TLS scan
    python benchmarks/bench_simulate.py --paper    # + the whole paper preset, overlaps, pictures

Prints: small preset wall time and points per scan; paper world build time and triangles; time of
one 8M-point BLK360-like scan (ray casting, and writing the LAZ); with --paper the overlap fraction
between the centre scan and each corner scan (share of the centre scan's points within 5 cm / 25 cm
of the corner scan's points, both mapped to UTM by their ground-truth poses) and the ALS density.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from plotmosaic.io.las import write_cloud
from plotmosaic.poses import load_poses
from plotmosaic.simulate.run import make_config, scanner_pose, simulate
from plotmosaic.simulate.scene import Scene, build_world
from plotmosaic.simulate.stats import overlap_fraction, scan_in_world
from plotmosaic.simulate.tls import scan_tls


def bench_small(tmp: Path) -> None:
    t = time.perf_counter()
    r = simulate(tmp / "small", "small", seed=0)
    wall = time.perf_counter() - t
    tls = [v for k, v in r.points.items() if k != "als"]
    print(
        f"small preset: {wall:.1f} s wall ({', '.join(f'{k} {v:.1f}' for k, v in r.seconds.items())}); "
        f"points per scan {min(tls):,}-{max(tls):,}; ALS {r.points['als']:,} points, {r.als_density:.2f} pts/m2 "
        f"(requested {r.config.als.density_per_m2})"
    )


def bench_big_scan(tmp: Path, points: int) -> None:
    cfg = make_config("paper", points_per_scan=points)
    t, c = time.perf_counter(), time.process_time()
    world = build_world(cfg, 0)
    t_world, c_world = time.perf_counter() - t, time.process_time() - c
    counts = np.bincount(world.mesh.labels, minlength=4)
    t, c = time.perf_counter(), time.process_time()
    scene = Scene(world.mesh)
    pose = scanner_pose(world, world.sites[0].xy, np.random.default_rng(0))
    scene.cast(pose[:3, 3], np.array([[1.0, 0, 0]]))  # builds the BVH
    t_bvh, c_bvh = time.perf_counter() - t, time.process_time() - c
    t, c = time.perf_counter(), time.process_time()
    cloud = scan_tls(scene, pose, cfg.tls, np.random.default_rng(1))
    t_scan, c_scan = time.perf_counter() - t, time.process_time() - c
    t, c = time.perf_counter(), time.process_time()
    write_cloud(tmp / "big.laz", cloud)
    t_write, c_write = time.perf_counter() - t, time.process_time() - c
    size = (tmp / "big.laz").stat().st_size / 1e6
    print(
        f"paper world: {t_world:.1f} s to build, {len(world.mesh):,} triangles "
        f"(ground {counts[0]:,}, woody {counts[1]:,}, foliage {counts[2]:,}, understory {counts[3]:,}), "
        f"{len(world.vegetation.trees)} trees; BVH {t_bvh:.1f} s (CPU: world {c_world:.1f} s, BVH {c_bvh:.1f} s)"
    )
    print(
        f"one TLS scan: {len(cloud):,} points (asked {points:,}) in {t_scan:.1f} s ray casting + {t_write:.1f} s "
        f"writing LAZ ({size:.0f} MB) = {t_scan + t_write:.1f} s wall; with the world {t_world + t_bvh + t_scan + t_write:.1f} s"
    )
    print(
        f"one TLS scan CPU time (all threads): ray casting {c_scan:.1f} s, LAZ {c_write:.1f} s; "
        f"wall on 2 free cores >= {(c_scan + c_write) / 2:.1f} s; load average now {os.getloadavg()[0]:.1f}"
    )


def bench_paper(tmp: Path, seed: int, figures_to: Path | None) -> None:
    t = time.perf_counter()
    r = simulate(tmp / "paper", "paper", seed=seed, figures=True)
    wall = time.perf_counter() - t
    tls = {k: v for k, v in r.points.items() if k != "als"}
    print(
        f"paper preset: {wall:.1f} s wall ({', '.join(f'{k} {v:.1f}' for k, v in r.seconds.items())}); "
        f"points per scan {', '.join(f'{k} {v:,}' for k, v in tls.items())}"
    )
    print(
        f"paper ALS: {r.points['als']:,} points over {np.ptp(r.als_extent[::2]):.0f} x {np.ptp(r.als_extent[1::2]):.0f} m, "
        f"{r.als_density:.2f} pts/m2 (requested {r.config.als.density_per_m2})"
    )
    truth = load_poses(r.ground_truth_path)
    centre = scan_in_world(r.scan_paths["P1-S0"], truth.transform("P1-S0"))
    for sid in ["P1-S1", "P1-S2", "P1-S3", "P1-S4"]:
        corner = scan_in_world(r.scan_paths[sid], truth.transform(sid))
        d = np.linalg.norm(truth.transform(sid)[:2, 3] - truth.transform("P1-S0")[:2, 3])
        print(
            f"overlap P1-S0 -> {sid} ({d:.1f} m apart): {overlap_fraction(centre, corner, 0.05):.3f} within 5 cm, "
            f"{overlap_fraction(centre, corner, 0.25):.3f} within 25 cm"
        )
    if figures_to:
        figures_to.mkdir(parents=True, exist_ok=True)
        for fig in r.figures:
            shutil.copy(fig, figures_to / fig.name)
        print(f"pictures copied to {figures_to}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--points", type=int, default=8_000_000, help="points of the single big TLS scan"
    )
    ap.add_argument("--paper", action="store_true", help="also simulate the whole paper preset")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--figures-to", type=Path, default=None, help="copy the paper pictures here (e.g. docs/)"
    )
    args = ap.parse_args()
    print(f"cores available: {len(os.sched_getaffinity(0))}")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        bench_small(tmp)
        bench_big_scan(tmp, args.points)
        if args.paper:
            bench_paper(tmp, args.seed, args.figures_to)


if __name__ == "__main__":
    main()

"""Breast-height ring spread at the true poses and with one scan moved by 5 cm / 0.2 deg, on full points or voxel centroids.

    python benchmarks/slice_on_prepared.py SIM_DIR --voxel 0.05   # as register-plot's prepared clouds (delta0)
    python benchmarks/slice_on_prepared.py SIM_DIR --voxel 0      # the scans' own points

SIM_DIR is a `plotmosaic simulate` folder (ground_truth.json, P1/*.laz). Prints, per pose set, the
stems found, the median ring spread and that of the stems the moved scan sees.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from plotmosaic.align.voxel import voxel_centroids
from plotmosaic.bench.protocol import params_to_matrix
from plotmosaic.config.report import ReportConfig
from plotmosaic.io.las import read_cloud
from plotmosaic.poses import load_poses
from plotmosaic.report.build import collect
from plotmosaic.report.slice import ring_spread


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sim", type=Path)
    ap.add_argument(
        "--voxel",
        type=float,
        default=0.05,
        help="voxel centroids of this size (m); 0: the points as read",
    )
    ap.add_argument("--moved", default="P1-S2")
    args = ap.parse_args()
    truth = load_poses(args.sim / "ground_truth.json")
    poses = {k: v.transform for k, v in truth.scans.items()}
    paths = {k: args.sim / v.plot / f"{k}.laz" for k, v in truth.scans.items()}
    raw = {}
    for p in paths.values():
        xyz = read_cloud(p, attributes=False).xyz
        raw[p] = voxel_centroids(xyz, args.voxel) if args.voxel > 0 else xyz
    off = dict(poses)
    off[args.moved] = poses[args.moved] @ params_to_matrix([0, 0, 0.2, 0.03, 0.04, 0])
    for name, P in (("true poses", poses), (f"{args.moved} moved 5 cm / 0.2 deg", off)):
        v = collect("P1", sorted(P), paths, P, raw.__getitem__, ReportConfig(), 0)
        print(
            f"voxel {args.voxel:g} m, {name}: {len(v.stems)} stems, median ring spread {ring_spread(v.stems) * 100:.2f} cm, "
            f"stems {args.moved} sees {ring_spread(v.stems, args.moved) * 100:.2f} cm; "
            f"slice points per scan {', '.join(str(len(x)) for x in v.slices.values())}"
        )


if __name__ == "__main__":
    main()

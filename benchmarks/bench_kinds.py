"""Sensor-kind detection (align/kinds.py) on every real input and the simulator's presets: the figures
each kind is decided on, against the thresholds of [align.kinds].

    nice -n 10 python benchmarks/bench_kinds.py --sim /tmp/kinds_sim --out benchmarks/results/kinds.md

Real inputs: ../shared/data (spanner clips, the TreeLS plot, the E57 scans with enough points).
Simulated: the `small` preset (seed 0, its own scan density) and `paper`, `grassland`, `understorey`
at 200k points a scan (seed 1), every TLS scan, the ALS tile, and each plot's scans merged in the plot
frame by the ground truth (a merged tripod plot). Simulations are kept in --sim and reused.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from plotmosaic.align.kinds import detect_kind
from plotmosaic.config.align import AlignConfig
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.las import read_cloud
from plotmosaic.poses import load_poses
from plotmosaic.simulate.run import simulate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
REAL = [
    ("spanner/ALS_Clip.laz", "als"),
    ("spanner/UAS_Clip.laz", "uls"),
    ("spanner/MLS_Clip.laz", "mls"),
    ("treels/pine_plot.laz", "tls"),
    ("e57/pumpAVisualReferenceImage.e57", "tls"),
    ("e57/bunnyDouble.e57", "tls"),
    ("e57/ColouredCubeFloat.e57", "tls"),
]
PRESETS = [("small", 0, None), ("paper", 1, 200_000), ("grassland", 1, 200_000)]
PRESETS += [("understorey", 1, 200_000)]


def _sim(root: Path, preset: str, seed: int, points: int | None):
    out = root / f"{preset}-{seed}"
    return simulate(out, preset, seed=seed, points_per_scan=points)


def clouds(root: Path):
    """(name, expected kind, xyz) of every input measured."""
    for rel, kind in REAL:
        if (DATA / rel).is_file():
            yield rel, kind, read_cloud(DATA / rel, attributes=False).xyz
    for preset, seed, points in PRESETS:
        sim = _sim(root, preset, seed, points)
        truth = load_poses(sim.ground_truth_path)
        merged = []
        for scan_id, path in sim.scan_paths.items():
            xyz = read_cloud(path, attributes=False).xyz
            yield f"sim {preset} {scan_id}", "tls", xyz
            T = truth.transform(scan_id)
            merged.append(xyz @ T[:3, :3].T + T[:3, 3])
        yield f"sim {preset} scans merged", "tls", np.vstack(merged)
        for path in sim.als_paths:
            yield f"sim {preset} ALS tile", "als", read_cloud(path, attributes=False).xyz


def _fmt(v) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return "-" if math.isnan(v) else f"{v:.3g}"
    return str(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sim", type=Path, required=True, help="folder for the simulations (reused)")
    ap.add_argument("--out", type=Path, help="markdown file whose table is replaced (prose kept)")
    args = ap.parse_args()
    cfg = AlignConfig()
    cols = ("density_per_m2", "coverage", "dense_share", "understorey_share", "ground_share")
    rows = [
        "| input | expected | detected | pts/m2 | coverage | densest 5 % | understorey | ground | station |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    wrong = 0
    for name, expected, xyz in clouds(args.sim):
        found = detect_kind(xyz, cfg.kinds, cfg.viewpoint)
        e = found.evidence
        wrong += found.kind != expected
        figures = " | ".join(_fmt(getattr(e, c)) for c in cols)
        mark = "" if found.kind == expected else " **wrong**"
        rows.append(f"| {name} | {expected} | {found.kind}{mark} | {figures} | {_fmt(e.station)} |")
        print(rows[-1], flush=True)
    k = cfg.kinds
    rows += [
        "",
        f"{wrong} wrong. Thresholds ([align.kinds]): airborne = coverage >= {k.min_airborne_coverage} "
        f"and (densest 5 % <= {k.max_airborne_dense_share} or understorey <= "
        f"{k.max_airborne_understorey}); uls from {k.min_uls_density:g} pts/m2; ground-based: mls "
        f"when ground <= {k.max_mls_ground_share}, else tls; fewer than {k.min_points} points or "
        f"narrower than {k.min_extent_m} m: too small to tell (tls).",
    ]
    if args.out:  # the table replaces the one in --out; the prose above it stays
        old = args.out.read_text() if args.out.is_file() else ""
        prose = old[: old.find(rows[0])] if rows[0] in old else ""
        write_text_atomic(args.out, prose + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()

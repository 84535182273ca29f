"""Memory and result of `plotmosaic align` on a pair whose source carries one stray point far away.

For a simulated plot (made here, or --sim DIR), the source scan is written twice at 1 cm LAS scale
(the scale a 10,000 km coordinate needs to fit the LAS integers): as it is, and with one extra point
--distance-km away. Each is aligned onto the target by a whole `plotmosaic align` process under
/usr/bin/time -v; the table shows exit code, wall time, peak memory and the pose error against the
simulator's ground truth, beside the time to just read both inputs.

    python benchmarks/bench_stray.py --preset small --workdir /tmp/stray_small
    python benchmarks/bench_stray.py --preset paper --points-per-scan 8000000 --workdir /tmp/stray_8m
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np

from plotmosaic.io.las import read_cloud
from plotmosaic.poses import load_poses

SCALE = 0.01  # 1 cm: +-21,474 km fit the LAS int32 coordinates


def write_source(src: Path, dst: Path, distance_m: float | None) -> Path:
    """`src` at 1 cm scale, with one more point `distance_m` away in x when given."""
    las = laspy.read(src)
    xyz = np.column_stack([las.x, las.y, las.z])
    if distance_m is not None:
        xyz = np.vstack([xyz, xyz[:1] + [distance_m, 0.0, 0.0]])
    header = laspy.LasHeader(
        point_format=las.header.point_format.id, version=str(las.header.version)
    )
    header.scales = np.array([SCALE] * 3)
    header.offsets = np.round(np.asarray(las.header.offsets) / 1000.0) * 1000.0
    out = laspy.LasData(header)
    out.x, out.y, out.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    dst.parent.mkdir(parents=True, exist_ok=True)
    out.write(dst)
    return dst


def timed_align(src: Path, tgt: Path, out: Path) -> dict:
    cmd = [
        "/usr/bin/time",
        "-v",
        sys.executable,
        "-m",
        "plotmosaic",
        "align",
        str(src),
        str(tgt),
        "--out",
        str(out),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", proc.stderr)
    seconds = (
        sum(float(p) * 60**i for i, p in enumerate(reversed(wall.group(1).split(":"))))
        if wall
        else float("nan")
    )
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error")]
    return {
        "code": proc.returncode,
        "peak_gb": int(rss.group(1)) / 1e6 if rss else float("nan"),
        "seconds": seconds,
        "error": errors[0] if errors else "",
    }


def pose_error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    D = np.linalg.inv(T_true) @ T
    return float(np.linalg.norm(D[:3, 3])), float(
        np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--sim", type=Path, help="an existing `plotmosaic simulate` folder (else one is made)"
    )
    ap.add_argument("--preset", default="small")
    ap.add_argument("--points-per-scan", type=int)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/bench_stray"))
    ap.add_argument("--source", default="P1-S1")
    ap.add_argument("--target", default="P1-S0")
    ap.add_argument("--distance-km", type=float, default=10_000.0)
    args = ap.parse_args()

    sim = args.sim
    if sim is None:
        sim = args.workdir / "sim"
        if not (sim / "manifest.toml").is_file():
            cmd = [
                sys.executable,
                "-m",
                "plotmosaic",
                "simulate",
                str(sim),
                "--preset",
                args.preset,
                "--seed",
                str(args.seed),
            ]
            if args.points_per_scan:
                cmd += ["--points-per-scan", str(args.points_per_scan)]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    truth = load_poses(sim / "ground_truth.json")
    T_true = np.linalg.inv(truth.transform(args.target)) @ truth.transform(args.source)
    scan = {p.stem: p for p in sim.rglob("*.laz")}
    tgt = scan[args.target]
    clean = write_source(scan[args.source], args.workdir / "clean.laz", None)
    stray = write_source(scan[args.source], args.workdir / "stray.laz", args.distance_km * 1000.0)
    t0 = time.perf_counter()
    n_src, n_tgt = len(read_cloud(stray, attributes=False)), len(read_cloud(tgt, attributes=False))
    read_s = time.perf_counter() - t0

    print(
        f"pair {args.source} -> {args.target} of {sim} ({n_src:,} / {n_tgt:,} points); reading both: {read_s:.1f} s"
    )
    print("| source | exit | wall (s) | peak memory (GB) | error vs truth (cm / deg) | message |")
    print("|---|---|---|---|---|---|")
    for name, src in (("as is", clean), (f"+1 point {args.distance_km:g} km away", stray)):
        out = args.workdir / f"{src.stem}.json"
        out.unlink(missing_ok=True)
        r = timed_align(src, tgt, out)
        err = "-"
        if r["code"] == 0:
            dt, dr = pose_error(np.asarray(json.loads(out.read_text())["transform"]), T_true)
            err = f"{dt * 100:.2f} / {dr:.3f}"
        print(
            f"| {name} | {r['code']} | {r['seconds']:.1f} | {r['peak_gb']:.2f} | {err} | {r['error']} |"
        )


if __name__ == "__main__":
    main()

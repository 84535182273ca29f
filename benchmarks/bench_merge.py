"""Benchmark `plotmosaic merge`: throughput (points/s) and peak memory on large synthetic scans.

Generates SCANS x POINTS synthetic TLS scans as LAZ (PF 7: intensity, returns, classification,
gps_time, RGB) in scanner frames with UTM poses (generation is not timed, written chunk-wise), then
runs, each as a whole process under /usr/bin/time -v: a read-only pass over the inputs, `plotmosaic
merge` plain and (with --voxel) voxel-thinned; reports wall, CPU, points/s and peak RSS.

    .venv/bin/python benchmarks/bench_merge.py                  # 5 x 8M points
    .venv/bin/python benchmarks/bench_merge.py --scans 2 --points 1000000 --voxel 0.05
    nice -n 10 .venv/bin/python benchmarks/bench_merge.py --scans 25 --points 8000000 --voxel 0.01 --no-plain  # 200M
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import laspy
import numpy as np
from pyproj import CRS

from plotmosaic.io.las import make_header, make_record
from plotmosaic.manifest import Manifest, Plot, Scan, dump_manifest
from plotmosaic.poses import Poses, ScanPose

UTM = "EPSG:32612"
GEN_CHUNK = 2_000_000


def synthetic_scan(path: Path, n: int, seed: int) -> None:
    """A TLS-like scan: points swept by azimuth, dense near the scanner, smooth attributes (so LAZ
    compresses about as well as on real scans, not as badly as on white noise)."""
    rng = np.random.default_rng(seed)
    header = make_header(
        [
            "intensity",
            "return_number",
            "number_of_returns",
            "classification",
            "gps_time",
            "red",
            "green",
            "blue",
        ]
    )
    with laspy.open(path, mode="w", header=header, do_compress=True) as writer:
        for start in range(0, n, GEN_CHUNK):
            m = min(GEN_CHUNK, n - start)
            azimuth = np.sort(rng.uniform(0, 2 * np.pi, m)) / (n / m) + 2 * np.pi * start / n
            rng_m = 2.0 + rng.exponential(12.0, m).clip(0, 60)
            elev = rng.uniform(-0.6, 1.2, m)
            xyz = np.column_stack(
                [rng_m * np.cos(azimuth), rng_m * np.sin(azimuth), 1.5 + rng_m * np.tan(elev) * 0.5]
            )
            nret = rng.integers(1, 4, m).astype(np.uint8)
            shade = (20000 + 30000 * np.exp(-rng_m / 20)).astype(np.uint16)
            attrs = {
                "intensity": (shade + rng.integers(0, 2000, m)).astype(np.uint16),
                "number_of_returns": nret,
                "return_number": np.minimum(rng.integers(1, 4, m), nret).astype(np.uint8),
                "classification": np.where(xyz[:, 2] < 0.3, 2, 5).astype(np.uint8),
                "gps_time": 1e5
                + seed * 1000
                + np.linspace(start, start + m, m, endpoint=False) * 1e-5,
                "red": shade,
                "green": (shade * 0.9).astype(np.uint16),
                "blue": (shade * 0.7).astype(np.uint16),
            }
            writer.write_points(make_record(header, xyz, attrs))


def make_inputs(root: Path, scans: int, points: int) -> Path:
    rng = np.random.default_rng(0)
    poses, entries = {}, []
    for k in range(scans):
        path = root / f"scan_{k}.laz"
        if not path.exists() or laspy.open(path).header.point_count != points:
            synthetic_scan(path, points, seed=k)
        yaw = rng.uniform(-np.pi, np.pi)
        T = np.eye(4)
        T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        T[:3, 3] = [470_000 + 20 * k, 3_810_000 + 15 * k, 2_100]
        poses[f"s{k}"] = ScanPose(T, plot="P1")
        entries.append(Scan(id=f"s{k}", path=Path(path.name)))
    (root / "manifest.toml").write_text(
        dump_manifest(Manifest(plots=[Plot(id="P1", crs=UTM, scans=entries)]))
    )
    Poses(poses, frame="crs", crs=CRS.from_user_input(UTM).to_wkt()).save(root / "poses.json")
    return root / "manifest.toml"


def timed(cmd: list[str]) -> dict:
    """Run `cmd` under /usr/bin/time -v (the whole process): wall, CPU and peak RSS."""
    with tempfile.NamedTemporaryFile(suffix=".time") as rep, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        proc = subprocess.run(
            ["/usr/bin/time", "-v", "-o", rep.name, *cmd], stdout=subprocess.DEVNULL, stderr=err
        )
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            err.seek(0)
            sys.exit(f"{' '.join(cmd[:4])} ... failed: {err.read().decode().strip()}")
        fields = dict(
            line.strip().rsplit(": ", 1)
            for line in Path(rep.name).read_text().splitlines()
            if ": " in line
        )
    return {
        "wall_s": wall,
        "cpu_s": float(fields["User time (seconds)"]) + float(fields["System time (seconds)"]),
        "peak_rss_mb": int(fields["Maximum resident set size (kbytes)"]) / 1024,
    }


READ_ONLY = """
import sys
from pathlib import Path
from plotmosaic.manifest import load_manifest
from plotmosaic.stages.merge import read_records
from plotmosaic.config.merge import CHUNK_SIZE
m = load_manifest(sys.argv[1])
n = sum(len(c) for s in m.scans for c in read_records(m.resolve(s.path), CHUNK_SIZE))
print(n)
"""


def run_read(root: Path) -> dict:
    """Time to just read (decompress) every input, chunk by chunk, in a child process."""
    return timed([sys.executable, "-c", READ_ONLY, str(root / "manifest.toml")])


def run_merge(root: Path, extra: list[str]) -> dict:
    out = root / "merged.laz"
    cmd = [
        sys.executable,
        "-m",
        "plotmosaic",
        "merge",
        str(root / "manifest.toml"),
        "--poses",
        str(root / "poses.json"),
        "--out",
        str(out),
        "--force",
        *extra,
    ]
    r = timed(cmd)
    side = json.loads(out.with_name(out.name + ".json").read_text())
    return {
        **r,
        "merge_s": side["seconds"],
        "points_in": side["points_in"],
        "points_out": side["points_out"],
        "out_mb": out.stat().st_size / 1e6,
    }


def profile_merge(root: Path) -> None:
    """Where the CPU time goes, by difference of three in-process passes over the same inputs:
    read only, read + pose (numpy), full merge (+ LAZ compression and writing)."""
    from threadpoolctl import threadpool_limits

    from plotmosaic.config.merge import MergeConfig
    from plotmosaic.manifest import load_manifest
    from plotmosaic.poses import load_poses
    from plotmosaic.stages.merge import merge_scans, plan_sources, posed_record, read_records

    manifest, poses = load_manifest(root / "manifest.toml"), load_poses(root / "poses.json")
    config = MergeConfig(force=True)
    sources, _, _ = plan_sources(manifest, poses, config)
    header = laspy.open(root / "merged.laz").header  # same scaling as the merge's own header

    def cpu_of(work) -> float:
        t0 = time.process_time()
        with threadpool_limits(1, user_api="blas"):
            work()
        return time.process_time() - t0

    def read():
        for s in sources:
            for _ in read_records(s.path, config.chunk_size):
                pass

    def read_pose():
        for s in sources:
            for chunk in read_records(s.path, config.chunk_size):
                posed_record(s, chunk, header, None, None)

    n = sum(s.info.point_count for s in sources)
    t_read = cpu_of(read)
    t_pose = cpu_of(read_pose)
    t_all = cpu_of(
        lambda: merge_scans(manifest, poses, root / "profiled.laz", config, progress=False)
    )
    (root / "profiled.laz").unlink()
    (root / "profiled.laz.json").unlink()
    print(
        f"CPU split of an in-process merge ({n:,} points, {t_all:.1f} s CPU = {t_all / n * 1e6:.2f} us/point):"
    )
    for label, cpu in [
        ("read + LAZ decompress", t_read),
        ("pose + build records", t_pose - t_read),
        ("LAZ compress + write", t_all - t_pose),
    ]:
        print(
            f"  {label:24s} {cpu:6.1f} s  {cpu / n * 1e6:.3f} us/point  {100 * cpu / t_all:4.0f} %"
        )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--scans", type=int, default=5)
    ap.add_argument("--points", type=int, default=8_000_000)
    ap.add_argument("--voxel", type=float, default=None, help="also time a run with voxel thinning")
    ap.add_argument(
        "--memory-mb", type=int, default=None, help="merge --memory-mb for the voxel run"
    )
    ap.add_argument("--no-plain", action="store_true", help="skip the plain (unthinned) merge")
    ap.add_argument(
        "--workdir", type=Path, default=None, help="keep (and reuse) the generated scans here"
    )
    ap.add_argument(
        "--generate-only", action="store_true", help="only write the inputs (with --workdir)"
    )
    ap.add_argument(
        "--profile",
        action="store_true",
        help="also profile one merge in-process (CPU time per stage)",
    )
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench_merge_") as tmp:
        root = args.workdir or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        make_inputs(root, args.scans, args.points)
        print(
            f"inputs: {args.scans} scans x {args.points:,} points (PF7, LAZ) in {root} ({time.perf_counter() - t0:.0f} s, not timed)"
        )
        if args.generate_only:
            return
        print(
            f"load average before merging: {', '.join(f'{v:.1f}' for v in os.getloadavg())} (2 cores)"
        )
        r = run_read(root)
        print(
            f"read only: wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s, peak RSS {r['peak_rss_mb']:.0f} MB"
        )
        runs = [] if args.no_plain else [("plain", [])]
        runs += (
            [
                (
                    f"voxel {args.voxel:g} m",
                    [
                        "--voxel",
                        str(args.voxel),
                        *(["--memory-mb", str(args.memory_mb)] if args.memory_mb else []),
                    ],
                )
            ]
            if args.voxel
            else []
        )
        for name, extra in runs:
            r = run_merge(root, extra)
            print(
                f"merge {name}: {r['points_in']:,} -> {r['points_out']:,} points, wall {r['wall_s']:.1f} s "
                f"(merge itself {r['merge_s']:.1f} s), {r['points_in'] / r['wall_s'] / 1e6:.2f} M points/s wall, "
                f"{r['points_in'] / r['merge_s'] / 1e6:.2f} M points/s merge; CPU {r['cpu_s']:.1f} s "
                f"({r['cpu_s'] / r['points_in'] * 1e6:.2f} us/point, i.e. {r['points_in'] / r['cpu_s'] * 2 / 1e6:.2f} M points/s if 2 cores were free); "
                f"peak RSS {r['peak_rss_mb']:.0f} MB; output {r['out_mb']:.0f} MB"
            )
        if args.profile:
            profile_merge(root)


if __name__ == "__main__":
    main()

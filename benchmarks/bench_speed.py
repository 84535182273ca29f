"""Speed of whole processes beside their read floor: one table anyone can rerun.

Each case runs the real command line in a child process (nothing imported here is timed) and reports
wall time, CPU time (user + system of the child and its workers) and peak memory, beside the *read
floor*: the same files only read with laspy in a child process of its own. The inputs are simulated
once under `--work` and reused.

    .venv/bin/python benchmarks/bench_speed.py --work /tmp/speed                  # every case
    .venv/bin/python benchmarks/bench_speed.py --work /tmp/speed --cases pair400k,demo

Cases (the targets of the speed issue are in benchmarks/results/speed.md):
  pair400k  `plotmosaic align` of the demo's P1-S1 onto P1-S0 (400k points each) from anywhere
  pair8m    the same at 8M points a scan
  demo      register-plot + tie-to-als + merge on the demo's plot (five 400k scans; simulate excluded)
  plot400k  register-plot alone on the demo's plot (10 pairs: a spanning tree by the global search,
            the loop pairs verified from the poses it implies)
  large1m   register-plot of the `large` preset (36 scans) at 1M points a scan
  large10m  register-plot + tie-to-als + merge of the `large` preset at 10M points a scan (survey
            density: 360M points; not in the default cases), each stage on a row of its own too.
            The simulation takes long and is reused: a link WORK/large10000k -> an existing one
            (`plotmosaic simulate DIR --preset large --points-per-scan 10000000`) skips it.

The chains (demo, large10m) print their total, then one row per stage (its read floor left empty).
Measure on a quiet machine (nothing else running) or compare CPU seconds only. Each case's row
ends with the box gauge: the CPU seconds of fixed numpy / scipy work (KD-tree, FFT, sort) run just
before it, which moves with the machine's speed and not with plotmosaic's code.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

PLOTMOSAIC = [sys.executable, "-m", "plotmosaic"]
READ = "import sys, laspy\nfor p in sys.argv[1:]:\n    laspy.read(p)\n"


@dataclass(frozen=True)
class Run:
    wall_s: float
    cpu_s: float
    peak_mb: float  # the largest child process's peak RSS


# runs the command in a fresh process whose only children are the command's: RUSAGE_CHILDREN is then
# the command's own CPU time and peak memory, however many runs came before
MEASURE = """
import json, resource, subprocess, sys, time
start = time.perf_counter()
subprocess.run(sys.argv[1:], check=True, stdout=subprocess.DEVNULL)
wall = time.perf_counter() - start
r = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps([wall, r.ru_utime + r.ru_stime, r.ru_maxrss / 1024.0]))
"""


def timed(argv: list[str]) -> Run:
    """Run `argv` to the end (it must succeed): its wall, CPU and peak memory."""
    out = subprocess.run(
        [sys.executable, "-c", MEASURE, *argv], check=True, capture_output=True, text=True
    ).stdout
    return Run(*json.loads(out))


def simulated(work: Path, name: str, preset: str, points: int) -> Path:
    """A simulated plot under `work` (made once): its folder."""
    folder = work / name
    if not (folder / "manifest.toml").is_file():
        args = ["simulate", str(folder), "--preset", preset, "--points-per-scan", str(points)]
        subprocess.run([*PLOTMOSAIC, *args], check=True, stdout=subprocess.DEVNULL)
    return folder


# The box's own speed at the moment, from work that does not depend on plotmosaic's code (KD-tree
# queries, FFTs, a sort: the kernels a pair is made of), one thread: this box's speed drifts by up
# to 45 % within the hour, so a case's figures are compared across runs beside their gauge.
GAUGE = """
import time, numpy as np
from scipy import fft
from scipy.spatial import cKDTree
rng = np.random.default_rng(0)
t = time.process_time()
pts = rng.random((1_000_000, 3)) * 50
cKDTree(pts).query(pts[:200_000], k=16, workers=1)
fft.irfft2(fft.rfft2(rng.random((16, 512, 512)), workers=1), workers=1)
np.sort(rng.integers(0, 2**40, 8_000_000))
print(time.process_time() - t)
"""


def gauge() -> float:
    """CPU seconds of the fixed gauge work in a fresh process, now."""
    out = subprocess.run([sys.executable, "-c", GAUGE], check=True, capture_output=True, text=True)
    return float(out.stdout)


def read_floor(paths: list[Path]) -> Run:
    return timed([sys.executable, "-c", READ, *map(str, paths)])


def fresh(out: Path) -> Path:
    """This benchmark's own output folder, emptied: a run over a kept folder would reuse its prepared
    clouds and pair records (register-plot's caches) and skip the work measured."""
    shutil.rmtree(out, ignore_errors=True)
    return out


def pair(work: Path, points: int) -> tuple[Run, Run]:
    sim = simulated(work, f"paper{points // 1000}k", "paper", points)
    src, tgt = sim / "P1" / "P1-S1.laz", sim / "P1" / "P1-S0.laz"
    out = work / f"pair{points // 1000}k.json"
    out.unlink(missing_ok=True)
    run = timed([*PLOTMOSAIC, "align", str(src), str(tgt), "--out", str(out), "--force"])
    return run, read_floor([src, tgt])


def chain(
    work: Path, jobs: int, preset: str = "paper", points: int = 400_000
) -> tuple[Run, Run, dict[str, Run]]:
    """register-plot, tie-to-als and merge on a simulated plot: (total, read floor, each stage)."""
    name = f"{preset}{points // 1000}k"
    sim = simulated(work, name, preset, points)
    manifest = sim / "manifest.toml"
    out = fresh(work / ("demo-chain" if name == "paper400k" else f"{name}-chain"))
    steps = [
        ["register-plot", str(manifest), "--out", str(out / "reg"), "-j", str(jobs), "--force"],
        [
            "tie-to-als",
            str(manifest),
            "--poses",
            str(out / "reg" / "poses.json"),
            "--out",
            str(out / "geo"),
            "-j",
            str(jobs),
            "--force",
        ],
        [
            "merge",
            str(manifest),
            "--poses",
            str(out / "geo" / "poses.json"),
            "--out",
            str(out / "merged.laz"),
            "--force",
        ],
    ]
    runs = {step[0]: timed([*PLOTMOSAIC, *step]) for step in steps}
    total = Run(
        sum(r.wall_s for r in runs.values()),
        sum(r.cpu_s for r in runs.values()),
        max(r.peak_mb for r in runs.values()),
    )
    return total, read_floor(sorted(sim.rglob("*.laz"))), runs


def register(work: Path, jobs: int, preset: str, points: int) -> tuple[Run, Run]:
    """register-plot alone on a simulated plot, beside reading its scans."""
    name = f"{preset}{points // 1000}k"
    sim = simulated(work, name, preset, points)
    out = fresh(work / f"{name}-reg")
    run = timed(
        [*PLOTMOSAIC, "register-plot", str(sim / "manifest.toml"), "--out", str(out)]
        + ["-j", str(jobs), "--force"]
    )
    return run, read_floor(sorted((sim / "P1").glob("*.laz")))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, required=True, help="folder for the simulated inputs")
    ap.add_argument("--cases", default="pair400k,pair8m,demo,plot400k,large1m")
    ap.add_argument("-j", "--jobs", type=int, default=os.cpu_count() or 1)
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    cases = {
        "pair400k": lambda: pair(a.work, 400_000),
        "pair8m": lambda: pair(a.work, 8_000_000),
        "demo": lambda: chain(a.work, a.jobs),
        "plot400k": lambda: register(a.work, a.jobs, "paper", 400_000),
        "large1m": lambda: register(a.work, a.jobs, "large", 1_000_000),
        "large10m": lambda: chain(a.work, a.jobs, "large", 10_000_000),
    }
    print(
        "| case | wall (s) | CPU (s) | peak (MB) | read floor wall (s) | wall / floor "
        "| box gauge (CPU s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for name in a.cases.split(","):
        box = gauge()
        run, floor, *stages = cases[name]()
        print(
            f"| {name} | {run.wall_s:.1f} | {run.cpu_s:.1f} | {run.peak_mb:.0f} "
            f"| {floor.wall_s:.1f} | {run.wall_s / floor.wall_s:.1f} | {box:.2f} |",
            flush=True,
        )
        for stage, r in (stages[0] if stages else {}).items():
            print(f"| {name}: {stage} | {r.wall_s:.1f} | {r.cpu_s:.1f} | {r.peak_mb:.0f} | | | |")


if __name__ == "__main__":
    main()

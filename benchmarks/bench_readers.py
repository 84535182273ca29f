"""Point-cloud readers compared: E57 (pye57 vs `e57`), and a LAZ scan read for registration.

Each case runs in its own process under `/usr/bin/time -v`: whole-process wall time, CPU time (user +
system) and peak RSS, beside the time spent inside the read call (printed by the child). `e57` is not
a plotmosaic dependency: `.venv/bin/pip install e57` first (its rows are skipped without it). Run:

    nice -n 10 .venv/bin/python benchmarks/bench_readers.py [FILE.e57] [--repeat 3]
    nice -n 10 .venv/bin/python benchmarks/bench_readers.py --big 10000000 --repeat 1   # memory bound
    nice -n 10 .venv/bin/python benchmarks/bench_readers.py --laz SCAN.laz --budget 4000000 --repeat 1

`--big N` writes an N-point scan (pye57, single-precision xyz + intensity) to a temporary folder and
compares reading it whole with streaming it block by block (peak memory should stay flat).

`--laz SCAN` reads one LAZ scan: laspy's parallel lazrs decoder against the single-threaded one
(coordinates only, as registration reads), plotmosaic's whole read, and `read_bounded` (what
register-plot's prepare reads) with `[read] max_points_in_memory` above the scan's count and at each
`--budget` below it, alone and followed by `prepare_cloud` (what a prepare worker holds at its peak).
"""

from __future__ import annotations

import argparse
import importlib.util
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT = (
    Path(__file__).resolve().parents[2]
    / "shared"
    / "data"
    / "e57"
    / "pumpAVisualReferenceImage.e57"
)

CASES = {
    "python + numpy only (baseline)": "import numpy; t0 = time.perf_counter(); n = 0",
    "pye57 read_scan_raw (all fields)": (
        "import pye57; t0 = time.perf_counter(); d = pye57.E57(F).read_scan_raw(0); n = len(d['cartesianX'])"
    ),
    "pye57 read_scan (xyz+intensity+colour, invalid dropped)": (
        "import pye57; t0 = time.perf_counter(); "
        "d = pye57.E57(F).read_scan(0, intensity=True, colors=True, ignore_missing_fields=True); "
        "n = len(d['cartesianX'])"
    ),
    "e57 read_points (xyz+intensity+colour)": (
        "import e57; t0 = time.perf_counter(); d = e57.read_points(F); n = len(d.points)"
    ),
    "plotmosaic iter_e57_chunks (pye57, 1M-point blocks)": (
        "from plotmosaic.io.e57 import iter_e57_chunks; t0 = time.perf_counter(); "
        "n = sum(len(xyz) for xyz, _ in iter_e57_chunks(F))"
    ),
}


BIG_CASES = {
    "python + numpy only (baseline)": CASES["python + numpy only (baseline)"],
    "pye57 read_scan_raw (whole scan)": CASES["pye57 read_scan_raw (all fields)"],
    "plotmosaic read_cloud (whole scan, float64)": (
        "from plotmosaic.io.las import read_cloud; t0 = time.perf_counter(); n = len(read_cloud(F))"
    ),
    "plotmosaic iter_chunks (streamed, 1M-point blocks)": (
        "from plotmosaic.io.las import iter_chunks; t0 = time.perf_counter(); n = sum(len(c) for c in iter_chunks(F))"
    ),
}


_LAZ_DECODE = (
    "import laspy; t0 = time.perf_counter(); n = 0\n"
    "with laspy.open(F, laz_backend=laspy.LazBackend.{backend}, decompression_selection="
    "laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z) as r:\n"
    "    for c in r.chunk_iterator(2_000_000): n += len(c)"
)
_BOUNDED = (
    "from plotmosaic.config.reading import ReadingConfig; from plotmosaic.io.bounded import read_bounded; "
    "t0 = time.perf_counter(); c = read_bounded(F, ReadingConfig(max_points_in_memory={budget}), 0.025); "
    "n = len(c)"
)
_PREPARE = (
    "; from plotmosaic.align.prepare import prepare_cloud; from plotmosaic.config.align import AlignConfig; "
    "n = len(prepare_cloud(c, 'tls', 3, AlignConfig()).points)"
)


def laz_cases(budgets: list[int]) -> dict[str, str]:
    """The LAZ cases: decoders, whole read, bounded read at 2**31-1 (above any scan) and each budget."""
    cases = {
        "laspy decode, lazrs parallel (xyz layers)": _LAZ_DECODE.format(backend="LazrsParallel"),
        "laspy decode, lazrs single thread (xyz layers)": _LAZ_DECODE.format(backend="Lazrs"),
        "plotmosaic read_cloud (whole scan, float64)": (
            "from plotmosaic.io.las import read_cloud; t0 = time.perf_counter(); "
            "n = len(read_cloud(F, attributes=False))"
        ),
    }
    for budget in [2_000_000_000, *budgets]:
        read = _BOUNDED.format(budget=budget)
        cases[f"read_bounded, budget {budget:,}"] = read
        cases[f"read_bounded + prepare_cloud, budget {budget:,} (points: delta0 cloud)"] = (
            read + _PREPARE
        )
    return cases


def write_big(folder: Path, n: int) -> Path:
    import numpy as np
    import pye57

    rng = np.random.default_rng(0)
    path = folder / "big.e57"
    with pye57.E57(str(path), mode="w") as e57:
        xyz = rng.uniform(-50, 50, (n, 3))
        e57.write_scan_raw(
            {
                "cartesianX": xyz[:, 0],
                "cartesianY": xyz[:, 1],
                "cartesianZ": xyz[:, 2],
                "intensity": rng.uniform(0, 1, n),
            },
            name="big",
        )
    return path


def run_case(code: str, path: Path) -> tuple[float, float, float, int, float]:
    script = f"import time\nF = {str(path)!r}\n{code}\nprint('READ', time.perf_counter() - t0, n)"
    proc = subprocess.run(
        ["/usr/bin/time", "-v", sys.executable, "-c", script],
        capture_output=True,
        text=True,
        check=True,
    )
    read_s, n = proc.stdout.split("READ")[1].split()
    wall = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", proc.stderr)
    h, m, s = wall.groups()
    seconds = int(h or 0) * 3600 + int(m) * 60 + float(s)
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
    cpu = sum(
        float(re.search(rf"{k} time \(seconds\): ([\d.]+)", proc.stderr).group(1))
        for k in ("User", "System")
    )
    return seconds, rss_kb / 1024, float(read_s), int(n), cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("file", nargs="?", type=Path, default=DEFAULT)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--big", type=int, default=0, help="write and read an N-point scan instead")
    ap.add_argument("--laz", type=Path, help="read this LAZ scan for registration instead")
    ap.add_argument("--budget", type=int, nargs="*", default=[], help="budgets below its count")
    args = ap.parse_args()
    if args.laz:
        table(args.laz, laz_cases(args.budget), args.repeat)
        return
    with tempfile.TemporaryDirectory() as tmp:
        path, cases = (
            (write_big(Path(tmp), args.big), BIG_CASES) if args.big else (args.file, CASES)
        )
        table(path, cases, args.repeat)


def table(path: Path, cases: dict[str, str], repeat: int) -> None:
    print(f"file: {path} ({path.stat().st_size / 1e6:.1f} MB), median of {repeat} runs")
    print("| reader | points | process wall s | process CPU s | read call s | peak RSS MB |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, code in cases.items():
        module = code.split()[1].split(".")[0].rstrip(";")
        if importlib.util.find_spec(module) is None:
            print(f"| {name} | not installed | | | | |")
            continue
        runs = [run_case(code, path) for _ in range(repeat)]
        wall, rss, read, _, cpu = (statistics.median(r[i] for r in runs) for i in range(5))
        print(
            f"| {name} | {runs[0][3]:,} | {wall:.2f} | {cpu:.2f} | {read:.3f} | {rss:.0f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()

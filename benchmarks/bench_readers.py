"""E57 readers compared: pye57 (libE57Format) vs `e57` (Rust), plus plotmosaic's chunked reader.

Each case runs in its own process under `/usr/bin/time -v`: whole-process wall time and peak RSS,
beside the time spent inside the read call (printed by the child). Run:

    nice -n 10 .venv/bin/python benchmarks/bench_readers.py [FILE.e57] [--repeat 3]
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
from pathlib import Path

DEFAULT = Path(__file__).resolve().parents[2] / "shared" / "data" / "e57" / "pumpAVisualReferenceImage.e57"

CASES = {
    "python + numpy only (baseline)": "import numpy; t0 = time.perf_counter(); n = 0",
    "pye57 read_scan_raw (all fields)": (
        "import pye57; t0 = time.perf_counter(); d = pye57.E57(F).read_scan_raw(0); n = len(d['cartesianX'])"
    ),
    "pye57 read_scan (xyz+intensity+colour, invalid dropped)": (
        "import pye57; t0 = time.perf_counter(); "
        "d = pye57.E57(F).read_scan(0, intensity=True, colors=True, ignore_missing_fields=True); n = len(d['cartesianX'])"
    ),
    "e57 read_points (xyz+intensity+colour)": (
        "import e57; t0 = time.perf_counter(); d = e57.read_points(F); n = len(d.points)"
    ),
    "plotmosaic iter_e57_chunks (pye57, 1M-point blocks)": (
        "from plotmosaic.io.e57 import iter_e57_chunks; t0 = time.perf_counter(); n = sum(len(c) for c in iter_e57_chunks(F))"
    ),
}


def run_case(code: str, path: Path) -> tuple[float, float, float, int]:
    script = f"import time\nF = {str(path)!r}\n{code}\nprint('READ', time.perf_counter() - t0, n)"
    proc = subprocess.run(["/usr/bin/time", "-v", sys.executable, "-c", script], capture_output=True, text=True, check=True)
    read_s, n = proc.stdout.split("READ")[1].split()
    wall = re.search(r"Elapsed \(wall clock\) time.*: (?:(\d+):)?(\d+):([\d.]+)", proc.stderr)
    h, m, s = wall.groups()
    seconds = int(h or 0) * 3600 + int(m) * 60 + float(s)
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1))
    return seconds, rss_kb / 1024, float(read_s), int(n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("file", nargs="?", type=Path, default=DEFAULT)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"file: {args.file} ({args.file.stat().st_size / 1e6:.1f} MB), median of {args.repeat} runs")
    print("| reader | points | process wall s | read call s | peak RSS MB |")
    print("|---|---:|---:|---:|---:|")
    for name, code in CASES.items():
        runs = [run_case(code, args.file) for _ in range(args.repeat)]
        wall, rss, read = (statistics.median(r[i] for r in runs) for i in range(3))
        print(f"| {name} | {runs[0][3]:,} | {wall:.2f} | {read:.3f} | {rss:.0f} |")


if __name__ == "__main__":
    main()

"""Where a pair's CPU time goes: `plotmosaic align` under cProfile on the CPU clock, whole process.

    .venv/bin/python benchmarks/profile_pair.py SRC.laz TGT.laz --top 40
    .venv/bin/python benchmarks/profile_pair.py SRC.laz TGT.laz --save pair.prof   # for snakeviz etc.
    .venv/bin/python benchmarks/profile_pair.py SRC.laz TGT.laz --plain   # stage CPU, no profiler

The command runs in this process (cProfile sees every stage, imports included; worker processes are not
profiled: a pair runs in one process). The thread budget is 1 by default, because cProfile sees only the
thread it runs in: two-thread maps would show up as time waiting on a lock. The clock is `time.process_time`, so a loaded machine gives the
same figures as a quiet one, apart from cache effects. Printed first: the CPU of each stage and of the
kernels the fixed cost is made of (rows overlap: a kernel runs inside a stage, an import inside
whatever asked for it); then the functions by cumulative CPU time and by own CPU time.

`--plain` runs the pair without the profiler (which inflates Python-heavy stages) and prints the stage
timings the result records: with a thread budget of 1 a stage's wall time is its CPU time.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from plotmosaic.align.pipeline import AlignRequest, align_files
from plotmosaic.cli import app
from plotmosaic.parallel import set_threads

# (row, file the function is in (path ending), function): a row sums the cumulative CPU of its matches
STAGES = [
    ("imports", "<frozen importlib._bootstrap>", "_find_and_load"),
    ("read both files", "plotmosaic/io/las.py", "read_cloud"),
    ("kind detection", "plotmosaic/align/kinds.py", "detect_kind"),
    ("prepare both clouds", "plotmosaic/align/prepare.py", "prepare_cloud"),
    ("coarse search", "plotmosaic/align/coarse/stage.py", "coarse_align"),
    ("level ICP", "plotmosaic/align/level_icp.py", "level_stage"),
    ("final ICP", "plotmosaic/align/fine.py", "final_icp"),
    ("judge", "plotmosaic/align/judge/verdict.py", "judge"),
]
KERNELS = [
    ("ICP runs (all stages)", "plotmosaic/align/icp.py", "point_to_plane_icp"),
    ("  their correspondence searches", "plotmosaic/align/icp.py", "__call__"),
    ("normals filled on demand (ICP targets)", "plotmosaic/align/normals.py", "__call__"),
    ("level features (prepare)", "plotmosaic/align/normals.py", "level_shape"),
    ("local_shape (coarse clouds, FPFH, fills)", "plotmosaic/align/normals.py", "local_shape"),
    ("complexity levels (vMF mixtures)", "plotmosaic/align/complexity.py", "fit_levels"),
    ("raster NCC (FFT)", "plotmosaic/align/rasters.py", "scores"),
    ("FPFH descriptors", "plotmosaic/align/features3d.py", "fpfh"),
    ("vertical hypotheses", "plotmosaic/align/levelling.py", "vertical_hypotheses"),
    ("full nearest queries (evaluate, judge)", "plotmosaic/align/icp.py", "nearest"),
]


# the align command's imports alone, in a fresh process: under cProfile they cost several times
# more (scipy rewrites hundreds of docstrings at import, many small Python calls the profiler times)
BARE_IMPORTS = (
    "import time; t = time.process_time(); import plotmosaic.cli, plotmosaic.commands.align; "
    "print(time.process_time() - t)"
)


def bare_imports() -> float:
    """CPU seconds of the align command's imports in a fresh process, without the profiler."""
    out = subprocess.run(
        [sys.executable, "-c", BARE_IMPORTS], capture_output=True, text=True, check=True
    )
    return float(out.stdout)


def summary(stats: pstats.Stats, total: float) -> str:
    """The stage and kernel rows: CPU s, share of the run, calls."""
    lines = [f"{'':44s} {'CPU s':>7s} {'share':>6s} {'calls':>6s}"]
    for title, rows in (("stages", STAGES), ("kernels", KERNELS)):
        lines.append(title)
        for name, path, function in rows:
            hits = [
                v for (f, _, fn), v in stats.stats.items() if fn == function and f.endswith(path)
            ]
            cpu, calls = sum(v[3] for v in hits), sum(v[1] for v in hits)
            lines.append(f"  {name:42s} {cpu:7.2f} {cpu / total:6.0%} {calls:6d}")
    lines.append(f"  {'whole command':42s} {total:7.2f}")
    lines.append(f"  {'imports without the profiler (own process)':42s} {bare_imports():7.2f}")
    return "\n".join(lines)


def plain(source: Path, target: Path) -> str:
    """Stage seconds of one unprofiled run in this process (CPU seconds at a thread budget of 1)."""
    start = time.process_time()
    result = align_files(source, target, AlignRequest())
    total = time.process_time() - start
    lines = [f"{'':44s} {'s':>7s}"]
    for name, value in result.timings.items():
        if isinstance(value, dict):  # a stage's parts (prepare_source, prepare_target)
            value = ", ".join(f"{k} {v:.2f}" for k, v in value.items())
            lines.append(f"  {name:42s} {value}")
        else:
            lines.append(f"  {name:42s} {value:7.2f}")
    lines.append(f"  {'the pair, CPU (imports excluded)':42s} {total:7.2f}")
    lines.append(f"  {'imports (own process)':42s} {bare_imports():7.2f}")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("source", type=Path)
    ap.add_argument("target", type=Path)
    ap.add_argument("--top", type=int, default=30, help="rows of each table")
    ap.add_argument("--threads", type=int, default=1, help="thread budget (1: every call is seen)")
    ap.add_argument("--save", type=Path, help="write the raw profile here")
    ap.add_argument("--plain", action="store_true", help="no profiler: the stages' own timings")
    ap.add_argument("align_args", nargs="*", help="more `plotmosaic align` options, after --")
    args = ap.parse_args()
    set_threads(args.threads)
    if args.plain:
        if args.align_args:
            ap.error("--plain runs the default settings: no align options after --")
        print(plain(args.source, args.target))
        return
    with tempfile.TemporaryDirectory() as tmp:
        argv = [
            "align",
            str(args.source),
            str(args.target),
            "--out",
            f"{tmp}/r.json",
            *args.align_args,
        ]
        profile = cProfile.Profile(time.process_time)
        start = time.process_time()
        profile.enable()
        try:
            app(argv, standalone_mode=False)
        finally:
            profile.disable()
        total = time.process_time() - start
    print(f"CPU {total:.1f} s (process clock, this process)", file=sys.stderr)
    stats = pstats.Stats(profile, stream=sys.stdout)
    print(summary(stats, total))
    if args.save:
        stats.dump_stats(args.save)
    stats.sort_stats("cumulative").print_stats(args.top)
    stats.sort_stats("tottime").print_stats(args.top)


if __name__ == "__main__":
    main()

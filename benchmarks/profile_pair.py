"""Where a pair's CPU time goes: `plotmosaic align` under cProfile on the CPU clock, whole process.

    .venv/bin/python benchmarks/profile_pair.py SRC.laz TGT.laz --top 40
    .venv/bin/python benchmarks/profile_pair.py SRC.laz TGT.laz --save pair.prof   # for snakeviz etc.

The command runs in this process (cProfile sees every stage, imports included; worker processes are not
profiled: a pair runs in one process). The thread budget is 1 by default, because cProfile sees only the
thread it runs in: two-thread maps would show up as time waiting on a lock. The clock is `time.process_time`, so a loaded machine gives the
same figures as a quiet one, apart from cache effects. Printed: the functions by cumulative CPU time and
by own CPU time.
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import sys
import tempfile
import time
from pathlib import Path

from plotmosaic.cli import app
from plotmosaic.parallel import set_threads


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("source", type=Path)
    ap.add_argument("target", type=Path)
    ap.add_argument("--top", type=int, default=30, help="rows of each table")
    ap.add_argument("--threads", type=int, default=1, help="thread budget (1: every call is seen)")
    ap.add_argument("--save", type=Path, help="write the raw profile here")
    ap.add_argument("align_args", nargs="*", help="more `plotmosaic align` options, after --")
    args = ap.parse_args()
    set_threads(args.threads)
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
    if args.save:
        stats.dump_stats(args.save)
    stats.sort_stats("cumulative").print_stats(args.top)
    stats.sort_stats("tottime").print_stats(args.top)


if __name__ == "__main__":
    main()

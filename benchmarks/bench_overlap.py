"""Success against overlap (issue 54): forestalign, the baselines and Sylva on the same `paper` draws of
ground-based view pairs binned by their overlap.

Sources: `mls` (two virtual ground scans of the spanner MLS clip), `treels` (of the TreeLS pine plot) and
`sim` (the simulator's `understorey` preset on a 2 x 2 grid, its six scan pairs). The overlap comes from
the scanners' spacing and range alone (bench/overlap_pairs.py): seeded candidates are cut in order and
fill the bins, --pairs of them a bin and source; a pair's overlap is measured at the true pose both ways
(share of points within 25 cm of the other scan) and binned on the larger share: a pair in
[0.10, 0.15) shares less than 15 % of either scan. Each bin and source gets --n draws of the `paper`
protocol (+-45 deg on all three angles, +-15 m) applied to the source; found = within 1 deg / 10 cm,
refused = the method said no (exit 3), wrong = a wrong pose with exit 0 (forestalign's keeps its
result JSON in OUT/wrong/). Methods: forestalign, icp, fpfh-ransac, cpd (bench/methods.py; CPD needs
probreg) and Sylva's pair registration, `sylva` (the clouds alone) and `sylva-levelled` (also each
scan's levelling and scanner position, as a TLS records them; bench/peers.py; needs sylva-rs).

Resumable: pairs are cached in OUT/pairs, trials in OUT/trials.jsonl (a larger --n runs only the new
draws); -j changes nothing but the wall time.

    nice -n 10 .venv/bin/python benchmarks/bench_overlap.py --n 20 -j 2 --out /tmp/overlap
    nice -n 10 .venv/bin/python benchmarks/bench_overlap.py --cut-only --out /tmp/overlap   # the pairs
    nice -n 10 .venv/bin/python benchmarks/bench_overlap.py --redraw --out /tmp/overlap \\
        --figure benchmarks/figures/overlap.png
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

from plotmosaic.bench.methods import option_names, runnable
from plotmosaic.bench.overlap_pairs import (
    DEFAULT_EDGES,
    PAIRS_PER_BIN,
    SOURCES,
    PairRef,
    bin_label,
    build_catalogue,
    parse_bins,
)
from plotmosaic.bench.overlap_suite import method_available, run
from plotmosaic.bench.overlap_tables import ALL_METHODS, markdown, summarise, write_outputs
from plotmosaic.bench.real_suite import TRIALS_FILE, print_wrong, read_trials
from plotmosaic.errors import InputError
from plotmosaic.io.atomic import write_text_atomic

INFO_FILE = "runs.json"


def _commands(out: Path) -> list[str]:
    f = out / INFO_FILE
    return json.loads(f.read_text()).get("commands", []) if f.is_file() else []


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=5, help="paper draws per bin and source")
    ap.add_argument(
        "--bins",
        default=",".join(f"{e:.2f}" for e in DEFAULT_EDGES),
        help="overlap bin edges (the last bin is closed)",
    )
    ap.add_argument("--sources", default=",".join(SOURCES), help=f"from {', '.join(SOURCES)}")
    ap.add_argument(
        "--methods", default=",".join(ALL_METHODS), help=f"from {', '.join(ALL_METHODS)}"
    )
    ap.add_argument(
        "--pairs", type=int, default=PAIRS_PER_BIN, help="distinct pairs per bin and source"
    )
    ap.add_argument("--seed", type=int, default=0, help="seed of the cuts and of the draws")
    ap.add_argument("-j", "--jobs", type=int, default=1, help="trials run side by side (processes)")
    ap.add_argument("--data", type=Path, default=None, help="folder holding spanner/ and treels/")
    ap.add_argument("--out", type=Path, default=Path("bench_overlap"), help="output folder")
    ap.add_argument("--figure", type=Path, default=None, help="PNG (default OUT/overlap.png)")
    ap.add_argument("--cut-only", action="store_true", help="cut and list the pairs, run nothing")
    ap.add_argument(
        "--redraw", action="store_true", help="run nothing: table and figure from OUT's trials"
    )
    args = ap.parse_args(argv)
    command = "nice -n 10 .venv/bin/python benchmarks/bench_overlap.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])
    )
    try:
        if args.redraw:
            return redraw(args.out, command, args.figure)
        bins = parse_bins(args.bins)
        sources = option_names(args.sources, SOURCES, "--sources")
        methods = option_names(args.methods, ALL_METHODS, "--methods")
        if args.n < 1 or args.jobs < 1 or args.pairs < 1:
            raise InputError("--n, --pairs and --jobs must be at least 1")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    methods, skipped = runnable(methods, method_available)
    if not methods:
        print("error: --methods: none of them can run here", file=sys.stderr)
        return 2

    def log(m: str) -> None:
        print(m, file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    catalogues: dict[str, dict] = {}
    try:
        for src in sources:
            log(f"cutting {src} pairs ({args.pairs} a bin, seed {args.seed})")
            cat = build_catalogue(
                src, bins, args.pairs, args.seed, args.out / "pairs", args.data, log=log
            )
            for b, refs in cat.items():
                if len(refs) < args.pairs:
                    log(f"  {src} [{bin_label(b)}]: only {len(refs)} pair(s) found in that bin")
            catalogues[src] = cat
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    _save_catalogue(args.out, catalogues)
    if args.cut_only:
        log(f"{time.perf_counter() - t0:.0f} s")
        return 0
    info = {"commands": [*_commands(args.out), command], "skipped": skipped}
    write_text_atomic(args.out / INFO_FILE, json.dumps(info, indent=1))
    try:
        run(catalogues, args.n, methods, args.out, args.seed, args.jobs, log)
    except KeyboardInterrupt:
        log(f"interrupted: the finished trials are in {args.out / TRIALS_FILE}")
        return 130
    log(f"{time.perf_counter() - t0:.0f} s")
    return redraw(args.out, command, args.figure)


def _save_catalogue(out: Path, catalogues: dict[str, dict[tuple, list[PairRef]]]) -> None:
    doc = {
        src: {bin_label(b): [r.__dict__ for r in refs] for b, refs in cat.items()}
        for src, cat in catalogues.items()
    }
    write_text_atomic(out / "catalogue.json", json.dumps(doc, indent=1))


def redraw(out: Path, command: str, figure: Path | None) -> int:
    """Table and curve over every trial in OUT/trials.jsonl."""
    rows = read_trials(out / TRIALS_FILE)
    if not rows:
        print(f"error: no trials in {out / TRIALS_FILE}", file=sys.stderr)
        return 2
    commands = _commands(out) or [command]
    paths = write_outputs(rows, out, "\n    ".join(commands), figure)
    print(markdown(summarise(rows)))
    print_wrong(rows, lambda r: f"{r['case']} {r['pair']} trial {r['trial']}")
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

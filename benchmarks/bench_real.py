"""The real-data benchmark suite (issue 15): plotmosaic and the bench baselines on the same draws of real pairs.

Cases (plotmosaic/bench/real_cases.py): treels-2views, mls-2views, mls-boxed6m, uas-strip-als, uas-als, mls-uas,
sim-understorey (and sim-small on request). Protocols: paper (+-45 deg all three angles, +-15 m), beyond (any
heading, +-45 deg tilts, +-20 m), true (the source handed over in its true pose). Per case, protocol and method:
found (within 1 deg / 10 cm), refused (exit 3), wrong with exit 0, median / worst / RMSE errors of the found,
s/trial; forestalign's coarse generators (hypotheses near the truth, winners); a reliability diagram.

Every trial is one line of OUT/trials.jsonl; a trial's draw depends on (seed, case, protocol, trial) only, so
running again with a larger --n runs just the new trials, and -j only changes the wall time. A wrong forestalign
pose with exit 0 keeps its result JSON in OUT/wrong/.

    nice -n 10 .venv/bin/python benchmarks/bench_real.py --n 10 --n-true 10 -j 2 --out /tmp/real
    nice -n 10 .venv/bin/python benchmarks/bench_real.py --n 50 --n-true 50 -j 2 --out /tmp/real   # extends
    nice -n 10 .venv/bin/python benchmarks/bench_real.py --out /tmp/real --redraw --figure real.png
    nice -n 10 .venv/bin/python benchmarks/bench_real.py --cases mls-boxed6m --n 3 --protocol paper --methods forestalign

`--methods forestalign-placement` runs plotmosaic with register-plot's settings for placing a scan on an
airborne tile (the cases whose target is airborne: uas-strip-als, uas-als, mls-uas).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

from plotmosaic.bench.methods import METHODS, option_names, runnable
from plotmosaic.bench.real_cases import ALL_CASES, CASES
from plotmosaic.bench.real_suite import (
    CASES_FILE,
    SUITE_PROTOCOLS,
    TRIALS_FILE,
    Suite,
    print_wrong,
    read_trials,
    run_suite,
)
from plotmosaic.bench.suite_tables import markdown, summarise, write_outputs
from plotmosaic.errors import InputError


def _info(folders: list[Path]) -> dict:
    info: dict = {"cases": {}, "skipped": {}}
    for folder in folders:
        f = folder / CASES_FILE
        if f.is_file():
            data = json.loads(f.read_text())
            info["cases"].update(data.get("cases", {}))
            info["skipped"].update(data.get("skipped", {}))
    return info


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--cases", default=",".join(CASES), help=f"comma-separated, from {', '.join(ALL_CASES)}"
    )
    ap.add_argument("--n", type=int, default=5, help="trials per case for paper and beyond")
    ap.add_argument(
        "--n-true", type=int, default=2, help="trials per case for the true-pose control"
    )
    ap.add_argument(
        "--protocol", default="paper,beyond,true", help="comma-separated: paper, beyond, true"
    )
    ap.add_argument(
        "--methods",
        default="forestalign,icp,fpfh-ransac,cpd",
        help=f"comma-separated, from {', '.join(METHODS)}",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("-j", "--jobs", type=int, default=1, help="trials run side by side (processes)")
    ap.add_argument(
        "--data",
        type=Path,
        default=None,
        help="folder holding spanner/ and treels/ (default ../shared/data)",
    )
    ap.add_argument(
        "--out",
        type=Path,
        default=Path("bench_real"),
        help=f"folder for {TRIALS_FILE}, table.md, summary.json",
    )
    ap.add_argument(
        "--figure", type=Path, default=None, help="reliability PNG (default OUT/reliability.png)"
    )
    ap.add_argument(
        "--redraw", action="store_true", help="run nothing: tables and figure from OUT's trials"
    )
    ap.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=None,
        help="combine earlier runs' OUT folders into --out",
    )
    args = ap.parse_args(argv)
    command = "nice -n 10 .venv/bin/python benchmarks/bench_real.py " + " ".join(
        shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:])
    )
    try:
        if args.merge or args.redraw:
            return redraw(args.merge or [args.out], args.out, command, args.figure)
        cases = option_names(args.cases, ALL_CASES, "--cases")
        methods = option_names(args.methods, METHODS, "--methods")
        protos = option_names(args.protocol, SUITE_PROTOCOLS, "--protocol")
        if args.n < 1 or args.n_true < 1 or args.jobs < 1:
            raise InputError("--n, --n-true and --jobs must be at least 1")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    methods, skipped = runnable(methods)
    if not methods:
        print("error: --methods: none of them can run here", file=sys.stderr)
        return 2
    counts = {p: (args.n_true if p == "true" else args.n) for p in protos}
    t0 = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    info = _info([args.out])
    info["skipped"].update(skipped)
    info.setdefault("commands", [])
    info["commands"] = [*_info_commands(args.out), command]

    def on_trial(case_info: dict, rows: list[dict]) -> None:
        name = rows[0]["case"]
        if name not in info["cases"]:
            info["cases"][name] = case_info
            _save_info(args.out, info)

    _save_info(args.out, info)
    try:
        run_suite(
            Suite(tuple(cases), counts, tuple(methods), args.seed, args.data),
            args.out,
            args.jobs,
            log=lambda m: print(m, file=sys.stderr, flush=True),
            on_trial=on_trial,
        )
    except KeyboardInterrupt:
        print(
            "interrupted: the finished trials are in " + str(args.out / TRIALS_FILE),
            file=sys.stderr,
        )
        return 130
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return redraw([args.out], args.out, "\n".join(info["commands"]), args.figure)


def _info_commands(out: Path) -> list[str]:
    f = out / CASES_FILE
    return json.loads(f.read_text()).get("commands", []) if f.is_file() else []


def _save_info(out: Path, info: dict) -> None:
    from plotmosaic.io.atomic import write_text_atomic

    write_text_atomic(out / CASES_FILE, json.dumps(info, indent=1, default=float))


def redraw(folders: list[Path], out: Path, command: str, figure: Path | None) -> int:
    """Tables and the reliability diagram over every trial in the folders' trials files."""
    rows = [r for f in folders for r in read_trials(f / TRIALS_FILE)]
    if not rows:
        print(
            f"error: no trials in {', '.join(str(f / TRIALS_FILE) for f in folders)}",
            file=sys.stderr,
        )
        return 2
    info = _info(folders)
    commands = [c for f in folders for c in _info_commands(f)]
    paths = write_outputs(rows, info, out, "\n".join(commands) or command, figure)
    print(markdown(summarise(rows)))
    print_wrong(rows, lambda r: f"{r['case']} {r['protocol']} {r['method']} seed {r['seed']} trial {r['trial']}")  # fmt: skip
    print("wrote " + ", ".join(str(p) for p in paths.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

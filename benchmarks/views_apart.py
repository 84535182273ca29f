"""Two ground-based views of a real cloud, far apart, registered as a user would: cut, then align.

    python benchmarks/views_apart.py --cloud ../shared/data/spanner/MLS_Clip.laz \
        --spacing 12 --max-range 10 --seeds 0-9 --work /tmp/views

For each seed: `plotmosaic simulate WORK/sSEED --from-cloud CLOUD --views 2 --spacing S --max-range R
--seed SEED`, then `plotmosaic align P1-S1.laz P1-S0.laz` from the files as cut (each view in its own
frame). Printed per seed: the exit code, the pose's error against the cut's exact truth, the CPU
seconds of align, and the outcome: found (exit 0, within 5 cm / 0.2 deg), wrong (exit 0, outside) or
refused (exit 3). A wrong pose with exit 0 is the one outcome that must never appear.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np

from plotmosaic.io.frame import inverse, pose_error

FOUND_M, FOUND_DEG = 0.05, 0.2


def _seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def _run(*args: str) -> tuple[int, str, float]:
    """Exit code, stderr and CPU seconds of one plotmosaic command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(
        [sys.executable, "-m", "plotmosaic", *args], capture_output=True, text=True, check=False
    )
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return done.returncode, done.stderr, cpu


def one_seed(cloud: Path, spacing: float, max_range: float, seed: int, work: Path) -> dict:
    sim = work / f"s{seed}"
    if not (sim / "ground_truth.json").exists():
        code, err, _ = _run(
            "simulate", str(sim), "--from-cloud", str(cloud), "--views", "2",
            "--spacing", str(spacing), "--max-range", str(max_range), "--seed", str(seed),
        )  # fmt: skip
        if code != 0:
            raise SystemExit(f"error: cutting seed {seed} failed: {err.strip()}")
    out = work / f"r{seed}.json"
    out.unlink(missing_ok=True)  # our own result file: each run starts clean
    for sibling in (out.with_suffix(".matrix.txt"), out.with_suffix(".config-used.toml")):
        sibling.unlink(missing_ok=True)
    code, err, cpu = _run("align", str(sim / "P1" / "P1-S1.laz"), str(sim / "P1" / "P1-S0.laz"), "--out", str(out))  # fmt: skip
    row = {"seed": seed, "exit": code, "cpu_s": cpu, "deg": None, "m": None}
    if code == 0:
        truth = json.loads((sim / "ground_truth.json").read_text())["scans"]
        T = {k: np.asarray(v["transform"], dtype=float) for k, v in truth.items()}
        got = np.asarray(json.loads(out.read_text())["transform"], dtype=float)
        row["deg"], row["m"] = pose_error(got, inverse(T["P1-S0"]) @ T["P1-S1"])
        ok = row["m"] < FOUND_M and row["deg"] < FOUND_DEG
        row["outcome"] = "found" if ok else "WRONG"
    elif code == 3:
        row["outcome"] = "refused"
        row["why"] = err.strip().splitlines()[-1] if err.strip() else ""
    else:
        raise SystemExit(f"error: align on seed {seed} exited {code}: {err.strip()}")
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cloud", type=Path, default=Path("../shared/data/spanner/MLS_Clip.laz"))
    ap.add_argument("--spacing", type=float, default=12.0)
    ap.add_argument("--max-range", type=float, default=10.0)
    ap.add_argument("--seeds", default="0-9", help="a seed or a range, e.g. 0-9")
    ap.add_argument("--work", type=Path, required=True, help="folder for the cuts and results")
    a = ap.parse_args(argv)
    if not a.cloud.is_file():
        print(f"error: {a.cloud}: no such cloud", file=sys.stderr)
        return 2
    a.work.mkdir(parents=True, exist_ok=True)
    rows = []
    print("| seed | outcome | error (deg / cm) | align CPU s |")
    print("|---|---|---|---|")
    for seed in _seeds(a.seeds):
        r = one_seed(a.cloud, a.spacing, a.max_range, seed, a.work)
        rows.append(r)
        err = f"{r['deg']:.3f} / {100 * r['m']:.2f}" if r["deg"] is not None else r.get("why", "")
        print(f"| {seed} | {r['outcome']} | {err} | {r['cpu_s']:.1f} |", flush=True)
    count = {k: sum(r["outcome"] == k for r in rows) for k in ("found", "refused", "WRONG")}
    print(f"\n{count['found']} / {len(rows)} found, {count['refused']} refused, {count['WRONG']} wrong with exit 0")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Same transforms from two runs of the real-data suite: the largest difference per case, in m and deg.

    .venv/bin/python benchmarks/compare_trials.py BEFORE_OUT AFTER_OUT

BEFORE_OUT / AFTER_OUT are `bench_real.py --out` folders of the same draws (same --seed, cases,
protocols and --n), e.g. run from two checkouts. Printed per case: trials compared, outcomes that
differ, and the largest difference of the recovered rotation angles (deg) and translations (m).
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

ANGLES = ("roll", "pitch", "yaw")
SHIFTS = ("tx", "ty", "tz")


def trials(out: Path) -> dict[tuple, dict]:
    rows = {}
    for line in (out / "trials.jsonl").read_text().splitlines():
        r = json.loads(line)
        rows[(r["case"], r["protocol"], r["trial"], r["method"])] = r
    return rows


def largest(a: dict, b: dict, keys: tuple[str, ...]) -> float:
    pairs = [(a[k], b[k]) for k in keys if a.get(k) is not None and b.get(k) is not None]
    return max((abs(x - y) for x, y in pairs), default=0.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    args = ap.parse_args()
    before, after = trials(args.before), trials(args.after)
    rows: dict[str, list] = defaultdict(lambda: [0, 0, 0.0, 0.0])
    for key in sorted(set(before) & set(after)):
        a, b = before[key], after[key]
        row = rows[f"{key[0]} [{key[1]}] {key[3]}"]
        row[0] += 1
        row[1] += a["outcome"] != b["outcome"]
        row[2] = max(row[2], largest(a, b, ANGLES))
        row[3] = max(row[3], largest(a, b, SHIFTS))
    print(
        "| case | trials | outcomes differ | max rotation diff (deg) | max translation diff (m) |"
    )
    print("|---|---|---|---|---|")
    for name, (n, differ, deg, m) in rows.items():
        print(f"| {name} | {n} | {differ} | {deg:.1e} | {m:.1e} |")
    only = len(set(before) ^ set(after))
    if only:
        print(f"\n{only} trials are in one run only (not compared)")


if __name__ == "__main__":
    main()

"""Same result before and after a refactor: the transforms of a few fixed pairs, to full precision.

    python benchmarks/same_result.py OUT.json --sim /tmp/same_sim     # simulate once (reused), align, write
    python benchmarks/same_result.py --compare BEFORE.json AFTER.json  # max difference in m and deg

Pairs: three of the simulated `small` preset (seed 0) and, when ../shared/data/spanner is present,
the real UAS clip onto the ALS clip. Each pair goes through `align_files` in-process with seed 0;
a pair that cannot register records the rejected transform and the error.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from plotmosaic.align.pipeline import AlignRequest, align_files
from plotmosaic.errors import RegistrationFailed
from plotmosaic.simulate.run import scan_path, simulate

SIM_PAIRS = [("P1", "P1-S1", "P1-S0"), ("P1", "P1-S3", "P1-S2"), ("P1", "P1-S4", "P1-S0")]
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "spanner"


def _pairs(sim: Path) -> list[tuple[str, Path, Path, str, str]]:
    if not (sim / "manifest.toml").exists():
        simulate(sim, preset="small", seed=0)
    pairs = [
        (f"{s}->{t}", sim / scan_path(plot, s), sim / scan_path(plot, t), "tls", "tls")
        for plot, s, t in SIM_PAIRS
    ]
    if (REAL / "UAS_Clip.laz").exists() and (REAL / "ALS_Clip.laz").exists():
        pairs.append(("UAS->ALS", REAL / "UAS_Clip.laz", REAL / "ALS_Clip.laz", "uls", "als"))
    return pairs


def _record(name: str, src: Path, tgt: Path, sk: str, tk: str) -> dict:
    error = None
    try:
        result = align_files(src, tgt, AlignRequest(source_kind=sk, target_kind=tk, seed=0))
    except RegistrationFailed as err:
        result, error = getattr(err, "result", None), str(err)
    rec = {"pair": name, "error": error}
    if result is not None:
        rec.update(
            transform=np.asarray(result.transform, dtype=float).tolist(),
            fitness=result.fitness,
            inlier_rmse=result.inlier_rmse,
            confidence=result.confidence,
        )
    print(f"{name}: {'ok' if error is None else error}", flush=True)
    return rec


def _difference(a: dict, b: dict) -> tuple[float, float]:
    if ("transform" in a) != ("transform" in b) or a["error"] != b["error"]:
        return float("inf"), float("inf")
    if "transform" not in a:
        return 0.0, 0.0
    ta, tb = np.asarray(a["transform"]), np.asarray(b["transform"])
    metres = float(np.max(np.abs(ta[:3, 3] - tb[:3, 3])))
    cos = np.clip((np.trace(ta[:3, :3].T @ tb[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    # arccos is flat near 1: the matrix entries bound the angle too (radians, small-angle)
    degrees = max(
        float(np.degrees(np.arccos(cos))) if cos < 1.0 - 1e-12 else 0.0,
        float(np.degrees(np.max(np.abs(ta[:3, :3] - tb[:3, :3])))),
    )
    return metres, degrees


def compare(path_a: Path, path_b: Path) -> float:
    a = {r["pair"]: r for r in json.loads(path_a.read_text())["pairs"]}
    b = {r["pair"]: r for r in json.loads(path_b.read_text())["pairs"]}
    if set(a) != set(b):
        print(f"different pairs: {sorted(set(a) ^ set(b))}")
        return float("inf")
    worst_m = worst_deg = 0.0
    for name in a:
        m, deg = _difference(a[name], b[name])
        print(f"{name}: {m:.3e} m  {deg:.3e} deg")
        worst_m, worst_deg = max(worst_m, m), max(worst_deg, deg)
    print(f"max difference: {worst_m:.3e} m  {worst_deg:.3e} deg")
    return worst_m


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", type=Path, help="JSON to write the transforms to")
    ap.add_argument("--sim", type=Path, default=Path("/tmp/same_result_sim"))
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    args = ap.parse_args()
    if args.compare:
        return 0 if compare(*args.compare) <= 1e-9 else 1
    if args.out is None:
        ap.error("OUT.json or --compare A B")
    records = [_record(*pair) for pair in _pairs(args.sim)]
    args.out.write_text(json.dumps({"pairs": records}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

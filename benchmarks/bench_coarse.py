"""Start-from-anywhere benchmark (issue 5): ForestAlign with its global coarse stage.

Runs the paper protocol (roll/pitch/yaw +-45 deg, +-15 m) and the wider one (heading +-180 deg,
roll/pitch +-10 deg, +-25 m) on
  * simulated TLS-TLS pairs (corner scans onto the centre scan, paper layout),
  * simulated TLS-ALS pairs (centre scan onto the ALS tile),
  * the real Fort Valley clips: UAS -> ALS and MLS -> UAS,
and prints the paper-style table per case (per-parameter RMSE, success < 1 deg / 10 cm, s/trial).

    python benchmarks/bench_coarse.py --trials 50 --points-per-scan 800000 --out bench-output/coarse
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from plotmosaic.bench.pairs import manifest_pairs
from plotmosaic.bench.protocol import get_protocol
from plotmosaic.bench.run import BenchPair, run_bench, write_outputs
from plotmosaic.config.bench import BenchConfig
from plotmosaic.io import read_cloud
from plotmosaic.manifest import load_manifest
from plotmosaic.poses import load_poses
from plotmosaic.simulate.run import simulate

SPANNER = Path(__file__).resolve().parents[2] / "shared" / "data" / "spanner"


def simulated_pairs(out: Path, points_per_scan: int, which: str, max_pairs: int) -> list[BenchPair]:
    sim_dir = out / f"sim-{points_per_scan}"
    if not (sim_dir / "manifest.toml").is_file():
        simulate(sim_dir, "small", seed=0, points_per_scan=points_per_scan)
    manifest = load_manifest(sim_dir / "manifest.toml")
    return manifest_pairs(manifest, load_poses(sim_dir / "ground_truth.json"), which, max_pairs)


def real_pairs() -> list[BenchPair]:
    if not SPANNER.is_dir():
        return []
    clip = {
        n: read_cloud(SPANNER / f"{n}_Clip.laz", attributes=False) for n in ("UAS", "ALS", "MLS")
    }
    return [
        BenchPair("UAS->ALS (real)", clip["UAS"], clip["ALS"], np.eye(4), "uls", "als"),
        BenchPair("MLS->UAS (real)", clip["MLS"], clip["UAS"], np.eye(4), "mls", "uls"),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--points-per-scan", type=int, default=800_000)
    ap.add_argument("--max-pairs", type=int, default=2, help="simulated TLS-TLS pairs used")
    ap.add_argument("--protocols", default="paper,beyond")
    ap.add_argument("--cases", default="tls-tls,tls-als,real")
    ap.add_argument("--out", type=Path, default=Path("bench-output/coarse"))
    args = ap.parse_args()

    cases: dict[str, list[BenchPair]] = {}
    for case in args.cases.split(","):
        if case == "real":
            for pair in real_pairs():
                cases[pair.name] = [pair]
        else:
            cases[f"simulated {case}"] = simulated_pairs(
                args.out, args.points_per_scan, case, args.max_pairs
            )
    for protocol in args.protocols.split(","):
        for name, pairs in cases.items():
            if not pairs:
                continue
            start = time.perf_counter()
            config = BenchConfig(
                protocol=get_protocol(protocol), trials=args.trials, methods=["forestalign"], seed=0
            )
            slug = (
                f"{protocol}-{name}".replace(" ", "_")
                .replace(">", "")
                .replace("(", "")
                .replace(")", "")
            )
            result = run_bench(pairs, config, progress=False, failures=args.out / slug / "failures")
            write_outputs(result, args.out / slug, title=f"{name}, protocol {protocol}")
            print(
                f"\n### {name}, protocol `{protocol}`: {len(pairs)} pair(s) x {args.trials} trials, {time.perf_counter() - start:.0f} s"
            )
            print(result.table)
            for r in result.rows:
                if r["picture"]:
                    print(f"failure picture: {args.out / slug / 'failures' / r['picture']}")


if __name__ == "__main__":
    main()

"""A big plot's ALS placements as a register-plot worker runs them: CPU per placement, where it goes.

    python benchmarks/placements.py SIM/manifest.toml --n 6 --prepared DIR [--compare REG/placement]
    python benchmarks/placements.py SIM/manifest.toml --n 4 --prepared DIR --profile p.prof
    python benchmarks/placements.py SIM/manifest.toml --pick 0,5,10 --prepared DIR \
        --coarse '{"fpfh": false}' --compare REG/placement      # one coarse setting changed

The first `--n` scan -> ALS jobs of the manifest's big plots (register-plot's own jobs: same keys,
settings and seed) run one after another in this process with a thread budget of 1, as one pool
worker of `-j 2` runs them: the tile is loaded, and its memo kept, across the placements. Scans are
prepared into `--prepared` (a copy of REG/prepared skips that). The clock is the process's CPU.
Printed per placement: its CPU and the coarse stage's own timings (wall, within the placement);
`--compare REG/placement`: whether each transform and confidence equal that run's to the bit;
`--profile FILE`: cProfile of the placements alone (sort it with pstats); `--coarse JSON`: the
placements' coarse settings updated (compared with `--compare` against the default's records).
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.executor import run_pair_job
from plotmosaic.manifest import load_manifest
from plotmosaic.parallel import set_threads
from plotmosaic.stages.register_plot.place import placement_plan


def jobs(manifest_path: str, prepared: str, seed: int = 0):
    """register-plot's placement jobs of every big plot without positions (default settings)."""
    return placement_plan(load_manifest(manifest_path), RegisterConfig(), seed, Path(prepared))


def changed(job, coarse_json: str):
    """The job with its coarse settings updated (its key kept: records compare with the default's)."""
    config = job.config
    coarse = config.coarse.model_copy(update=json.loads(coarse_json))
    return dataclasses.replace(job, config=config.model_copy(update={"coarse": coarse}))


def _difference(record: dict, other: dict) -> str:
    """How a placement differs from the run's: its status, pose (cm / deg) and confidence."""
    if record.get("status") != other.get("status") or "transform" not in other:
        return f"status {record.get('status')} (the run's {other.get('status')})"
    a, b = np.asarray(record["transform"]), np.asarray(other["transform"])
    cos = np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1)
    return (
        f"pose {100 * np.linalg.norm(a[:3, 3] - b[:3, 3]):.4f} cm / {np.degrees(np.arccos(cos)):.5f} deg"
        f" from the run's, confidence {record.get('confidence', 0):.3f} (the run's {other.get('confidence', 0):.3f})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("manifest")
    ap.add_argument("--n", type=int, default=4, help="placements run (the first n scans)")
    ap.add_argument("--pick", help="placements run by index, e.g. 0,5,10 (instead of --n)")
    ap.add_argument("--coarse", help="coarse settings changed, JSON, e.g. '{\"fpfh\": false}'")
    ap.add_argument("--prepared", required=True, help="prepared-cloud cache folder")
    ap.add_argument("--compare", help="a register-plot run's placement/ folder")
    ap.add_argument("--profile", help="write cProfile stats of the placements here")
    args = ap.parse_args()
    set_threads(1)
    found = jobs(args.manifest, args.prepared)
    todo = [found[int(i)] for i in args.pick.split(",")] if args.pick else found[: args.n]
    profiler = cProfile.Profile() if args.profile else None
    # the run's record of each scan's placement, whatever settings its key was made with
    earlier = {}
    for path in sorted(Path(args.compare).glob("*.json")) if args.compare else []:
        record = json.loads(path.read_text())
        earlier[record.get("source")] = record
    total, differ = 0.0, 0
    for job in todo:
        t = time.process_time()
        if profiler:
            profiler.enable()
        record = run_pair_job(changed(job, args.coarse) if args.coarse else job)
        if profiler:
            profiler.disable()
        cpu = time.process_time() - t
        total += cpu
        coarse = (record.get("coarse") or {}).get("timing", {})
        line = f"{job.source}: {record['status']}, {cpu:.2f} CPU s; coarse " + ", ".join(
            f"{k} {v:.2f}" for k, v in coarse.items()
        )
        if args.compare:
            other = earlier.get(job.source, {})
            same = all(record.get(k) == other.get(k) for k in ("status", "transform", "confidence"))
            differ += not same
            line += "; same bits" if same else "; " + _difference(record, other)
        print(line, flush=True)
    print(f"{len(todo)} placements: {total:.1f} CPU s ({total / max(1, len(todo)):.2f} each)")
    if args.compare:
        print("all the same to the bit" if not differ else f"{differ} differ")
    if profiler:
        profiler.dump_stats(args.profile)


if __name__ == "__main__":
    main()

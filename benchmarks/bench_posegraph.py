"""Pose graph scaling (issue 16): a synthetic grid of scans with wrong edges, optimised with the register-plot solver.

    python benchmarks/bench_posegraph.py --scans 500 --wrong 0.05 --seed 0

Prints the number of edges, wrong edges, how many of them were dropped (and why), good edges
dropped, the optimise time and the worst pose error against the synthetic truth.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

from plotmosaic.graph.posegraph import _edge_id, build_graph, optimise, pose_error
from plotmosaic.graph.synthetic import grid_graph


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, nargs="+", default=[500])
    ap.add_argument("--wrong", type=float, default=0.05, help="share of wrong edges")
    ap.add_argument("--seed", type=int, nargs="+", default=[0])
    args = ap.parse_args()
    print("| scans | edges | wrong | wrong dropped | good dropped | reasons | optimise (s) | worst error (cm / deg) |")
    print("|---|---|---|---|---|---|---|---|")
    for n in args.scans:
        for seed in args.seed:
            truth, nodes, edges, wrong = grid_graph(n, args.wrong, seed=seed)
            G = build_graph(nodes, edges)
            start = time.perf_counter()
            sol = optimise(G, "s0000")
            seconds = time.perf_counter() - start
            dropped = {_edge_id(d["source"], d["target"]) for d in sol.dropped}
            w = {_edge_id(*e) for e in wrong}
            errs = [pose_error(sol.poses[k], truth[k]) for k in truth if k in sol.poses]
            reasons = ", ".join(f"{k} {v}" for k, v in sorted(Counter(d["reason"] for d in sol.dropped).items()))
            print(f"| {n} (seed {seed}) | {len(edges)} | {len(w)} | {len(w & dropped)} | {len(dropped - w)} | {reasons} "
                  f"| {seconds:.2f} | {max(e[0] for e in errs) * 100:.2f} / {max(e[1] for e in errs):.3f} |"
                  + ("" if not sol.unplaced else f" unplaced: {len(sol.unplaced)}"))


if __name__ == "__main__":
    main()

"""Pose graph scaling (issue 16): a synthetic grid of scans with wrong edges, optimised with the register-plot solver.

    python benchmarks/bench_posegraph.py --scans 500 --wrong 0.05 --seed 0
    python benchmarks/bench_posegraph.py --pairs 9 25 49 100

The second form prints how many pairs register-plot's selection runs for plots of that many scans
(on an 18 m grid with 1 m jitter, positions known or from the ALS step), against all pairs.

Prints the number of edges, wrong edges, how many of them were dropped (and why), good edges
dropped, the optimise time and the worst pose error against the synthetic truth.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

from plotmosaic.graph.posegraph import _edge_id, build_graph, optimise, pose_error
from plotmosaic.graph.synthetic import grid_graph


def pair_counts(sizes: list[int]) -> None:
    import networkx as nx
    import numpy as np

    from plotmosaic.graph.pairs import candidate_pairs
    from plotmosaic.manifest import Plot, Scan

    print(
        "| scans | pairs run | pairs per scan | max pairs of one scan | all pairs | connected | scans in no triangle |"
    )
    print("|---|---|---|---|---|---|---|")
    for n in sizes:
        rng = np.random.default_rng(0)
        side = int(np.ceil(np.sqrt(n)))
        pos = [
            ((k % side) * 18.0 + rng.normal(0, 1), (k // side) * 18.0 + rng.normal(0, 1), 0.0)
            for k in range(n)
        ]
        plot = Plot(
            id="P",
            scans=[
                Scan(id=f"s{k}", path=f"s{k}.laz", approx_position=p) for k, p in enumerate(pos)
            ],
        )
        start = time.perf_counter()
        pairs = candidate_pairs(plot, 60.0)
        seconds = time.perf_counter() - start
        G = nx.Graph([(s.id, t.id) for s, t in pairs])
        lonely = sum(1 for v in nx.triangles(G).values() if v == 0)
        print(
            f"| {n} | {len(pairs)} | {len(pairs) / n:.2f} | {max(d for _, d in G.degree())} | {n * (n - 1) // 2} "
            f"| {nx.is_connected(G)} | {lonely} |  ({seconds * 1000:.1f} ms)"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, nargs="+", default=[500])
    ap.add_argument("--wrong", type=float, default=0.05, help="share of wrong edges")
    ap.add_argument("--seed", type=int, nargs="+", default=[0])
    ap.add_argument(
        "--pairs",
        type=int,
        nargs="+",
        help="print the pair counts for plots of these sizes instead",
    )
    args = ap.parse_args()
    if args.pairs:
        pair_counts(args.pairs)
        return
    print(
        "| scans | edges | wrong | wrong dropped | good dropped | reasons | optimise wall (s) | CPU (s) | worst error (cm / deg) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for n in args.scans:
        for seed in args.seed:
            truth, nodes, edges, wrong = grid_graph(n, args.wrong, seed=seed)
            G = build_graph(nodes, edges)
            start, cpu = time.perf_counter(), time.process_time()
            sol = optimise(G, "s0000")
            seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
            dropped = {_edge_id(d["source"], d["target"]) for d in sol.dropped}
            w = {_edge_id(*e) for e in wrong}
            errs = [pose_error(sol.poses[k], truth[k]) for k in truth if k in sol.poses]  # (deg, m)
            reasons = ", ".join(
                f"{k} {v}" for k, v in sorted(Counter(d["reason"] for d in sol.dropped).items())
            )
            print(
                f"| {n} (seed {seed}) | {len(edges)} | {len(w)} | {len(w & dropped)} | {len(dropped - w)} | {reasons} "
                f"| {seconds:.2f} | {cpu:.2f} | {max(e[1] for e in errs) * 100:.2f} / {max(e[0] for e in errs):.3f} |"
                + ("" if not sol.unplaced else f" unplaced: {len(sol.unplaced)}")
            )


if __name__ == "__main__":
    main()

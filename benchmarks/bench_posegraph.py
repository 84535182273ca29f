"""Pose graph scaling (issue 16): a synthetic grid of scans with wrong edges, optimised with the register-plot solver.

    python benchmarks/bench_posegraph.py --scans 500 --wrong 0.05 --seed 0
    python benchmarks/bench_posegraph.py --pairs 9 25 49 100
    python benchmarks/bench_posegraph.py --pairs 9 25 49 100 --placed
    python benchmarks/bench_posegraph.py --signature-pairs 9 25 49 100 400

The second form prints how many pairs register-plot's selection runs for plots of that many scans
(on an 18 m grid with 1 m jitter, approximate positions in the manifest; with --placed, positions
to 1 cm as from the ALS step or the verified graph, paired within `PlacedPriors.reach` x the
spacing), against all pairs; the
third for plots without any position, paired by stem-map signatures (synthetic stem maps:
bench/synthetic.stem_map_grid, 300 stems / ha seen to 20 m, 20 % occluded, 5 cm noise).

Prints the number of edges, wrong edges, how many of them were dropped (and why), good edges
dropped, the optimise time and the worst pose error against the synthetic truth.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

from plotmosaic.bench.synthetic import grid_graph
from plotmosaic.graph.cycles import _edge_id
from plotmosaic.graph.posegraph import build_graph, optimise, pose_error


def pair_counts(sizes: list[int], placed: bool = False) -> None:
    import networkx as nx
    import numpy as np

    from plotmosaic.config.scale import PlacedPriors
    from plotmosaic.graph.pairs import candidate_pairs
    from plotmosaic.manifest import Plot, Scan

    jitter = 0.01 if placed else 1.0

    print(
        "| scans | pairs run | pairs per scan | max pairs of one scan | all pairs | connected | scans in no triangle |"
    )
    print("|---|---|---|---|---|---|---|")
    for n in sizes:
        rng = np.random.default_rng(0)
        side = int(np.ceil(np.sqrt(n)))
        pos = [
            (
                (k % side) * 18.0 + rng.normal(0, jitter),
                (k // side) * 18.0 + rng.normal(0, jitter),
                0.0,
            )
            for k in range(n)
        ]
        plot = Plot(
            id="P",
            scans=[
                Scan(id=f"s{k}", path=f"s{k}.laz", approx_position=None if placed else p)
                for k, p in enumerate(pos)
            ],
        )
        start = time.perf_counter()
        if placed:
            known = {f"s{k}": np.asarray(p) for k, p in enumerate(pos)}
            pairs = candidate_pairs(plot, 60.0, known, reach=PlacedPriors().reach)
        else:
            pairs = candidate_pairs(plot, 60.0)
        seconds = time.perf_counter() - start
        G = nx.Graph([(s.id, t.id) for s, t in pairs])
        lonely = sum(1 for v in nx.triangles(G).values() if v == 0)
        print(
            f"| {n} | {len(pairs)} | {len(pairs) / n:.2f} | {max(d for _, d in G.degree())} | {n * (n - 1) // 2} "
            f"| {nx.is_connected(G)} | {lonely} |  ({seconds * 1000:.1f} ms)"
        )


def signature_counts(sizes: list[int]) -> None:
    import networkx as nx
    import numpy as np

    from plotmosaic.bench.synthetic import stem_map_grid
    from plotmosaic.config.scale import SignatureConfig
    from plotmosaic.graph.signature import Signature, signature_pairs, similarity, stem_triangles

    config = SignatureConfig()
    print(
        "| scans | pairs planned | pairs per scan | max pairs of one scan | grid links found "
        "| pairs > 26 m apart | all pairs | connected | signatures + ranking (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for n in sizes:
        side = int(round(np.sqrt(n)))
        positions, maps = stem_map_grid(side, seed=side)
        start = time.perf_counter()
        sigs = []
        for xy in maps:
            sides, corners = stem_triangles(
                xy, config.min_side_m, config.max_side_m, config.max_triangles
            )
            sigs.append(Signature(xy, np.zeros(len(xy)), sides, corners))
        pairs = signature_pairs(similarity(sigs, config), len(maps), config.partners, 8)
        seconds = time.perf_counter() - start
        m = len(maps)
        grid = {
            (i, j)
            for i in range(m)
            for j in range(i + 1, m)
            if np.linalg.norm(positions[i] - positions[j]) < 19
        }
        far = sum(np.linalg.norm(positions[i] - positions[j]) > 26 for i, j in pairs)
        G = nx.Graph(pairs)
        G.add_nodes_from(range(m))
        print(
            f"| {m} | {len(pairs)} | {len(pairs) / m:.2f} | {max(d for _, d in G.degree())} "
            f"| {len(grid & set(pairs))}/{len(grid)} | {far} | {m * (m - 1) // 2} "
            f"| {nx.is_connected(G)} | {seconds:.2f} |"
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
    ap.add_argument(
        "--signature-pairs",
        type=int,
        nargs="+",
        help="print the signature-planned pair counts for plots of these sizes (no positions)",
    )
    ap.add_argument(
        "--placed", action="store_true", help="--pairs with positions to 1 cm (ALS / graph)"
    )
    args = ap.parse_args()
    if args.signature_pairs:
        signature_counts(args.signature_pairs)
        return
    if args.pairs:
        pair_counts(args.pairs, args.placed)
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

"""Stem-map signatures rank the partners of scans that have no position (graph/signature.py)."""

from __future__ import annotations

import json

import networkx as nx
import numpy as np
import pytest

from plotmosaic.bench.synthetic import stem_map_grid
from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.executor import Workers
from plotmosaic.graph.signature import (
    Signature,
    SignatureConfig,
    grow_candidates,
    signature_pairs,
    similarity,
    stem_triangles,
)

GRID = 15.0  # m between scan positions of the simulated 3 x 3 grid


def _synthetic_plot(side: int, seed: int):
    """Stem maps of a `side` x `side` grid 18 m apart in one random forest (bench/synthetic.py)."""
    positions, maps = stem_map_grid(side, seed)
    config = SignatureConfig()
    sigs = []
    for xy in maps:
        sides, corners = stem_triangles(
            xy, config.min_side_m, config.max_side_m, config.max_triangles
        )
        sigs.append(Signature(xy, np.full(len(xy), 0.3), sides, corners))
    return positions, sigs, config


@pytest.mark.parametrize("side", [3, 5, 7])
def test_signature_plan_grows_linearly_and_finds_the_grid(side):
    positions, sigs, config = _synthetic_plot(side, seed=side)
    n = len(sigs)
    pairs = signature_pairs(similarity(sigs, config), n, config.partners, 8)
    degree = np.bincount(np.array(pairs).ravel(), minlength=n)
    assert len(pairs) <= (config.partners + 1) * n  # linear, not n(n-1)/2
    assert degree.max() <= 8
    assert nx.is_connected(nx.Graph(pairs))
    grid = {
        (i, j)
        for i in range(n)
        for j in range(i + 1, n)
        if np.linalg.norm(positions[i] - positions[j]) < 19
    }
    assert len(grid & set(pairs)) >= 0.9 * len(grid)


def test_unrelated_scans_score_below_true_neighbours():
    """Scans of forests that share no tree: chance triangle matches rarely agree on one pose, and
    when they do, they score below every true grid neighbour."""
    positions, sigs, config = _synthetic_plot(3, seed=3)
    scores = similarity(sigs, config)
    near = [v for (i, j), v in scores.items() if np.linalg.norm(positions[i] - positions[j]) < 19]
    chance = []
    for seed in range(1, 11):
        _, a, _ = _synthetic_plot(1, seed=seed)
        _, b, _ = _synthetic_plot(1, seed=100 + seed)
        chance.append(similarity(a + b, config).get((0, 1), 0.0))
    assert sum(c > 0 for c in chance) <= 5
    assert max(chance) < min(near)


def test_growth_only_where_the_graph_is_apart():
    ranks = {"A": ["B", "C"], "B": ["A", "C"], "C": ["D", "A", "B"], "D": ["C", "B"]}
    comps = [{"A", "B", "C"}, {"D"}]
    tried = {frozenset(p) for p in [("A", "B"), ("B", "C"), ("A", "C")]}
    degree = {"A": 2, "B": 2, "C": 2, "D": 0}
    assert grow_candidates(ranks, tried, comps, degree, 2, 8) == [("D", "C"), ("D", "B")]
    assert grow_candidates(ranks, tried, [{"A", "B", "C", "D"}], degree, 2, 8) == []
    assert grow_candidates(ranks, tried, comps, {**degree, "C": 8, "B": 8}, 2, 8) == []


@pytest.fixture(scope="module")
def grid9(tmp_path_factory):
    """A 3 x 3 simulated grid (`small` scene, 50k points a scan) with no positions and no ALS."""
    from plotmosaic.config.simulate import grid_layout
    from plotmosaic.simulate.run import make_config, simulate

    root = tmp_path_factory.mktemp("grid9")
    cfg = make_config("small").model_copy(update={"scan_layout": grid_layout(3, GRID)})
    simulate(root, config=cfg, seed=0)
    text = (root / "manifest.toml").read_text()
    (root / "noals.toml").write_text(text.replace('[[als]]\npath = "als/als.laz"\n', ""))
    return root


@pytest.mark.slow
def test_nine_scan_grid_without_positions_or_als(grid9, tmp_path):
    from plotmosaic.manifest import load_manifest
    from plotmosaic.stages.register_plot import match_signatures, pair_settings, plan_jobs

    manifest = load_manifest(grid9 / "noals.toml")
    assert not manifest.als
    config = RegisterConfig()
    linked, ranks = match_signatures(
        manifest, config, 0, tmp_path, {}, Workers(jobs=1, progress=False)
    )
    truth = json.loads((grid9 / "ground_truth.json").read_text())["scans"]
    pos = {k: np.asarray(v["transform"])[:2, 3] for k, v in truth.items()}
    ids = sorted(pos)
    for (
        s
    ) in ids:  # each scan's best-ranked partner is a grid neighbour; its neighbours in the top 4
        near = {o for o in ids if o != s and np.linalg.norm(pos[o] - pos[s]) < GRID + 1}
        assert ranks[s][0] in near
        assert len(near & set(ranks[s][:4])) >= len(near) - 1
    jobs = plan_jobs(manifest, config, pair_settings(config, 0, tmp_path / "prepared"), {}, linked)
    assert len(jobs) < 9 * 8 / 2  # not all pairs
    planned = {frozenset((j.source, j.target)) for j in jobs}
    grid = {
        frozenset((a, b))
        for a in ids
        for b in ids
        if a < b and np.linalg.norm(pos[a] - pos[b]) < GRID + 1
    }
    assert len(grid & planned) >= len(grid) - 1
    assert nx.is_connected(nx.Graph([tuple(p) for p in planned]))
    # a scan id -> ranked list of the other eight (or fewer, those with matching stems)
    assert all(len(r) <= 8 for r in ranks.values())

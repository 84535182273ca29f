"""Candidate pairs, cache keys and the pair executor's bookkeeping (no registration involved)."""

import numpy as np
import pytest
from typer.testing import CliRunner

from plotmosaic.cli import app
from plotmosaic.config.align import AlignConfig
from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.cache import PairCache, file_hash
from plotmosaic.graph.executor import Workers, run_pairs
from plotmosaic.graph.jobs import JobSettings, PairJob, ScanFile, pair_job
from plotmosaic.graph.pairs import candidate_pairs, spanning_first
from plotmosaic.manifest import Manifest, Plot, Scan
from plotmosaic.stages.register_plot import pair_settings, plan_jobs, tree_first
from plotmosaic.stages.register_plot.grow import from_graph, joining, next_round
from plotmosaic.stages.register_plot.pairs import Pairs


def _plot(positions):
    scans = [Scan(id=f"s{i}", path=f"s{i}.laz", approx_position=p) for i, p in enumerate(positions)]
    return Plot(id="P", scans=scans)


def test_pairs_all_without_positions_and_by_distance_with_them():
    plot = _plot([None, None, None, None])
    pairs = [(s.id, t.id) for s, t in candidate_pairs(plot, 10.0)]
    assert pairs == [
        ("s1", "s0"),
        ("s2", "s0"),
        ("s3", "s0"),
        ("s2", "s1"),
        ("s3", "s1"),
        ("s3", "s2"),
    ]
    plot = _plot([(0, 0, 0), (8, 0, 0), (30, 0, 0), (36, 0, 5)])
    assert [(s.id, t.id) for s, t in candidate_pairs(plot, 10.0)] == [("s1", "s0"), ("s3", "s2")]
    assert len(candidate_pairs(plot, None)) == 6


def test_cache_key_follows_content_and_settings(tmp_path):
    a, b = tmp_path / "a.laz", tmp_path / "b.laz"
    a.write_bytes(b"x" * 3_000_000)
    b.write_bytes(b"y" * 10)
    coarse = AlignConfig().model_copy(update={"voxel": 0.1})

    def key_of(a, b, kinds=("tls", "tls"), levels=(3, 3), config=AlignConfig(), seed=0):
        sides = (
            ScanFile("a", str(a), kinds[0], levels[0]),
            ScanFile("b", str(b), kinds[1], levels[1]),
        )
        return pair_job(JobSettings(config, seed), *sides).key

    key = key_of(a, b)
    assert key == key_of(a, b)
    assert key != key_of(b, a)
    assert key != key_of(a, b, config=coarse)
    assert key != key_of(a, b, seed=1)
    assert key != key_of(a, b, ("tls", "als"), (3, 2))
    before = file_hash(b)
    b.write_bytes(b"z" * 11)  # new content (and size): new hash, new key
    assert file_hash(b) != before and key_of(a, b) != key
    cache = PairCache(tmp_path / "pairs")
    assert cache.get(key) is None
    cache.put(
        key,
        {
            "key": key,
            "source": "s1",
            "target": "s0",
            "status": "ok",
            "transform": np.eye(4).tolist(),
            "information": np.eye(6).tolist(),
            "fitness": 0.5,
            "inlier_rmse": 0.01,
            "overlap": 0.5,
        },
    )
    (tmp_path / "pairs" / "broken.json").write_text(
        '{"status": "o'
    )  # e.g. a file cut short by hand
    assert cache.get(key)["status"] == "ok" and cache.get("broken") is None and cache.writes == 1


def test_unreadable_pair_becomes_failed_record_not_crash(tmp_path):
    bad = tmp_path / "bad.laz"
    bad.write_bytes(b"not a laz file")
    job = PairJob("k", "s1", "s0", str(bad), str(bad), "tls", "tls", 3, 3, AlignConfig(), 0)
    (record,) = run_pairs([job], Workers(jobs=1, progress=False))
    assert (
        record["status"] == "failed"
        and "bad.laz" in record["error"]
        and record["cacheable"] is False
    )


runner = CliRunner()


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--executor", "spark"], "--executor"),
        (["--jobs", "0"], "--jobs"),
        (["--scheduler", "tcp://x:1"], "--scheduler"),
    ],
)
def test_register_plot_bad_options_one_line(tmp_path, args, needle):
    manifest = tmp_path / "m.toml"
    manifest.write_text('[[scans]]\nid = "a"\npath = "a.laz"\n')
    result = runner.invoke(
        app, ["register-plot", str(manifest), "--out", str(tmp_path / "o"), *args]
    )
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and needle in lines[0], result.output


def test_register_plot_missing_scan_file_one_line(tmp_path):
    manifest = tmp_path / "m.toml"
    manifest.write_text('[[scans]]\nid = "a"\npath = "a.laz"\n')
    result = runner.invoke(app, ["register-plot", str(manifest), "--out", str(tmp_path / "o")])
    assert result.exit_code == 2 and "a.laz" in result.output and "Traceback" not in result.output


def test_tie_to_als_needs_als_tile(tmp_path):
    from plotmosaic.io.las import PointCloud, write_cloud
    from plotmosaic.poses import Poses, ScanPose

    write_cloud(tmp_path / "a.laz", PointCloud(np.random.default_rng(0).normal(size=(100, 3))))
    manifest = tmp_path / "m.toml"
    manifest.write_text('[[scans]]\nid = "a"\npath = "a.laz"\n')
    Poses({"a": ScanPose(np.eye(4), "plot")}).save(tmp_path / "poses.json")
    result = runner.invoke(
        app,
        [
            "tie-to-als",
            str(manifest),
            "--poses",
            str(tmp_path / "poses.json"),
            "--out",
            str(tmp_path / "g"),
        ],
    )
    assert (
        result.exit_code == 2
        and "als" in result.output.lower()
        and "Traceback" not in result.output
    )


def _grid_plot(side, spacing=15.0, seed=0):
    rng = np.random.default_rng(seed)
    pos = [
        (i * spacing + rng.normal(0, 1), j * spacing + rng.normal(0, 1), 0.0)
        for i in range(side)
        for j in range(side)
    ]
    return _plot(pos)


def test_big_plot_pairs_grow_linearly_connected_with_loops():
    import networkx as nx

    counts = {}
    for side in (3, 5, 7):
        plot = _grid_plot(side)
        pairs = candidate_pairs(plot, 60.0)
        G = nx.Graph([(s.id, t.id) for s, t in pairs])
        n = side * side
        counts[n] = len(pairs)
        assert set(G.nodes) == {s.id for s in plot.scans} and nx.is_connected(G)
        assert max(d for _, d in G.degree()) <= 8  # at most 8 pairs a scan
        assert (
            min(nx.triangles(G).values()) >= 1
        )  # every scan closes a loop: its edges can be checked
        assert all(
            plot.scans.index(s) > plot.scans.index(t) for s, t in pairs
        )  # later scan is the source
    assert counts[9] <= 36 and counts[49] <= 4 * 49 and counts[49] / 49 <= 1.2 * counts[25] / 25
    assert counts[49] < 49 * 48 / 2 / 5  # all pairs would be 1176


def test_small_plot_keeps_every_pair_and_far_groups_stay_apart():
    assert (
        len(candidate_pairs(_grid_plot(2), 60.0)) == 6
    )  # <= 8 scans: all pairs, as for the paper's five
    from plotmosaic.graph.pairs import neighbour_pairs

    xy = np.array(
        [(x, y) for x in range(0, 60, 15) for y in range(0, 45, 15)]
        + [(x + 1000, 0) for x in range(0, 45, 15)]
    )
    pairs = neighbour_pairs(xy, 6, 8, 60.0)
    assert not any(
        i < 12 <= j for i, j in pairs
    )  # 1 km away: not linked, reported unplaced instead
    assert len(neighbour_pairs(xy, 6, 8, None)) > len(
        pairs
    )  # without a distance cap the groups are joined


def test_positions_from_the_als_step_select_pairs_and_give_priors():
    from plotmosaic.graph.placement import prior

    plot = _plot([None] * 12)
    rng = np.random.default_rng(2)
    poses = {}
    for k, s in enumerate(plot.scans[:-1]):  # the last scan could not be placed on the ALS
        T = np.eye(4)
        c, si = np.cos(k), np.sin(k)
        T[:2, :2] = [[c, -si], [si, c]]
        T[:3, 3] = [(k % 4) * 15.0 + 470000.0, (k // 4) * 15.0 + 3810000.0, rng.normal()]
        poses[s.id] = T
    pairs = candidate_pairs(plot, 60.0, {sid: T[:3, 3] for sid, T in poses.items()})
    ids = {(s.id, t.id) for s, t in pairs}
    lost = plot.scans[-1].id
    partners = [
        t for s, t in ids if s == lost
    ]  # unplaced: its neighbours in the manifest, nearest first, capped
    assert "s10" in partners and 2 <= len(partners) <= 8
    import networkx as nx

    assert max(d for _, d in nx.Graph(list(ids)).degree()) <= 8
    assert len(ids) < 66 and all(plot.scans.index(s) > plot.scans.index(t) for s, t in pairs)
    P = np.asarray(prior(poses, "s3", "s1"))
    assert np.allclose(poses["s1"] @ P, poses["s3"]) and prior(poses, lost, "s1") is None


def _exact_grid(side, spacing=18.0):
    """Scan id -> 4x4 pose on a `side` x `side` grid (as from the ALS step: exact positions)."""
    poses = {}
    for k in range(side * side):
        T = np.eye(4)
        c, s = np.cos(0.3 * k), np.sin(0.3 * k)
        T[:2, :2] = [[c, -s], [s, c]]
        T[:3, 3] = [(k % side) * spacing + 470000.0, (k // side) * spacing + 3810000.0, 0.1 * k]
        poses[f"s{k}"] = T
    return poses


def test_placed_scans_are_paired_within_reach_of_their_spacing():
    from plotmosaic.graph.pairs import reach_distance, scan_spacing

    poses = _exact_grid(6)
    plot = _plot([None] * 36)
    holes = {"s14", "s22", "s23", "s28"}  # not placed on the ALS
    placed = {k: T[:3, 3] for k, T in poses.items() if k not in holes}
    xy = np.array(list(placed.values()))
    assert scan_spacing(xy) == pytest.approx(18.0)
    assert reach_distance(xy, 1.25, 60.0) == pytest.approx(22.5)
    assert reach_distance(xy, 1.25, 20.0) == 20.0 and reach_distance(xy, None, 60.0) == 60.0
    pairs = candidate_pairs(plot, 60.0, placed, reach=1.25)
    both = [(s.id, t.id) for s, t in pairs if s.id in placed and t.id in placed]
    d = [np.linalg.norm((placed[a] - placed[b])[:2]) for a, b in both]
    assert max(d) <= 22.5  # no diagonal, none across a hole
    grid = {
        frozenset((a, b))
        for a in placed
        for b in placed
        if a < b and np.linalg.norm((placed[a] - placed[b])[:2]) < 19
    }
    assert grid == {frozenset(p) for p in both}  # every grid neighbour of two placed scans
    # without the reach (manifest positions, approximate), the holes are bridged by farther pairs
    far = candidate_pairs(plot, 60.0, placed)
    assert (
        max(
            np.linalg.norm((placed[s.id] - placed[t.id])[:2])
            for s, t in far
            if s.id in placed and t.id in placed
        )
        > 30
    )


def test_graph_placed_scans_get_their_neighbours_verified_first(tmp_path):
    import networkx as nx

    from plotmosaic.config.register import RegisterConfig
    from plotmosaic.manifest import Manifest
    from plotmosaic.stages.register_plot import pair_settings, plot_pair, position_jobs

    for k in range(16):
        (tmp_path / f"s{k}.laz").write_bytes(bytes([k]) * 10)
    plot = Plot(id="P", scans=[Scan(id=f"s{k}", path=f"s{k}.laz") for k in range(16)])
    manifest = Manifest(plots=[plot], source=tmp_path / "m.toml")
    config = RegisterConfig()
    poses = _exact_grid(4)
    poses.pop("s15")  # the graph has not placed it
    settings = pair_settings(config, 0, tmp_path)
    done = [plot_pair(settings, manifest, plot, ("s1", "s0"), {})]
    done += [plot_pair(settings, manifest, plot, (f"s{k}", "s5"), {}) for k in range(6, 13)]
    jobs = position_jobs(manifest, config, settings, poses, done)
    got = {frozenset((j.source, j.target)) for j in jobs}
    assert frozenset(("s1", "s0")) not in got  # tried already
    assert all(j.start == "stored" and j.init is not None for j in jobs)  # a prior, verified first
    for j in jobs:
        assert "s15" not in (j.source, j.target)
        d = np.linalg.norm((poses[j.source] - poses[j.target])[:2, 3])
        assert d < 19  # neighbours only
        T = np.asarray(j.init)
        assert np.allclose(poses[j.target] @ T, poses[j.source])  # the graph's relative pose
    degree = nx.Graph([(j.source, j.target) for j in done + jobs]).degree()
    assert max(d for _, d in degree) <= config.pairs.max_per_scan
    assert degree["s5"] == 8  # capped: s5 had 7 pairs, one more neighbour at most
    assert frozenset(("s14", "s13")) in got and frozenset(("s11", "s7")) in got


def test_spanning_first_takes_pairs_in_order_one_per_join():
    pairs = [("a", "b"), ("b", "c"), ("a", "c"), ("c", "d"), ("d", "b")]
    assert spanning_first(pairs) == [0, 1, 3]  # (a, c) and (d, b) close loops
    assert spanning_first(pairs, joined=[("a", "c")]) == [0, 3]
    assert spanning_first([]) == []


def _jobs_of(tmp_path, n, placed=None):
    """A plot of `n` scans (tiny files: no registration) and its planned pair jobs."""
    for k in range(n):
        (tmp_path / f"s{k}.laz").write_bytes(bytes([k]) * 10)
    plot = Plot(id="P", scans=[Scan(id=f"s{k}", path=f"s{k}.laz") for k in range(n)])
    manifest = Manifest(plots=[plot], source=tmp_path / "m.toml")
    config = RegisterConfig()
    return manifest, plan_jobs(manifest, config, pair_settings(config, 0, tmp_path), placed)


def test_a_small_plot_runs_a_spanning_tree_first_and_its_verified_priors_lead(tmp_path):
    import networkx as nx

    manifest, jobs = _jobs_of(tmp_path, 5)
    first, deferred = tree_first(manifest, jobs, {}, set())
    # no positions: a star around the first scan (the plan's order), the other six pairs wait
    assert [(j.source, j.target) for j in first] == [(f"s{k}", "s0") for k in range(1, 5)]
    assert len(deferred) == 6 and not any(
        j.start != "prior" or j.init is not None for j in deferred
    )
    assert {j.key for j in first} | {j.key for j in deferred} == {j.key for j in jobs}
    # positions (e.g. stored poses): the nearest scans first; a verified prior before any search
    poses = _exact_grid(3)
    placed = {f"s{k}": poses[f"s{k}"] for k in range(5)}
    manifest, jobs = _jobs_of(tmp_path, 5, placed)
    first, deferred = tree_first(manifest, jobs, placed, {"s3", "s4"})
    tree = nx.Graph([(j.source, j.target) for j in first])
    assert nx.is_tree(tree) and tree.number_of_nodes() == 5
    assert (first[0].source, first[0].target) == ("s4", "s3") and first[0].start == "stored"
    for j in first[1:]:
        d = np.linalg.norm((poses[j.source] - poses[j.target])[:2, 3])
        assert d == pytest.approx(18.0)  # grid neighbours, no diagonal
        assert j.start == "prior"  # a prior not verified first: the search runs


def test_loop_pairs_start_from_the_graph_and_pieces_are_joined_once(tmp_path):
    manifest, jobs = _jobs_of(tmp_path, 5)
    by_pair = {(j.source, j.target): j for j in jobs}
    poses = {k: T for k, T in _exact_grid(3).items() if k in ("s0", "s1", "s2")}
    ready = from_graph(jobs, poses)
    assert {(j.source, j.target) for j in ready} == {("s1", "s0"), ("s2", "s0"), ("s2", "s1")}
    for j in ready:
        assert j.start == "stored" and j.key.startswith(
            by_pair[(j.source, j.target)].key + "-stored-"
        )
        assert np.allclose(poses[j.target] @ np.asarray(j.init), poses[j.source])
    # s3 and s4 unplaced but verified together: one pair joins them to the placed piece
    ok = by_pair[("s4", "s3")]
    done = Pairs(jobs=[ok], records={ok.key: {"status": "ok"}}, computed=1)
    rest = [j for j in jobs if (j.source, j.target) not in {("s1", "s0"), ("s4", "s3")}]
    picked = joining(rest, poses, done)
    assert [(j.source, j.target) for j in picked] == [("s3", "s0")]
    failed = Pairs(jobs=[ok], records={ok.key: {"status": "failed"}}, computed=1)
    picked = joining(rest, poses, failed)
    assert [(j.source, j.target) for j in picked] == [("s3", "s0"), ("s4", "s0")]
    # one round: the loop pairs of the placed piece and, beside them, the joins of the rest
    both = next_round(rest, poses, done)
    assert [(j.source, j.target, j.start) for j in both] == [
        ("s2", "s0", "stored"),
        ("s2", "s1", "stored"),
        ("s3", "s0", "prior"),
    ]

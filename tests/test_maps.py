"""Scan-to-map placement (graph/maps.py) and the reasons an unplaced scan is named with (issue 54).

A scan registered against the union of its placed neighbours lands on its true pose and yields one
edge to each neighbour it overlaps; a wrong start is never returned as a pose."""

import json

import networkx as nx
import numpy as np
import pytest

from plotmosaic.config.align import AlignConfig
from plotmosaic.config.scale import MapConfig
from plotmosaic.graph.maps import MapJob, Member, map_key, run_map_job
from plotmosaic.graph.posegraph import build_graph
from plotmosaic.graph.prepared import PrepareJob, prepared_key
from plotmosaic.graph.unplaced import unplaced_reasons
from plotmosaic.io.frame import inverse, pose_error
from plotmosaic.manifest import load_manifest

MAX_M, MAX_DEG = 0.03, 0.15  # a sparse survey's bound (issue 54)


def _truth(sim) -> dict[str, np.ndarray]:
    scans = json.loads((sim.outdir / "ground_truth.json").read_text())["scans"]
    return {k: np.asarray(v["transform"], dtype=float) for k, v in scans.items()}


def _prepare_job(sim, scan_id: str, folder) -> PrepareJob:
    m = load_manifest(sim.outdir / "manifest.toml")
    scan = next(s for s in m.scans if s.id == scan_id)
    path = str(m.resolve(scan.path))
    key = prepared_key(path, "tls", scan.k, AlignConfig(), 0)
    return PrepareJob(key, scan.id, path, "tls", scan.k, AlignConfig(), 0, str(folder))


def _job(sim, scan: str, members: list[str], start: np.ndarray | None, folder) -> MapJob:
    truth = _truth(sim)
    frame = inverse(truth["P1-S0"])  # the plot frame: the reference scan's
    config = MapConfig()
    rows = lambda T: tuple(tuple(float(v) for v in r) for r in T)  # noqa: E731
    team = tuple(
        Member(scan=m, prepared=_prepare_job(sim, m, folder), pose=rows(frame @ truth[m]))
        for m in members
    )
    init = None if start is None else rows(start)
    fields = {"scan": scan, "members": members, "init": init}
    return MapJob(
        key=map_key(fields),
        source=scan,
        prepared=_prepare_job(sim, scan, folder),
        members=team,
        init=init,
        margin=config.margin_m,
        thin=None if start is not None else config.thin_voxel,
        config=AlignConfig(),
        seed=0,
        edge_distance=config.edge_distance,
        min_edge_points=config.min_edge_points,
    )


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("prepared")


def test_a_scan_placed_on_its_neighbours_lands_on_its_true_pose(small_sim, cache):
    truth = _truth(small_sim)
    true = inverse(truth["P1-S0"]) @ truth["P1-S1"]
    start = true.copy()
    start[:3, 3] += [0.05, -0.04, 0.02]  # a placement's few centimetres off
    record = run_map_job(_job(small_sim, "P1-S1", ["P1-S0", "P1-S2", "P1-S4"], start, cache))
    assert record["status"] == "ok", record.get("error")
    deg, m = pose_error(np.asarray(record["transform"]), true)
    assert m < MAX_M and deg < MAX_DEG, (m, deg)
    members = {e["target"] for e in record["edges"]}
    assert "P1-S0" in members and members <= {"P1-S0", "P1-S2", "P1-S4"}
    for e in record["edges"]:  # each edge: the scan in that member's frame, with its information
        member_true = inverse(truth[e["target"]]) @ truth["P1-S1"]
        deg, m = pose_error(np.asarray(e["transform"]), member_true)
        assert m < MAX_M and deg < MAX_DEG, (e["target"], m, deg)
        info = np.asarray(e["information"])
        assert np.all(np.linalg.eigvalsh(info) > 0) and e["points"] >= MapConfig().min_edge_points


def test_a_wrong_start_on_the_map_is_never_returned(small_sim, cache):
    truth = _truth(small_sim)
    true = inverse(truth["P1-S0"]) @ truth["P1-S3"]
    wrong = true.copy()
    c, s = np.cos(np.radians(40)), np.sin(np.radians(40))
    wrong[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ wrong[:3, :3]
    wrong[:3, 3] += [4.0, -3.0, 0.0]
    record = run_map_job(_job(small_sim, "P1-S3", ["P1-S0", "P1-S1", "P1-S2"], wrong, cache))
    if record["status"] == "ok":  # the search found the scan from there: it must be right
        deg, m = pose_error(np.asarray(record["transform"]), true)
        assert m < MAX_M and deg < MAX_DEG, (m, deg)
    else:  # refused: no pose, and the edges of none
        assert record["status"] == "failed" and "transform" not in record and "edges" not in record


def test_an_unplaced_scan_is_named_with_its_best_attempt():
    G = build_graph(
        {"a": {}, "b": {}, "c": {}, "d": {}},
        [
            {"source": "b", "target": "a", "status": "ok", "transform": np.eye(4)},
            {
                "source": "c",
                "target": "a",
                "status": "failed",
                "error": "pair cannot be registered: blunt fit: sharpness 0.010 < 0.03 (fitness 1)",
                "overlap": 0.13,
            },
            {
                "source": "c",
                "target": "map",
                "status": "failed",
                "error": "pair cannot be registered: judge score 0.05 < 0.12 (the clouds...)",
                "overlap": 0.21,
            },
        ],
    )
    reasons = {u.scan: u for u in unplaced_reasons(G, ["c", "d"])}
    assert reasons["c"].partner == "map" and reasons["c"].overlap == pytest.approx(0.21)
    assert reasons["c"].line() == "c: best overlap 0.210 with map (judge score 0.05 < 0.12)"
    assert reasons["d"].partner is None and "no pair was tried" in reasons["d"].line()
    assert isinstance(G, nx.Graph)

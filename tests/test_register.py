"""register-plot and tie-to-als end to end on the `small` simulated plot.

To keep the suite short the plot is cut to three neighbouring scans (S0 centre, S2 and S3 on the
west side: three pairs, two by the search and the third from their poses). One run is interrupted
after its first pair, resumed, and re-run; the same cache then serves the checks on poses, the
outputs, the Dask executor and tie-to-als.
"""

import json
import re

import numpy as np
import pytest
from pyproj import CRS

from plotmosaic.config.register import RegisterConfig
from plotmosaic.graph.cache import PairCache
from plotmosaic.graph.executor import Workers
from plotmosaic.graph.posegraph import inverse, pose_error
from plotmosaic.manifest import dump_manifest, load_manifest
from plotmosaic.poses import load_poses
from plotmosaic.stages.register_plot import register_plot

pytestmark = pytest.mark.slow
SUBSET = ["P1-S0", "P1-S2", "P1-S3"]


def subset_manifest(sim, scan_ids, folder):
    """The simulator's manifest with only some scans, paths made absolute."""
    m = load_manifest(sim.manifest_path)
    plot = m.plots[0]
    scans = [
        s.model_copy(update={"path": m.resolve(s.path).resolve()})
        for s in plot.scans
        if s.id in scan_ids
    ]
    als = [t.model_copy(update={"path": m.resolve(t.path).resolve()}) for t in m.als]
    sub = m.model_copy(update={"plots": [plot.model_copy(update={"scans": scans})], "als": als})
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "manifest.toml"
    path.write_text(dump_manifest(sub))
    return path


class Interrupt:
    """Ctrl-C after `after` pairs have finished (and been cached)."""

    def __init__(self, after):
        self.after, self.seen = after, 0

    def __call__(self, record):
        self.seen += 1
        if self.seen >= self.after:
            raise KeyboardInterrupt


@pytest.fixture(scope="module")
def runs(small_sim, tmp_path_factory):
    root = tmp_path_factory.mktemp("register")
    manifest = subset_manifest(small_sim, SUBSET, root)
    out = root / "out"
    with pytest.raises(KeyboardInterrupt):
        register_plot(
            manifest, out, workers=Workers(jobs=1, progress=False), on_result=Interrupt(1)
        )
    after_crash = PairCache(out / "pairs").keys()
    resumed = register_plot(manifest, out, workers=Workers(jobs=1, progress=False))
    mtimes = {p.name: p.stat().st_mtime_ns for p in (out / "pairs").glob("*.json")}
    again = register_plot(manifest, out, workers=Workers(jobs=1, progress=False))
    return {
        "manifest": manifest,
        "out": out,
        "after_crash": after_crash,
        "resumed": resumed,
        "again": again,
        "mtimes": mtimes,
        "sim": small_sim,
    }


def test_interrupted_run_resumes_without_redoing_pairs(runs):
    assert (
        len(runs["after_crash"]) == 1
    )  # the pair finished before Ctrl-C was kept, nothing half-written
    assert runs["resumed"].pairs == 3 and runs["resumed"].computed == 2
    assert runs["again"].computed == 0  # a full re-run registers nothing
    assert {p.name: p.stat().st_mtime_ns for p in (runs["out"] / "pairs").glob("*.json")} == runs[
        "mtimes"
    ]
    a, b = runs["resumed"].poses, runs["again"].poses
    for sid in a.scans:
        assert np.array_equal(a.transform(sid), b.transform(sid))


def test_the_loop_pair_starts_from_the_spanning_tree(runs):
    """S2 and S3 onto S0 by the global search (a star around the first scan); S3 -> S2 then starts
    from the pose those two imply and is verified from there, no search."""
    records = [json.loads(p.read_text()) for p in (runs["out"] / "pairs").glob("*.json")]
    searched = {
        (r["source"], r["target"]) for r in records if "coarse_skipped" not in r.get("steps", {})
    }
    assert searched == {("P1-S2", "P1-S0"), ("P1-S3", "P1-S0")}
    (loop,) = [r for r in records if r.get("steps", {}).get("coarse_skipped")]
    assert (loop["source"], loop["target"]) == ("P1-S3", "P1-S2") and loop["status"] == "ok"
    assert loop["coarse"]["stored_pose"]["verified"]


def test_poses_match_ground_truth(runs):
    truth = load_poses(runs["sim"].ground_truth_path)
    poses = load_poses(runs["out"] / "poses.json")
    assert poses.frame == "plot" and set(poses.scans) == set(SUBSET), runs["again"].unplaced
    ref = runs["again"].plots[0].reference
    assert np.allclose(poses.transform(ref), np.eye(4))
    for sid in SUBSET:
        expected = inverse(truth.transform(ref)) @ truth.transform(sid)
        rot, trans = pose_error(poses.transform(sid), expected)
        assert rot < 0.1 and trans < 0.02, (sid, rot, trans)
        sigma = poses.scans[sid].sigma
        assert sigma is not None and len(sigma) == 6 and np.all(sigma >= 0)


def test_outputs_written(runs):
    out = runs["out"]
    graph = json.loads((out / "graph.json").read_text())
    assert {n["id"] for n in graph["nodes"]} == set(SUBSET)
    assert len(graph["edges"]) + len(graph["graph"]["failed"]) == 3
    for e in graph["edges"]:
        assert np.asarray(e["transform"]).shape == (4, 4) and np.asarray(
            e["information"]
        ).shape == (6, 6)
        assert {
            "fitness",
            "inlier_rmse",
            "overlap",
            "confidence",
            "residual_before",
            "residual_after",
        } <= set(e)
    report = (out / "report.md").read_text()
    assert "| source | target |" in report and "P1-S3" in report
    for png in ("P1_scans.png", "P1_graph.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_dask_executor_gives_the_same_edge(runs, tmp_path):
    """The same plot through a Dask cluster, the tree's pairs cached from the local run: the scans
    are prepared there and the loop pair registered there, to the local run's edge and poses."""
    import shutil

    from dask.distributed import LocalCluster

    records = [json.loads(p.read_text()) for p in (runs["out"] / "pairs").glob("*.json")]
    (local,) = [r for r in records if r.get("steps", {}).get("coarse_skipped")]
    (tmp_path / "out" / "pairs").mkdir(parents=True)
    for p in (runs["out"] / "pairs").glob("*.json"):
        if p.stem != local["key"]:
            shutil.copy(p, tmp_path / "out" / "pairs" / p.name)
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        result = register_plot(
            runs["manifest"],
            tmp_path / "out",
            workers=Workers("dask", scheduler=cluster.scheduler_address, progress=False),
        )
    assert result.computed == 1
    remote = PairCache(tmp_path / "out" / "pairs").get(local["key"])
    assert remote is not None and local["status"] == remote["status"] == "ok"
    assert np.allclose(local["transform"], remote["transform"], atol=1e-6)
    assert local["fitness"] == pytest.approx(remote["fitness"], abs=1e-6)
    here = runs["again"].poses
    assert set(here.scans) == set(result.poses.scans) == set(SUBSET)
    for sid in here.scans:
        assert np.allclose(here.transform(sid), result.poses.transform(sid), atol=1e-6)


def test_tie_to_als_georeferences_every_scan(runs, tmp_path, monkeypatch):
    import plotmosaic.io.las as las
    from plotmosaic.stages.tie_to_als import tie_to_als

    read, inner = [], las.read_cloud

    def counted(path, *args, **kwargs):  # the real reader, the paths noted
        read.append(str(path))
        return inner(path, *args, **kwargs)

    monkeypatch.setattr(las, "read_cloud", counted)
    result = tie_to_als(  # one job: every read happens in this process, where it is counted
        runs["manifest"],
        runs["out"] / "poses.json",
        tmp_path / "geo",
        workers=Workers(jobs=1, progress=False),
    )
    # the plot cloud and the ALS crop are written once and registered from memory, not read back
    assert (tmp_path / "geo" / "plots" / "P1.laz").is_file()
    assert not [p for p in read if "plots" in p], read
    truth = load_poses(runs["sim"].ground_truth_path)
    poses = load_poses(tmp_path / "geo" / "poses.json")
    assert poses.frame == "crs" and CRS.from_user_input(poses.crs).to_epsg() == 26912
    assert set(poses.scans) == set(SUBSET)
    for sid in SUBSET:
        rot, trans = pose_error(poses.transform(sid), truth.transform(sid))
        assert rot < 0.2 and trans < 0.05, (sid, rot, trans)
    (anchor,) = result.anchors
    assert anchor.status == "ok" and anchor.fitness > 0.2
    assert anchor.fine_margin is not None and anchor.fit["als_offset_median_m"] is not None
    md = (tmp_path / "geo" / "report.md").read_text()
    assert "Anchors" in md
    # one anchor moves the plot as one piece: its within-plot checks are register-plot's, linked
    assert "as one piece" in md and "report.html" in md
    assert (tmp_path / "geo" / "P1_scans.png").is_file() and (
        tmp_path / "geo" / "P1_map.png"
    ).is_file()
    assert "not recorded" not in (tmp_path / "geo" / "report.html").read_text()  # stage times


def test_tie_to_als_keeps_the_plot_as_register_plot_placed_it(runs, tmp_path):
    """register-plot's solve may hold a plot by more than its pairs (ALS placements of a big plot):
    tie-to-als must not re-solve the pairs alone and undo it. Here graph.json's pairs are made to
    disagree with poses.json by 3 cm; the georeferenced plot keeps poses.json's shape."""
    import shutil

    from plotmosaic.stages.tie_to_als import tie_to_als

    src = tmp_path / "out"
    shutil.copytree(runs["out"], src, ignore=shutil.ignore_patterns("pairs"))
    graph = json.loads((src / "graph.json").read_text())
    for e in graph["edges"]:
        T = np.asarray(e["transform"])
        T[:3, 3] += [0.03, -0.02, 0.0]
        e["transform"] = T.tolist()
    (src / "graph.json").write_text(json.dumps(graph))
    tie_to_als(
        runs["manifest"],
        src / "poses.json",
        tmp_path / "geo",
        workers=Workers(jobs=1, progress=False),
    )
    before, after = load_poses(src / "poses.json"), load_poses(tmp_path / "geo" / "poses.json")
    ref = SUBSET[0]
    for sid in SUBSET:
        was = inverse(before.transform(ref)) @ before.transform(sid)
        now = inverse(after.transform(ref)) @ after.transform(sid)
        rot, trans = pose_error(now, was)
        # float noise only: the poses compose through UTM-sized offsets
        assert rot < 1e-5 and trans < 1e-6, (sid, rot, trans)


def test_cli_rerun_uses_the_cache(runs):
    from typer.testing import CliRunner

    from plotmosaic.cli import app

    result = CliRunner().invoke(
        app, ["register-plot", str(runs["manifest"]), "--out", str(runs["out"]), "--jobs", "1"]
    )
    assert result.exit_code == 0, result.output
    assert (
        "3 pairs" in result.output.replace("pairs: 3", "3 pairs")
        and "0 registered now" in result.output
    )
    assert "P1-S3" in result.output  # the per-scan table
    ref = json.loads((runs["out"] / "poses.json").read_text())["plots"]["P1"]["reference"]
    row = next(line for line in result.output.splitlines() if f" {ref} " in line and "│" in line)
    assert not re.search(r"\d", row.replace(ref, "")), row  # the frame itself: no zero figures


def test_register_plot_reads_the_report_settings(runs, tmp_path):
    """`[report]` drives register-plot's page as it does tie-to-als's: no 3D view when asked for
    none, the pictures' point budget as set."""
    import shutil

    from plotmosaic.config.report import ReportConfig

    assert (runs["out"] / "view3d.html").is_file()  # the default writes one
    out = tmp_path / "out"
    shutil.copytree(runs["out"], out)
    (out / "view3d.html").unlink()
    report = ReportConfig(picture_points=5000, view3d_points=0)
    result = register_plot(
        runs["manifest"],
        out,
        RegisterConfig(report=report),
        workers=Workers(jobs=1, progress=False),
    )
    assert result.computed == 0  # the pairs came from the cache: only the solve and the report
    assert (out / "report.html").is_file() and not (out / "view3d.html").exists()

"""`plotmosaic report`: an align result's report, and a run's report written again in its folder."""

from __future__ import annotations

import json
import re

import matplotlib.image as mpimg
import numpy as np
from builders import UTM, split_pair, synthetic_plot
from typer.testing import CliRunner

from plotmosaic.bench.protocol import params_to_matrix
from plotmosaic.cli import app
from plotmosaic.graph.posegraph import build_graph, graph_to_json, optimise
from plotmosaic.io.frame import apply_transform
from plotmosaic.io.las import PointCloud, write_cloud
from plotmosaic.poses import Poses, ScanPose


def _linked_pngs(index) -> list[str]:
    return re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", index.read_text())


def _check_pngs(folder, names):
    for name in names:
        img = mpimg.imread(folder / name)
        assert img.shape[0] > 300 and img.shape[1] > 300
        assert img[..., :3].std() > 0.01  # not a blank canvas


def test_report_for_a_pair(tmp_path):
    src, tgt = split_pair(synthetic_plot(trees=8))
    T = params_to_matrix([1.0, -2.0, 25.0, 3.0, -2.0, 0.5], UTM)
    moved = PointCloud(apply_transform(np.linalg.inv(T), src.xyz))  # the source as a misplaced scan
    write_cloud(tmp_path / "s.laz", moved)
    write_cloud(tmp_path / "t.laz", tgt)
    (tmp_path / "pair.json").write_text(
        json.dumps(
            {
                "transform": T.tolist(),
                "fitness": 0.91,
                "inlier_rmse": 0.012,
                "overlap": 0.8,
                "source_kind": "tls",
                "target_kind": "tls",
                "seconds": 12.5,
                "timings": {
                    "coarse": 3.0,
                    "final_icp": 1.5,
                    "final_iterations": 70,
                    "correction_deg": 0.4,
                    "correction_m": 0.03,
                },
            }
        )
    )
    out = tmp_path / "rep"
    result = CliRunner().invoke(
        app,
        [
            "report",
            "--pair",
            str(tmp_path / "pair.json"),
            str(tmp_path / "s.laz"),
            str(tmp_path / "t.laz"),
            "--out",
            str(out),
            "--points",
            "5000",
        ],
    )
    assert result.exit_code == 0, result.output
    index = out / "report.md"
    linked = _linked_pngs(index)
    assert {
        "before.png",
        "after.png",
        "after_slice.png",
        "levels.png",
        "pair_breast_slice.png",
        "pair_distances.png",
    } <= set(linked)
    assert (out / "report.html").is_file() and "report.html" in result.output
    _check_pngs(out, linked)
    text = index.read_text()
    assert "fitness: 0.9100" in text and f"{T[0, 3]: .9f}" in text
    assert not (out / "index.md").exists()
    page = (out / "report.html").read_text()
    # the transform in a user's words; the time table holds times only
    assert "rotation: " in page and "the source&#x27;s centre moves by" in page
    time_table = page[page.index("How long each stage took") :]
    assert "coarse" in time_table and "final_icp" in time_table
    for measure in ("final_iterations", "correction_deg", "correction_m"):
        assert measure not in time_table
    for png in ("before.png", "after.png"):  # shown on the page, not only written
        assert png.split(".")[0].capitalize() in page
    # the cloud-to-cloud figure rests on thousands of points
    rows = re.findall(r"<td>source s</td><td>target t</td><td>(\d+)</td>", page)
    assert rows and int(rows[0]) >= 2000, rows


def test_report_on_a_result_that_names_its_clouds(tmp_path):
    """`plotmosaic report RESULT.json`: the clouds come from the result's source_path / target_path."""
    src, tgt = split_pair(synthetic_plot(trees=4))
    write_cloud(tmp_path / "s.laz", src)
    write_cloud(tmp_path / "t.laz", tgt)
    (tmp_path / "r.json").write_text(
        json.dumps(
            {
                "transform": np.eye(4).tolist(),
                "source_path": "s.laz",
                "target_path": str(tmp_path / "t.laz"),
            }
        )
    )
    result = CliRunner().invoke(
        app, ["report", str(tmp_path / "r.json"), "--points", "3000", "--no-levels"]
    )
    assert result.exit_code == 0, result.output
    assert (tmp_path / "report-r" / "report.html").is_file()
    (tmp_path / "q.json").write_text(json.dumps({"transform": np.eye(4).tolist()}))
    result = CliRunner().invoke(app, ["report", str(tmp_path / "q.json")])
    assert result.exit_code == 2 and "source_path" in result.output and "--pair" in result.output


def test_report_rejects_a_result_without_transform(tmp_path):
    src, _ = split_pair(synthetic_plot(trees=2))
    write_cloud(tmp_path / "s.laz", src)
    (tmp_path / "bad.json").write_text(json.dumps({"fitness": 1.0}))
    result = CliRunner().invoke(
        app,
        [
            "report",
            "--pair",
            str(tmp_path / "bad.json"),
            str(tmp_path / "s.laz"),
            str(tmp_path / "s.laz"),
        ],
    )
    assert result.exit_code == 2
    assert (
        "bad.json" in result.output
        and "transform" in result.output
        and "Traceback" not in result.output
    )


def test_report_for_a_register_plot_folder(tmp_path):
    """A folder in register-plot's format (graph.json from the pose-graph module, poses.json)."""
    scene = synthetic_plot(trees=8)
    rng = np.random.default_rng(0)
    world = {}  # scan -> scanner-to-world pose
    nodes = {}
    for k, p in enumerate(
        ([0, 0, 0, 0, 0, 0], [0.5, -0.5, 70, 8, 3, 0.2], [-0.5, 0.3, -40, -7, 4, -0.1])
    ):
        world[f"S{k}"] = params_to_matrix(p)  # scanner frame -> plot frame
        idx = rng.choice(len(scene), len(scene) // 3, replace=False)
        path = tmp_path / "scans" / f"S{k}.laz"
        write_cloud(
            path, PointCloud(apply_transform(np.linalg.inv(world[f"S{k}"]), scene.xyz[idx] - UTM))
        )
        nodes[f"S{k}"] = {"plot": "P1", "kind": "tls", "path": str(path)}
    edges = []
    for a, b in (("S1", "S0"), ("S2", "S0"), ("S2", "S1")):
        T = (
            np.linalg.inv(world[b]) @ world[a] @ params_to_matrix([0, 0, 0.05, 0.01, 0, 0])
        )  # a little noise
        edges.append(
            {
                "source": a,
                "target": b,
                "transform": T,
                "fitness": 0.8,
                "inlier_rmse": 0.02,
                "overlap": 0.5,
                "information": np.eye(6) * 1e4,
            }
        )
    G = build_graph(nodes, edges)
    sol = optimise(G, "S0")
    G.graph["calibration"] = {"P1": {"tls-tls/translation": {"factor": 2.25, "redundancy": 3.0}}}
    reg = tmp_path / "reg"
    reg.mkdir()
    (reg / "graph.json").write_text(json.dumps(graph_to_json(G)))
    Poses({n: ScanPose(T, "P1") for n, T in sol.poses.items()}).save(reg / "poses.json")
    result = CliRunner().invoke(app, ["report", str(reg)])
    assert result.exit_code == 0, result.output
    # one report per run: written again in the run's folder, no second page or 3D view
    assert not (reg / "report").exists()
    linked = _linked_pngs(reg / "report.md")
    assert {f"P1_{n}.png" for n in ("graph", "breast_slice", "map", "distances", "scans")} <= set(
        linked
    )
    assert (reg / "report.html").is_file()
    _check_pngs(reg, linked)
    assert "| S1 | S0 |" in (reg / "report.md").read_text()
    # the calibration the run recorded in graph.json is shown with the plot's sigmas
    assert "| tls-tls translation | 2.25 | x 1.50 | 3 |" in (reg / "report.md").read_text()
    assert "P1: sigma calibration" in (reg / "report.html").read_text()
    assert sorted(p.name for p in tmp_path.rglob("report.html")) == ["report.html"]
    assert len(list(tmp_path.rglob("view3d.html"))) <= 1
    # a second run replaces the run's own report (it is the run's, not the user's)
    result = CliRunner().invoke(app, ["report", str(reg)])
    assert result.exit_code == 0, result.output
    result = CliRunner().invoke(app, ["report", str(reg), "--out", str(tmp_path / "x")])
    assert result.exit_code == 2 and "--out" in result.output


def test_3d_view_fits_the_size_cap_with_the_als_as_a_layer(tmp_path):
    """One view3d.html: the scans thinned to fit `[report] view3d_max_mb`, the ALS a trace of its own."""
    from plotmosaic.config.report import ReportConfig
    from plotmosaic.report.view3d import write_3d_view

    rng = np.random.default_rng(0)
    clouds = {f"S{k}": rng.uniform(0, 30, (60_000, 3)) + UTM for k in range(3)}
    als = rng.uniform(-20, 50, (60_000, 3)) + UTM
    roomy = write_3d_view(tmp_path / "a.html", clouds, als, ReportConfig(), seed=0)
    capped = ReportConfig(view3d_max_mb=5.6)
    small = write_3d_view(tmp_path / "b.html", clouds, als, capped, seed=0)
    assert roomy is not None and small is not None
    assert small.stat().st_size <= 5.6e6 < roomy.stat().st_size
    text = small.read_text()
    assert text.count("ALS (click to hide)") == 1 and text.count('"name":"S1"') == 1
    assert text.count("* plotly.js v") == 1  # plotly.js inlined once (its banner names it)
    tiny = ReportConfig(
        view3d_max_mb=1.0
    )  # below plotly.js itself: no page rather than a broken one
    assert write_3d_view(tmp_path / "c.html", clouds, als, tiny, seed=0) is None

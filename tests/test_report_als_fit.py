"""The georeferenced page's fit to the ALS: a plot moved 10 cm up reads +10 cm; the page shows it."""

from __future__ import annotations

import json
from html.parser import HTMLParser

import networkx as nx
import numpy as np
import pytest
from typer.testing import CliRunner

from plotmosaic.bench.protocol import params_to_matrix
from plotmosaic.cli import app
from plotmosaic.config.register import PoseGraphConfig
from plotmosaic.config.report import ReportConfig
from plotmosaic.graph.posegraph import graph_to_json
from plotmosaic.io.las import PointCloud, read_cloud, write_cloud
from plotmosaic.poses import Poses, ScanPose, load_poses
from plotmosaic.report.align_page import motion_of, source_centre
from plotmosaic.report.als_fit import spread
from plotmosaic.report.collect import collect, with_als_fit
from plotmosaic.report.tie_page import AnchorRow, TieRun, render_tie


@pytest.fixture(scope="module")
def plot_data(small_sim):
    """The small plot's true poses, its scans in memory and its ALS returns."""
    truth = {k: v.transform for k, v in load_poses(small_sim.ground_truth_path).scans.items()}
    raw = {str(p): read_cloud(p, attributes=False).xyz for p in small_sim.scan_paths.values()}
    als = np.vstack([read_cloud(p, attributes=False).xyz for p in small_sim.als_paths])
    return truth, raw, als


def _fit(sim, truth, raw, als, dz: float):
    poses = {}
    for k, T in truth.items():
        U = T.copy()
        U[2, 3] += dz
        poses[k] = U
    cfg = ReportConfig()
    view = collect("P1", sorted(truth), sim.scan_paths, poses, lambda p: raw[str(p)], cfg, 0)
    return with_als_fit(view, als, cfg).als


def test_ground_difference_reads_a_plot_moved_10_cm_up(small_sim, plot_data):
    truth, raw, als = plot_data
    at_truth = _fit(small_sim, truth, raw, als, 0.0)
    raised = _fit(small_sim, truth, raw, als, 0.10)
    assert at_truth.ground.count > 500 and raised.ground.count > 500
    assert abs(at_truth.ground.median) < 0.04, at_truth.ground
    assert abs(raised.ground.median - 0.10) < 0.04, raised.ground
    assert abs(raised.ground.median - at_truth.ground.median - 0.10) < 0.01
    # each scan moved with the plot: every scan's own ground reads the 10 cm too
    for before, after in zip(at_truth.scans, raised.scans):
        assert abs(after.ground.median - before.ground.median - 0.10) < 0.01, (before, after)
    # the canopy tops are compared where both see them, and agree at the true poses
    assert at_truth.canopy.count > 20 and abs(at_truth.canopy.median) < 0.5, at_truth.canopy


def test_spread_is_median_and_nmad():
    rng = np.random.default_rng(0)
    s = spread(np.r_[rng.normal(0.1, 0.05, 20_000), [np.nan, 50.0]])
    assert abs(s.median - 0.1) < 0.002 and abs(s.nmad - 0.05) < 0.002 and s.count == 20_001
    assert spread(np.array([np.nan])).count == 0


def test_motion_is_read_at_the_source_centre():
    """A 2 deg turn about the source's own centre plus 3 cm: far from the file origin the matrix's
    translation is metres, the centre moves 3 cm."""
    centre = np.array([470250.0, 3810150.0, 2100.0])
    xyz = centre + np.random.default_rng(0).uniform(-10, 10, (1000, 3))
    xyz = np.vstack([xyz, 2 * centre - xyz])  # the box centred on `centre`
    turn = params_to_matrix([0, 0, 2.0, 0, 0, 0])
    T = np.eye(4)
    T[:3, :3] = turn[:3, :3]
    T[:3, 3] = centre - turn[:3, :3] @ centre + [0.03, 0.0, 0.0]
    m = motion_of(T, source_centre({}, xyz))
    assert np.allclose(source_centre({"source_centre": [1.0, 2.0, 3.0]}, xyz), [1, 2, 3])
    assert np.linalg.norm(T[:3, 3]) > 100
    assert np.allclose(m.moves, [0.03, 0, 0], atol=1e-6) and abs(m.angle_deg - 2.0) < 1e-9
    assert np.allclose(np.abs(m.axis), [0, 0, 1])


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.text, self.captions, self._in = [], [], None

    def handle_starttag(self, tag, attrs):
        self._in = tag

    def handle_data(self, data):
        self.text.append(data)
        if self._in == "figcaption":
            self.captions.append(data)


def _tie_run(sim, truth, out, raw, als) -> TieRun:
    """tie-to-als's result at the true poses: each scan held to the reference, one ALS anchor."""
    ids = sorted(truth)
    G = nx.Graph()
    G.add_node("ALS", kind="als", plot=None)
    for s in ids:
        G.add_node(s, kind="tls", plot="P1", path=str(sim.scan_paths[s]))
    zero = {"translation": 0.0, "rotation_deg": 0.0, "chi2": 0.0}
    for s in ids[1:]:
        G.add_edge(s, ids[0], source=s, target=ids[0], from_poses=True, residual_after=zero)
    G.add_edge(ids[0], "ALS", source=ids[0], target="ALS", anchor=True, residual_after=zero)
    anchor = AnchorRow(
        plot="P1",
        reference=ids[0],
        status="ok",
        fitness=0.5,
        inlier_rmse=0.1,
        fine_margin=0.9,
        als_offset_median_m=-0.004,
        als_offset_nmad_m=0.03,
    )
    return TieRun(
        out=out,
        graph=G,
        anchors=(anchor,),
        poses=truth,
        sigmas={},
        plots={"P1": ids},
        paths=dict(sim.scan_paths),
        offset=np.zeros(3),
        als_xyz=als,
        source="manifest: test",
    )


def test_georeferenced_page_leads_with_the_fit_to_the_als(small_sim, plot_data, tmp_path):
    truth, raw, als = plot_data
    run = _tie_run(small_sim, truth, tmp_path, raw, als)
    cfg = ReportConfig(view3d_points=2000)
    md = render_tie(run, cfg, PoseGraphConfig().sure_edge_confidence, 0, lambda p: raw[str(p)])
    page = _Page()
    page.feed((tmp_path / "report.html").read_text())
    text = " ".join(page.text)
    for what in (
        "ground height of the placed scans minus the ALS ground",
        "canopy top of the placed scans against the ALS canopy",
        "each scan's ground and canopy top against the ALS",
        "breast-height slice",
    ):
        assert any(what in c for c in page.captions), (what, page.captions)
    assert text.count("How to read:") == len(page.captions)
    assert "ground" in text and "off the ALS ground (median), NMAD" in text
    # one anchor per plot: residuals zero by construction are not shown as quality figures
    assert "off the joint solution" not in text and "anchor residual" not in text
    assert "bundle error" not in text and "worst edge" not in text
    # the anchor's own figures instead: the ALS against the TLS surfaces, the fine margin
    assert "ALS returns -0.4 cm off the TLS surfaces" in text and "fine margin 0.90" in text
    assert "held by one edge only" not in text  # the scans are held to the reference by design
    # summary, the pictures that decide, tables, times last
    first_picture = text.index("ground height of the placed scans")
    assert text.index("Summary") < first_picture < text.index("Tables")
    assert text.index("Tables") < text.index("How long each stage took")
    assert "P1_ground_vs_als.png" in md.read_text()
    views3d = list(tmp_path.glob("*.html"))
    assert sorted(p.name for p in views3d) in (["report.html"], ["report.html", "view3d.html"])
    if (tmp_path / "view3d.html").is_file():  # plotly installed: the ALS is a layer of it
        assert "ALS (click to hide)" in (tmp_path / "view3d.html").read_text()


def test_report_dir_rewrites_a_georeferenced_run_in_place(small_sim, plot_data, tmp_path):
    """`plotmosaic report DIR` on a tie-to-als folder: its own report.html again, with the fit to
    the ALS read from the run's ALS crop (plots/<plot>_als.laz)."""
    truth, raw, als = plot_data
    run = _tie_run(small_sim, truth, tmp_path, raw, als)
    geo = tmp_path / "geo"
    (geo / "plots").mkdir(parents=True)
    (geo / "graph.json").write_text(json.dumps(graph_to_json(run.graph)))
    anchors = {
        "P1": {
            "reference": "P1-S0",
            "status": "ok",
            "fitness": 0.5,
            "crop": "buffer",
            "fine_margin": 0.8,
            "als_offset_median_m": 0.002,
            "jackknife_blocks": 25,
        }
    }
    extra = {"offset": [0.0, 0.0, 0.0], "unplaced": [], "anchors": anchors}
    scans = {s: ScanPose(T, "P1") for s, T in truth.items()}
    Poses(scans, frame="crs", crs="EPSG:32612", extra=extra).save(geo / "poses.json")
    write_cloud(geo / "plots" / "P1_als.laz", PointCloud(als))
    (geo / "config-used.toml").write_text("[report]\nview3d_points = 0\n")
    result = CliRunner().invoke(app, ["report", str(geo)])
    assert result.exit_code == 0, result.output
    page = _Page()
    page.feed((geo / "report.html").read_text())
    assert any("minus the ALS ground" in c for c in page.captions), page.captions
    assert (geo / "P1_ground_vs_als.png").is_file() and (geo / "report.md").is_file()
    assert not (geo / "view3d.html").exists()  # the run's own [report] settings: no 3D view
    assert not (geo / "report").exists() and not (geo / "index.md").exists()
    text = " ".join(page.text)
    assert f"folder: {geo}" in text and "manifest:" not in text
    assert "ALS returns +0.2 cm off the TLS surfaces" in text and "fine margin 0.80" in text

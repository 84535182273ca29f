"""report.html: the breast-height slice tells a right pose from a 5 cm / 0.2 deg wrong one; the page is self-contained."""

from __future__ import annotations

import base64
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from plotmosaic.bench.protocol import params_to_matrix
from plotmosaic.io.las import read_cloud
from plotmosaic.poses import load_poses


@pytest.fixture(scope="module")
def dense_sim(tmp_path_factory):
    """The `small` plot with 250k points a scan: at 50k a 10 cm slice holds too few points per stem."""
    from plotmosaic.simulate.run import simulate

    return simulate(tmp_path_factory.mktemp("dense"), "small", seed=0, points_per_scan=250_000)


def _truth(sim) -> dict[str, np.ndarray]:
    return {k: v.transform for k, v in load_poses(sim.ground_truth_path).scans.items()}


def test_breast_slice_rings_double_when_one_scan_is_off(dense_sim):
    from plotmosaic.config.report import ReportConfig
    from plotmosaic.report.build import collect
    from plotmosaic.report.slice import ring_spread

    truth = _truth(dense_sim)
    raw = {
        p: read_cloud(p, attributes=False).xyz for p in dense_sim.scan_paths.values()
    }  # read once
    ids = sorted(truth)
    cfg = ReportConfig()
    good = collect("P1", ids, dense_sim.scan_paths, truth, raw.__getitem__, cfg, 0)
    moved_id = "P1-S2"
    off = dict(truth)
    off[moved_id] = truth[moved_id] @ params_to_matrix(
        [0, 0, 0.2, 0.03, 0.04, 0]
    )  # 5 cm and 0.2 deg, scanner frame
    bad = collect("P1", ids, dense_sim.scan_paths, off, raw.__getitem__, cfg, 0)

    seen = [s for s in good.stems if moved_id in s.arcs]
    assert len(good.stems) >= 4 and len(seen) >= 2, [(s.scans, s.spread) for s in good.stems]
    single, doubled = ring_spread(good.stems, moved_id), ring_spread(bad.stems, moved_id)
    assert single < 0.01  # rings single within a centimetre at the true poses
    assert doubled > 3 * single, (single, doubled)
    # the stems the moved scan does not see stay single
    others = [s.spread for s in bad.stems if moved_id not in s.arcs]
    assert not others or np.median(others) < 0.01


class _Page(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.tables, self.captions, self.links, self.text = [], 0, [], [], []
        self._in = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a)
        elif tag == "table":
            self.tables += 1
        elif tag == "a":
            self.links.append(a.get("href"))
        self._in = tag

    def handle_data(self, data):
        self.text.append(data)
        if self._in == "figcaption":
            self.captions.append(data)

    def handle_endtag(self, tag):
        self._in = None


def _registered_folder(sim, out: Path):
    """register-plot's result on the small plot built from the truth (plus one bad pair), without registering."""
    from plotmosaic.config.register import RegisterConfig
    from plotmosaic.graph.posegraph import build_graph, optimise
    from plotmosaic.manifest import load_manifest
    from plotmosaic.poses import Poses, ScanPose
    from plotmosaic.stages.register_plot import PlotResult, RegisterResult

    truth = _truth(sim)
    ids = sorted(truth)
    ref = truth[ids[0]]
    nodes = {s: {"plot": "P1", "kind": "tls", "path": str(sim.scan_paths[s])} for s in ids}
    rng = np.random.default_rng(0)
    edges = []
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            T = (
                np.linalg.inv(truth[b])
                @ truth[a]
                @ params_to_matrix(rng.normal(0, [0.002, 0.002, 0.002, 0.002, 0.002, 0.001]))
            )
            if (a, b) == ("P1-S1", "P1-S3"):
                T = T @ params_to_matrix(
                    [0, 0, 2.0, 0.4, 0.0, 0.0]
                )  # a wrong pair: the loops catch it
            edges.append(
                {
                    "source": a,
                    "target": b,
                    "transform": T,
                    "fitness": 0.8,
                    "inlier_rmse": 0.01,
                    "overlap": 0.5,
                    "information": np.eye(6) * 1e4,
                    "confidence": 0.9,
                    "status": "ok",
                    "seconds": 1.5,
                }
            )
    G = build_graph(nodes, edges)
    sol = optimise(G, ids[0])
    poses = Poses(
        {n: ScanPose(np.linalg.inv(ref) @ ref @ T, "P1") for n, T in sol.poses.items()},
        frame="plot",
    )
    result = RegisterResult(
        out, poses, G, [PlotResult("P1", ids[0], sol, ids)], len(edges), len(edges), [], 12.0
    )
    return result, load_manifest(sim.manifest_path), RegisterConfig()


def test_report_html_is_self_contained(small_sim, tmp_path):
    from plotmosaic.report.runs import write_register_report

    result, manifest, config = _registered_folder(small_sim, tmp_path)
    md = write_register_report(result, manifest, config, seed=0)
    page_path = tmp_path / "report.html"
    assert md.is_file() and page_path.is_file()
    page = _Page()
    page.feed(page_path.read_text())
    text = " ".join(page.text)

    expected = [
        "breast-height slice",
        "map of scans and edges",
        "cloud-to-cloud distances per kept edge",
        "median distance to its neighbours",
        "placed scans from above",
    ]
    for what in expected:
        assert any(what in c for c in page.captions), (what, page.captions)
    assert len(page.images) == len(page.captions) >= len(expected)
    for img in page.images:  # every picture inside the page, a real PNG
        src = img["src"]
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    # tables: time, distances, per scan, poses, edges (the stems' when the slice holds stems)
    assert page.tables >= 5
    for title in (
        "How long each stage took",
        "cloud-to-cloud distances of the kept edges",
        "per scan after the joint solve",
        "Plot P1: poses",
        "Plot P1: edges",
    ):
        assert title in text, title
    # summary first, in plain words, with the dropped pair named
    assert text.index("Summary") < text.index("Tables") < text.index("How long each stage took")
    assert "scans placed: 5 of 5" in text
    assert "edge P1-S1-P1-S3 dropped" in text and "cm /" in text
    assert "bundle error" in text and "worst edge" in text
    # report.md stays, with its pictures beside it
    md_text = md.read_text()
    assert "report.html" in md_text and "| P1-S0 |" in md_text
    assert (tmp_path / "P1_breast_slice.png").is_file()
    # the 3D view, when plotly is there, is a separate file linked from the page
    if any(h and h.endswith("view3d.html") for h in page.links):
        assert (tmp_path / "view3d.html").stat().st_size < 20e6


def _arc(centre, r, a0, a1, n, rng, noise=0.002):
    t = np.linspace(a0, a1, n)
    return np.column_stack([centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)]) + rng.normal(
        0, noise, (n, 2)
    )


def test_ring_spread_reads_the_offset_between_two_half_rings():
    """Two scans see opposite sides of a 20 cm stem; the second one's ring is 3 cm off, or not at all."""
    from plotmosaic.config.report import SliceConfig
    from plotmosaic.report.slice import find_stems

    rng = np.random.default_rng(1)
    for shift in (0.0, 0.03):
        slices = {
            "A": np.column_stack([_arc((5.0, 5.0), 0.2, 0.2, np.pi - 0.2, 80, rng), np.zeros(80)]),
            "B": np.column_stack(
                [_arc((5.0 + shift, 5.0), 0.2, np.pi + 0.2, 2 * np.pi - 0.2, 60, rng), np.zeros(60)]
            ),
        }
        (stem,) = find_stems(slices, SliceConfig())
        assert stem.scans == ["A", "B"]
        assert abs(stem.spread - shift) < 0.004, (shift, stem.spread)
        assert abs(stem.radius - 0.2) < 0.02


def test_warnings_in_plain_words():
    import networkx as nx

    from plotmosaic.config.report import ReportConfig
    from plotmosaic.report.warnings import warnings_for

    G = nx.Graph()
    G.add_edge("S1", "S2", source="S1", target="S2")
    G.add_edge("S2", "S3", source="S2", target="S3")
    G.add_edge("S3", "S1", source="S3", target="S1")
    G.add_edge("S4", "S1", source="S4", target="S1")
    G.add_edge(
        "S2",
        "S5",
        source="S2",
        target="S5",
        dropped=True,
        drop_reason="cycle",
        residual_after={"translation": 0.4, "rotation_deg": 0.3},
    )
    G.add_edge(
        "S4",
        "S3",
        source="S4",
        target="S3",
        confidence=0.1,
        dropped=True,
        drop_reason="unverified",
        residual_after={"translation": 12.0, "rotation_deg": 90.0},
    )
    w = warnings_for(
        G,
        [],
        ["S5"],
        [{"source": "S5", "target": "S3", "error": "too few points"}],
        ReportConfig(),
        set(),
    )
    assert "scan S5 is not placed: no kept pair links it to the reference" in w
    assert any(x.startswith("scan S4 is held by one edge only (S1)") for x in w)
    assert (
        "edge S2-S5 dropped: its loops with the other edges do not close; it is 40 cm / 0.30 deg off the solution"
        in w
    )
    assert any("edge S4-S3 dropped" in x and "12.0 m" in x for x in w)
    assert "pair S5-S3 could not be registered: too few points" in w

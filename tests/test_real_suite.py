"""The real-data suite (benchmarks/bench_real.py): outcomes, tables, resumable seeded draws, and
its cases' truths."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from builders import split_pair, synthetic_plot
from scipy.spatial import cKDTree

from plotmosaic.bench.methods import available
from plotmosaic.bench.protocol import (
    PARAMS,
    is_success,
    params_to_matrix,
    pose_error,
    rotation_angle,
)
from plotmosaic.bench.real_cases import build_case, random_frame
from plotmosaic.bench.real_suite import (
    SUITE_PROTOCOLS,
    append_trials,
    draw,
    key,
    outcome,
    plan,
    read_trials,
)
from plotmosaic.bench.refined_truth import refine_truth
from plotmosaic.bench.suite_tables import accuracy, markdown, reliability, summarise, write_outputs
from plotmosaic.io.frame import apply_transform


def _row(case, proto, method, err, failed=False, confidence=None):
    e = np.asarray(err, dtype=float)
    r = {
        "case": case,
        "protocol": proto,
        "method": method,
        **dict(zip(PARAMS, e)),
        "success": bool(is_success(e)[0]),
        "failed": failed,
        "seconds": 1.0,
        "confidence": confidence,
    }
    return {**r, "outcome": outcome(r)}


def test_real_suite_counts_found_refused_and_wrong_with_exit_0(tmp_path):
    rows = [
        _row("c", "paper", "forestalign", [0.1, 0, 0, 0.01, 0, 0], confidence=0.9),
        _row("c", "paper", "forestalign", [0.3, 0, 0, 0.0, 0.02, 0], confidence=0.95),
        _row("c", "paper", "forestalign", [20, 0, 0, 3, 0, 0], failed=True, confidence=0.2),
        _row("c", "paper", "forestalign", [5, 0, 0, 1, 0, 0], confidence=0.6),
        _row("c", "paper", "icp", [40, 0, 0, 10, 0, 0]),
    ]
    s = {x["method"]: x for x in summarise(rows)}
    fa = s["forestalign"]
    assert (fa["n"], fa["found"], fa["refused"], fa["wrong"]) == (4, 2, 1, 1)
    assert fa["rmse_roll"] == pytest.approx(np.sqrt((0.1**2 + 0.3**2) / 2)) and fa[
        "t_rmse_m"
    ] == pytest.approx(np.sqrt((0.01**2 + 0.02**2) / 2))
    assert fa["wrong_errors"] == [pytest.approx((5.0, 1.0), rel=1e-3)]
    assert (s["icp"]["found"], s["icp"]["wrong"], s["icp"]["rmse_roll"]) == (0, 1, None)
    assert "| c | paper | forestalign | 4 | 2 | 1 | **1** |" in markdown(summarise(rows))
    bins = reliability(rows)
    assert (
        sum(b["n"] for b in bins) == 4
        and bins[9]["found"] == 2
        and bins[6]["wrong_returned"] == 1
        and bins[2]["returned"] == 0
    )
    paths = write_outputs(
        rows, {"cases": {"c": {"note": "a case"}}, "skipped": {}}, tmp_path, "cmd"
    )
    assert paths["figure"].stat().st_size > 10_000 and "a case" in paths["table"].read_text()


def test_refine_truth_recovers_a_small_offset_of_a_real_like_cloud():
    cloud = synthetic_plot(3, size=20.0, trees=12)
    src, tgt = split_pair(cloud)
    true = params_to_matrix([0.4, -0.3, 0.8, 0.15, -0.1, 0.05], tgt.xyz.mean(axis=0))
    moved = apply_transform(np.linalg.inv(true), src.xyz)  # true maps `moved` back onto the target
    T, meta = refine_truth(moved, tgt.xyz, voxel=0.1, distances=(1.0, 0.3, 0.1))
    err = pose_error(T, true, tgt.xyz.mean(axis=0))
    rot, trans = float(rotation_angle(err)[0]), float(np.linalg.norm(err[3:]))
    assert rot < 0.1 and trans < 0.03 and meta["spread_deg"] < 0.1 and len(meta["methods"]) == 3
    G = random_frame(cloud.xyz, np.random.default_rng(0))
    assert (
        np.allclose(G[:3, :3] @ G[:3, :3].T, np.eye(3))
        and np.abs(apply_transform(G, cloud.xyz)).max() < 60
    )


def test_real_cases_treels_pair_has_exact_truth_in_own_frames():
    if not (Path(__file__).resolve().parents[2] / "shared" / "data" / "treels").is_dir():
        pytest.skip("shared/data/treels not present")
    case = build_case("treels-2views", seed=1)
    assert case.meta["distance_m"] >= 6.0 and (case.source_kind, case.target_kind) == ("tls", "tls")
    assert (
        np.abs(case.source.xyz).max() < 40 and np.abs(case.target.xyz).max() < 40
    )  # scanner frames

    d, _ = cKDTree(case.target.xyz).query(apply_transform(case.truth, case.source.xyz))
    assert np.mean(d < 1e-6) > 0.05  # points both views saw land exactly on each other


def test_suite_draws_depend_on_the_trial_only_and_a_run_resumes(tmp_path):
    a = draw("paper", 0, "treels-2views", 7)
    np.testing.assert_array_equal(a, draw("paper", 0, "treels-2views", 7))
    assert np.all(np.abs(a) <= SUITE_PROTOCOLS["paper"].ranges)
    assert not np.allclose(a, draw("paper", 0, "treels-2views", 8))
    assert not np.allclose(a, draw("paper", 0, "mls-2views", 7))
    assert not np.allclose(a, draw("paper", 1, "treels-2views", 7))
    assert np.all(draw("true", 0, "x", 3) == 0)
    methods = ["forestalign", "icp"]
    jobs = plan(["c"], {"paper": 3, "true": 1}, methods, set())
    assert [(j.protocol, j.trial, j.methods) for j in jobs] == [
        ("paper", 0, ("forestalign", "icp")),
        ("paper", 1, ("forestalign", "icp")),
        ("paper", 2, ("forestalign", "icp")),
        ("true", 0, ("forestalign", "icp")),
    ]
    path = tmp_path / "trials.jsonl"
    rows = [
        {
            "case": "c",
            "protocol": "paper",
            "trial": 0,
            "method": m,
            "failed": False,
            "success": True,
        }
        for m in methods
    ] + [
        {
            "case": "c",
            "protocol": "paper",
            "trial": 1,
            "method": "icp",
            "failed": True,
            "success": False,
        }
    ]
    append_trials(path, rows)
    with open(path, "a") as fh:
        fh.write('{"case": "c", "proto')  # a line cut short by a killed run
    back = read_trials(path)
    assert [r["outcome"] for r in back] == ["found", "found", "refused"]
    left = plan(["c"], {"paper": 3}, methods, {key(r) for r in back})
    assert [(j.trial, j.methods) for j in left] == [
        (1, ("forestalign",)),
        (2, ("forestalign", "icp")),
    ]


def test_accuracy_table_gives_rmse_per_angle_of_the_found():
    rows = [
        _row("uas-als", "paper", "forestalign", [0.03, -0.04, 0.02, 0.004, 0, 0]),
        _row("uas-als", "true", "forestalign", [0.01, 0.02, -0.06, 0, 0.003, 0]),
        _row("uas-als", "paper", "forestalign", [9, 0, 0, 2, 0, 0]),
    ]
    line = [x for x in accuracy(rows).splitlines() if x.startswith("| uas-als | forestalign")][0]
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[2] == "2 / 3"
    assert float(cells[3]) == pytest.approx(np.sqrt((0.03**2 + 0.01**2) / 2), abs=1e-4)
    assert float(cells[5]) == pytest.approx(np.sqrt((0.02**2 + 0.06**2) / 2), abs=1e-4)
    assert float(cells[7]) == pytest.approx(1000 * np.sqrt((0.004**2 + 0.003**2) / 2), abs=0.1)


def test_cpd_without_probreg_is_skipped_with_one_line(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "probreg", None)  # import probreg -> ImportError
    why = available("cpd")
    assert why and "probreg" in why and "\n" not in why
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        import bench_real
    finally:
        sys.path.pop(0)
    assert (
        bench_real.main(["--methods", "cpd", "--cases", "treels-2views", "--out", str(tmp_path)])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("cpd: skipped, probreg is not installed") and len(err) == 2

"""`plotmosaic bench`: protocol sampling, error decomposition, overlap crops, the table vs the trials."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest
from builders import UTM, split_pair, synthetic_plot
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from plotmosaic.bench.methods import _rigid_cpd
from plotmosaic.bench.overlap import crop_to_overlap, overlap_fraction
from plotmosaic.bench.pairs import load_truth
from plotmosaic.bench.protocol import (
    PARAMS,
    PROTOCOLS,
    get_protocol,
    is_success,
    params_to_matrix,
    pose_error,
    sample_params,
)
from plotmosaic.bench.run import BenchPair, run_bench
from plotmosaic.cli import app
from plotmosaic.config.bench import BenchConfig, CpdConfig, FpfhConfig, MethodsConfig
from plotmosaic.errors import InputError
from plotmosaic.io.las import PointCloud, write_cloud
from plotmosaic.poses import Poses, ScanPose

# ---------------------------------------------------------------- protocol


def read_trials_csv(path) -> list[dict]:
    """Rows back from trials.csv, typed like `run_bench` made them."""
    rows = []
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            row = dict(r)
            for k in ("overlap_wanted", "overlap"):
                row[k] = float(r[k]) if r[k] != "" else None
            row["trial"] = int(r["trial"])
            for p in PARAMS:
                row[p] = float(r[p])
                row[f"init_{p}"] = float(r[f"init_{p}"])
            row["success"] = r["success"] == "True"
            row["failed"] = r["failed"] == "True"
            row["seconds"] = float(r["seconds"])
            row["confidence"] = (
                float(r["confidence"]) if r.get("confidence") not in (None, "") else None
            )
            rows.append(row)
    return rows


@pytest.mark.parametrize("name", ["paper", "beyond"])
def test_perturbations_lie_in_the_protocol_ranges_and_are_seeded(name):
    proto = PROTOCOLS[name]
    p = sample_params(proto, 2000, seed=7)
    assert p.shape == (2000, 6)
    assert np.all(np.abs(p) <= proto.ranges)
    # all six at once, filling the range (uniform): the extremes come close to the bounds
    assert np.all(np.abs(p).max(axis=0) > 0.95 * proto.ranges)
    assert np.all(np.abs(p.mean(axis=0)) < 0.1 * proto.ranges)
    np.testing.assert_array_equal(p, sample_params(proto, 2000, seed=7))
    assert not np.allclose(p, sample_params(proto, 2000, seed=8))


def test_protocol_ranges_match_the_issue():
    assert PROTOCOLS["paper"].ranges.tolist() == [45, 45, 45, 15, 15, 15]
    assert PROTOCOLS["beyond"].ranges.tolist() == [10, 10, 180, 25, 25, 25]
    assert get_protocol("custom", rotation=5, translation_m=0.5).ranges.tolist() == [
        5,
        5,
        5,
        0.5,
        0.5,
        0.5,
    ]


def test_pose_error_recovers_known_roll_pitch_yaw_and_translation():
    rng = np.random.default_rng(3)
    centre = UTM + rng.normal(0, 10, 3)
    T_true = params_to_matrix(
        [1.0, -2.0, 130.0, 5.0, -7.0, 0.3], UTM
    )  # any truth, far from the origin
    for p in sample_params(PROTOCOLS["paper"], 50, seed=1):
        T_est = params_to_matrix(p, centre) @ T_true
        np.testing.assert_allclose(pose_error(T_est, T_true, centre), p, atol=1e-6)
    # a perfect estimate has zero error; a pure 2 deg yaw about the centre moves nothing there
    np.testing.assert_allclose(pose_error(T_true, T_true, centre), 0, atol=1e-9)
    err = pose_error(params_to_matrix([0, 0, 2.0, 0, 0, 0], centre) @ T_true, T_true, centre)
    np.testing.assert_allclose(err, [0, 0, 2.0, 0, 0, 0], atol=1e-9)


def test_success_needs_both_under_one_degree_and_ten_centimetres():
    e = np.array(
        [
            [0.5, 0.5, 0.5, 0.05, 0.05, 0.0],  # 0.87 deg, 7 cm: success
            [0.0, 0.0, 1.2, 0.0, 0.0, 0.0],  # 1.2 deg
            [0.0, 0.0, 0.0, 0.08, 0.08, 0.0],  # 11 cm
        ]
    )
    assert is_success(e).tolist() == [True, False, False]


# ---------------------------------------------------------------- overlap


def test_crop_to_overlap_reaches_the_paper_levels():
    # two scans of a 60 m strip that share its middle third: ~50 % overlap before cropping
    scene = synthetic_plot(size=60.0, trees=30)
    x = scene.xyz[:, 0] - UTM[0]
    rng = np.random.default_rng(2)
    half = rng.random(len(x)) < 0.5
    src, tgt = scene.select(half & (x > -10)), scene.select(~half & (x < 10))
    assert overlap_fraction(src.xyz, tgt.xyz) > 0.3
    for wanted in (0.28, 0.15, 0.05, 0.01):
        c = crop_to_overlap(src, tgt, wanted)
        measured = overlap_fraction(c.source.xyz, c.target.xyz)  # independent re-measure
        assert measured == pytest.approx(c.overlap, abs=1e-9)
        assert abs(measured - wanted) <= max(0.005, 0.1 * wanted), (wanted, measured)
        assert len(c.target) == len(tgt) and len(c.source) >= 1000
        # whole columns go, not scattered points: what is kept of a column is all of it
        kept = {tuple(k) for k in np.floor(c.source.xyz[:, :2] / 4.0).astype(int)}
        in_kept = np.array([tuple(k) in kept for k in np.floor(src.xyz[:, :2] / 4.0).astype(int)])
        assert in_kept.sum() == len(c.source)


# ---------------------------------------------------------------- a whole bench


def _bench_inputs(request, tmp_path):
    """(args before options, description): the small simulator preset when it exists, else a synthetic pair."""
    try:
        sim = request.getfixturevalue("small_sim")
    except pytest.FixtureLookupError:
        sim = None
    if sim is not None:
        return [
            "--manifest",
            str(sim.manifest_path),
            "--gt",
            str(sim.ground_truth_path),
            "--pairs",
            "tls-tls",
            "--max-pairs",
            "1",
        ]
    src, tgt = split_pair(synthetic_plot())
    write_cloud(tmp_path / "src.laz", src)
    write_cloud(tmp_path / "tgt.laz", tgt)
    return [str(tmp_path / "src.laz"), str(tmp_path / "tgt.laz"), "--gt", "identity"]


def _table_rows(text: str) -> dict[str, list[str]]:
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) >= 10 and cells[0] not in ("method", "") and not set(cells[0]) <= {"-"}:
            rows[cells[0]] = cells
    return rows


def test_bench_two_trials_table_matches_the_trials(request, tmp_path):
    out = tmp_path / "out"
    args = [
        "bench",
        *_bench_inputs(request, tmp_path),
        "--trials",
        "2",
        "--protocol",
        "custom",
        "--max-rotation",
        "3",
        "--max-translation",
        "0.5",
        "--methods",
        "icp",
        "--out",
        str(out),
        "--seed",
        "5",
    ]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    rows = read_trials_csv(out / "trials.csv")
    table = _table_rows((out / "table.md").read_text())
    methods = sorted({r["method"] for r in rows})
    assert "icp" in methods
    for method in methods:
        sub = [r for r in rows if r["method"] == method]
        assert len(sub) == 2
        errors = np.array([[r[p] for p in PARAMS] for r in sub])
        rmse = np.sqrt(np.mean(errors**2, axis=0))
        cells = table[method]
        # columns: method, n, 6 RMSEs, success, failed, s/trial; printed to 3 significant digits
        assert int(cells[1]) == 2
        np.testing.assert_allclose([float(c) for c in cells[2:8]], rmse, rtol=0.01, atol=6e-4)
        assert cells[8] == f"{100 * np.mean([r['success'] for r in sub]):.0f}%"
        # each row's success is the 1 deg / 10 cm test on its own errors
        assert [r["success"] for r in sub] == is_success(errors).tolist()
        assert int(cells[9]) == sum(r["failed"] for r in sub)
    # the initial row is the RMSE of the perturbations, identical for every method
    init = np.array([[r[f"init_{p}"] for p in PARAMS] for r in rows if r["method"] == "icp"])
    np.testing.assert_allclose(
        [float(c) for c in table["initial"][2:8]],
        np.sqrt(np.mean(init**2, axis=0)),
        rtol=0.01,
        atol=6e-4,
    )
    assert np.all(np.abs(init[:, :3]) <= 3) and np.all(np.abs(init[:, 3:]) <= 0.5)
    # ICP from a small perturbation registers every trial
    icp = [r for r in rows if r["method"] == "icp"]
    assert all(r["success"] for r in icp), icp
    summary = json.loads((out / "summary.json").read_text())
    assert summary["trials"] == 2 and summary["protocol"]["name"] == "custom"
    assert (out / "errors.png").stat().st_size > 10_000
    assert re.search(r"\| icp \| 2 \|", result.output)


def test_bench_is_deterministic_for_a_seed():
    src, tgt = split_pair(synthetic_plot(trees=10))
    config = BenchConfig(
        trials=1,
        seed=3,
        methods=["fpfh-ransac"],
        methods_config=MethodsConfig(
            fpfh=FpfhConfig(voxel=0.5, max_points=3000, ransac_iterations=5000)
        ),
    )
    runs = [
        run_bench([BenchPair("p", src, tgt, np.eye(4))], config, progress=False).rows
        for _ in range(2)
    ]
    for a, b in zip(*runs):
        assert [a[p] for p in PARAMS] == [b[p] for p in PARAMS]
        assert [a[f"init_{p}"] for p in PARAMS] == [b[f"init_{p}"] for p in PARAMS]


def test_bench_rejects_bad_options_with_one_line(tmp_path):
    src, tgt = split_pair(synthetic_plot(trees=2))
    write_cloud(tmp_path / "s.laz", src)
    for extra, needle in (
        (["--methods", "icp,magic"], "unknown method 'magic'"),
        (["--protocol", "wild"], "unknown protocol"),
        (["--overlap", "28,abc"], "--overlap"),
    ):
        result = CliRunner().invoke(
            app,
            [
                "bench",
                str(tmp_path / "s.laz"),
                str(tmp_path / "s.laz"),
                "--gt",
                "identity",
                *extra,
                "--out",
                str(tmp_path / "o"),
            ],
        )
        assert result.exit_code == 2, result.output
        assert needle in result.output and "Traceback" not in result.output
    result = CliRunner().invoke(
        app,
        [
            "bench",
            str(tmp_path / "s.laz"),
            str(tmp_path / "s.laz"),
            "--gt",
            str(tmp_path / "missing.json"),
        ],
    )
    assert result.exit_code == 2 and "missing.json" in result.output


def test_ground_truth_from_poses_transform_json_or_identity(tmp_path):
    Ta, Tb = params_to_matrix([1, 2, 30, *UTM]), params_to_matrix([-1, 0, -60, *(UTM + 15)])
    Poses({"S1": ScanPose(Ta), "S0": ScanPose(Tb)}, frame="crs").save(tmp_path / "gt.json")
    gt, a, b, als = (
        str(tmp_path / "gt.json"),
        tmp_path / "S1.laz",
        tmp_path / "S0.laz",
        tmp_path / "als.laz",
    )
    np.testing.assert_allclose(
        load_truth(gt, a, b), np.linalg.inv(Tb) @ Ta
    )  # ids from the file stems
    np.testing.assert_allclose(
        load_truth(gt, tmp_path / "x.laz", b, source_id="S1"), np.linalg.inv(Tb) @ Ta
    )
    np.testing.assert_allclose(
        load_truth(gt, a, als), Ta
    )  # no pose for the ALS tile: it is the CRS frame
    (tmp_path / "t.json").write_text(json.dumps({"transform": Ta.tolist()}))
    np.testing.assert_allclose(load_truth(str(tmp_path / "t.json"), a, b), Ta)
    np.testing.assert_array_equal(load_truth("identity", a, b), np.eye(4))
    with pytest.raises(InputError, match="no pose for 'S7'"):
        load_truth(gt, tmp_path / "S7.laz", b)


def test_bench_draws_forestalign_failures(tmp_path):
    """A trial forestalign gets wrong comes with a picture of where it put the source (and no picture for baselines)."""

    src, tgt = split_pair(synthetic_plot(trees=6))
    far = PointCloud(
        tgt.xyz + [400.0, 0.0, 0.0], crs=tgt.crs
    )  # the truth says they overlap; they cannot
    config = BenchConfig(trials=1, methods=["forestalign", "icp"])
    rows = run_bench(
        [BenchPair("far", src, far, np.eye(4))], config, progress=False, failures=tmp_path / "f"
    ).rows
    fa = next(r for r in rows if r["method"] == "forestalign")
    icp = next(r for r in rows if r["method"] == "icp")
    assert not fa["success"] and fa["picture"] and not icp["picture"]
    assert (tmp_path / "f" / fa["picture"]).stat().st_size > 10_000


# ---------------------------------------------------------------- baselines


def test_rigid_cpd_fixed_scale_converges_to_the_pose():
    pytest.importorskip("probreg")

    rng = np.random.default_rng(0)
    x = rng.uniform(-15, 15, (600, 3)) * [1, 1, 0.5]
    R = Rotation.from_euler("zyx", [8, 2, -3], degrees=True).as_matrix()
    y = (x - [0.8, -0.4, 0.1]) @ R  # y -> x: x = R y + t
    T = _rigid_cpd(y, x, CpdConfig(maxiter=100))
    # probreg's own fixed-scale M-step keeps sigma^2 at the clouds' spread and stops degrees off
    assert np.degrees(Rotation.from_matrix(T[:3, :3] @ R.T).magnitude()) < 0.01
    np.testing.assert_allclose(T[:3, 3], [0.8, -0.4, 0.1], atol=1e-3)

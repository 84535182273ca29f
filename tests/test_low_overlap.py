"""Pairs that barely overlap (issue 54): the fine stage samples where the clouds meet, and a refused
pose gets a second look from the candidates the judge did not weigh."""

import json

import numpy as np
import pytest
from helpers import invoke

from plotmosaic.align.fine import final_icp
from plotmosaic.align.memo import PairMemo
from plotmosaic.align.pipeline import AlignRequest, align_clouds, prepare_pair
from plotmosaic.bench.overlap_pairs import PairRef, candidate, cut_candidate, save_pair
from plotmosaic.bench.overlap_suite import Job, run_trial
from plotmosaic.config.align import AlignConfig
from plotmosaic.io.cloud import PointCloud
from plotmosaic.io.frame import inverse, pose_error, to_global_transform, to_local_transform
from plotmosaic.io.las import read_cloud


def _pair(sim, source: str, target: str):
    truth = json.loads((sim.outdir / "ground_truth.json").read_text())["scans"]
    T = {k: np.asarray(v["transform"], dtype=float) for k, v in truth.items()}
    cfg = AlignConfig()
    src, tgt = prepare_pair(
        read_cloud(sim.scan_paths[source], attributes=False),
        read_cloud(sim.scan_paths[target], attributes=False),
        ("tls", "tls"),
        (3, 3),
        cfg,
    )
    return src, tgt, inverse(T[target]) @ T[source], cfg


def test_a_thin_pair_is_refined_again_on_samples_of_its_overlap(small_sim):
    """P1-S1 -> P1-S0 of the paper layout: a fifth of the source's fine sample near the target."""
    src, tgt, true, cfg = _pair(small_sim, "P1-S1", "P1-S0")
    start = to_local_transform(true, src.frame, tgt.frame)
    plain = final_icp(src, tgt, start, cfg.model_copy(update={"lens_max_share": 0.0}), PairMemo())
    lens = final_icp(src, tgt, start, cfg, PairMemo())
    assert len(lens.p) > len(plain.p)  # more of the shared part holds the pose
    deg, m = pose_error(to_global_transform(lens.T, src.frame, tgt.frame), true)
    assert m < 0.01 and deg < 0.03, (m, deg)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 7])
def test_mls_views_twelve_metres_apart_are_found(spanner_dir, tmp_path, seed):
    """Two views of the real MLS clip 12 m apart with 10 m range. Seed 0 was once refused (the
    truth was among the slice starts the judge did not weigh), now found by the second look;
    seed 7 was refused while the screening ICP tilted its right slice starts 9-12 deg away,
    now found as they turn about their vertical."""
    sim = tmp_path / "views"
    cut = invoke(
        "simulate", sim, "--from-cloud", spanner_dir / "MLS_Clip.laz", "--views", "2",
        "--spacing", "12", "--max-range", "10", "--seed", str(seed),
    )  # fmt: skip
    assert cut.exit_code == 0, cut.output
    res = invoke(
        "align", sim / "P1" / "P1-S1.laz", sim / "P1" / "P1-S0.laz", "--out", tmp_path / "r.json"
    )
    assert res.exit_code == 0, res.output
    truth = json.loads((sim / "ground_truth.json").read_text())["scans"]
    T = {k: np.asarray(v["transform"], dtype=float) for k, v in truth.items()}
    got = np.asarray(json.loads((tmp_path / "r.json").read_text())["transform"])
    deg, m = pose_error(got, inverse(T["P1-S0"]) @ T["P1-S1"])
    assert m < 0.05 and deg < 0.2, (m, deg)


@pytest.mark.slow
def test_a_thin_real_pair_whose_truth_scores_below_the_stored_floor_is_found(spanner_dir):
    """A pair cut from the MLS clip sharing 0.11 / 0.18 (bench_overlap's mls candidate 21): its
    truth scores under 0.12 (a share of all points: thin pairs score little) but fits sharply; the
    searched pose's floor lets it stand, and the truth, a low-ranked slice start, is reached by the
    second look."""
    pair = cut_candidate(candidate("mls", 0, 21), spanner_dir.parent)[0]
    assert 0.10 < pair.overlap_st < 0.12 and 0.15 < pair.overlap_ts < 0.20
    request = AlignRequest(source_kind="tls", target_kind="tls")
    result = align_clouds(PointCloud(pair.source), PointCloud(pair.target), request)
    deg, m = pose_error(result.transform, pair.truth)
    assert m < 0.05 and deg < 0.2, (m, deg)
    assert result.judge["score"] < AlignConfig().judge.stored_min_score


@pytest.mark.slow
def test_a_second_look_does_not_let_a_chance_pose_through(spanner_dir, tmp_path):
    """TreeLS views sharing 0.10 / 0.08 (bench_overlap's treels candidate 30), paper draw 7: among
    40 looks one ended 3 deg / 6 m off at confidence 0.30 and passed the first pose's floors; a
    look's pose must be clear (second_look_min_confidence), so the pair is refused."""
    data = spanner_dir.parent
    if not (data / "treels").is_dir():
        pytest.skip("shared/data/treels not present")
    pair = cut_candidate(candidate("treels", 0, 30), data)[0]
    path = save_pair(tmp_path / "pair.npz", pair)
    ref = PairRef("treels-c30-p0", str(path), pair.overlap_st, pair.overlap_ts, 0.0, 0.0, 0.0)
    row = run_trial(Job("treels", (0.05, 0.10), 7, ref, ("forestalign",), 0))[0]
    assert row["outcome"] != "wrong", row

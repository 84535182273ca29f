"""The pose judge: every pairwise path (coarse, --init, --no-coarse) returns the right pose or exits 3."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import SIM_PAIR_MAX_DEG, SIM_PAIR_MAX_M
from typer.testing import CliRunner

from plotmosaic.align import judge
from plotmosaic.align.fine import FineResult
from plotmosaic.align.floors import blunt_fit
from plotmosaic.align.judge import rivals
from plotmosaic.align.judge.profile import Profile
from plotmosaic.align.memo import PairMemo
from plotmosaic.align.pair import PairContext, recover, register_prepared
from plotmosaic.align.pipeline import prepare_pair
from plotmosaic.align.prepare import prepare_cloud
from plotmosaic.align.result import PairResult
from plotmosaic.align.spacing import scale_factor
from plotmosaic.cli import app
from plotmosaic.config.align import AlignConfig
from plotmosaic.errors import RegistrationFailed
from plotmosaic.io.frame import rotation_deg, to_local_transform
from plotmosaic.io.las import PointCloud, read_cloud
from plotmosaic.poses import load_poses

runner = CliRunner()


def local(cfg: AlignConfig) -> AlignConfig:
    """The same settings with the coarse stage off (--no-coarse)."""
    out = cfg.model_copy(deep=True)
    out.coarse.enabled = False
    return out


def error(T, T_true, centre) -> tuple[float, float]:
    """(deg, m at the source point `centre`) between a result and the truth."""
    D = np.linalg.inv(T_true) @ T
    return rotation_deg(D), float(np.linalg.norm(D[:3, :3] @ centre + D[:3, 3] - centre))


def outcome(src, tgt, cfg, init, memo=None):
    """(result, accepted) of one registration; a refusal must carry its figures."""
    try:
        return register_prepared(src, tgt, cfg, init, seed=0, memo=memo), True
    except RegistrationFailed as exc:
        assert exc.result is not None and exc.result.judge is not None
        return exc.result, False


@pytest.fixture(scope="module")
def pair(small_sim):
    truth = load_poses(small_sim.ground_truth_path)
    T_true = np.linalg.inv(truth.transform("P1-S0")) @ truth.transform("P1-S1")
    s = read_cloud(small_sim.scan_paths["P1-S1"], attributes=False)
    t = read_cloud(small_sim.scan_paths["P1-S0"], attributes=False)
    cfg = AlignConfig()
    ps, pt = prepare_pair(s, t, ("tls", "tls"), (3, 3), cfg, 0)
    return ps, pt, T_true, s.xyz.mean(axis=0), cfg


@pytest.fixture(scope="module")
def pair_memo(pair):
    """The pair's memo, kept across its registrations as a run keeps it (one global search)."""
    return PairMemo()


def test_profile_separates_truth_from_a_distinct_pose(pair):
    ps, pt, T_true, _, cfg = pair
    T = to_local_transform(T_true, ps.frame, pt.frame)
    off = T.copy()
    off[:3, 3] += [2.0, -1.0, 0.0]
    right, wrong = judge.profile(ps, pt, T, cfg.judge), judge.profile(ps, pt, off, cfg.judge)
    assert len(right.scales) == len(cfg.judge.scales) and right.scales == sorted(right.scales)
    assert right.score > 1.5 * wrong.score, (right, wrong)
    assert right.structure_st[0] > 2 * wrong.structure_st[0]
    # a sparse cloud is judged at its own resolution: scales grow, never shrink
    assert scale_factor(ps, pt, cfg.judge) >= 1.0


@pytest.mark.slow
def test_sharpness_floor_refuses_a_blunt_fit(pair, pair_memo):
    """A pose the ICP settles at by chance fits bluntly: below min_sharpness, refused with the figure
    (the floors are the same on every path: checked on the local one, from the true pose)."""
    ps, pt, T_true, _, cfg = pair
    cfg = local(cfg)
    T = to_local_transform(T_true, ps.frame, pt.frame)
    off = T.copy()
    off[:3, 3] += [2.0, -1.0, 0.0]
    memo = pair_memo
    right = judge.sharpness(judge.profile(ps, pt, T, cfg.judge, memo))
    wrong = judge.sharpness(judge.profile(ps, pt, off, cfg.judge, memo))
    assert wrong < cfg.judge.min_sharpness < right, (wrong, right)
    res = register_prepared(ps, pt, cfg, T_true, seed=0, memo=memo)  # accepted: a sharp fit
    assert res.judge["sharpness"] >= cfg.judge.min_sharpness
    above = min(1.0, res.judge["sharpness"] + 0.01)
    strict = cfg.model_copy(deep=True)
    strict.judge.min_sharpness = strict.judge.blunt_min_sharpness = above
    with pytest.raises(RegistrationFailed, match="only by chance"):
        register_prepared(ps, pt, strict, T_true, seed=0, memo=memo)
    # between the two floors (a noisy sensor's right pose): accepted only as a clear winner
    zone = cfg.model_copy(deep=True)
    zone.judge.min_sharpness, zone.judge.blunt_min_sharpness = above, above - 0.02
    zone.judge.blunt_min_confidence = res.confidence
    assert register_prepared(ps, pt, zone, T_true, seed=0, memo=memo).confidence == res.confidence
    jc = zone.judge
    assert "must beat every distinct rival" in blunt_fit(
        above - 0.01, jc.blunt_min_confidence - 0.01, jc
    )
    assert "only by chance" in blunt_fit(above - 0.03, 1.0, jc)
    assert blunt_fit(None, None, jc) is None  # results cached before sharpness


@pytest.mark.slow
def test_right_pair_accepted_with_high_confidence(pair, pair_memo):
    ps, pt, T_true, centre, cfg = pair
    result = register_prepared(ps, pt, cfg, None, seed=0, memo=pair_memo)
    deg, m = error(result.transform, T_true, centre)
    assert deg < SIM_PAIR_MAX_DEG and m < SIM_PAIR_MAX_M, (deg, m)
    assert result.confidence > 0.6 and result.judge["fine_margin"] > cfg.judge.chance_margin
    assert result.judge["distinct_rivals"] >= 1
    # the score rival is the best distinct rival sharp enough to be accepted itself, if any
    sharp = [
        r for r in result.judge["rivals"]
        if r["distinct"] and "score" in r and r["sharpness"] >= cfg.judge.blunt_min_sharpness
    ]  # fmt: skip
    if sharp:
        assert result.judge["rival_score"] == max(r["score"] for r in sharp)
    else:
        assert result.judge["rival_score"] == 0.0 and result.judge["rival_profile"] is None
    # the figures round-trip, and results cached before the judge still load
    again = PairResult.from_dict(json.loads(json.dumps(result.to_dict())))
    assert again.judge["score"] == result.judge["score"] and again.confidence == result.confidence
    old = {k: v for k, v in result.to_dict().items() if k != "judge"}
    assert PairResult.from_dict(old).judge is None


@pytest.mark.slow
def test_local_start_far_off_is_refused_never_wrong(pair, pair_memo):
    """--no-coarse from a start that leaves ICP in a wrong minimum: exit 3 with the rival named, or right."""
    ps, pt, T_true, centre, cfg = pair
    cfg = local(cfg)
    bad = T_true.copy()
    c, s = np.cos(np.radians(60)), np.sin(np.radians(60))
    bad[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ bad[:3, :3]
    for init in (None, bad):
        try:
            result = register_prepared(ps, pt, cfg, init, seed=0, memo=pair_memo)
        except RegistrationFailed as exc:
            assert "distinct pose fits" in str(exc) and "rerun without --no-coarse" in str(exc), (
                str(exc)
            )
            assert exc.result.judge["rival_score"] >= exc.result.judge["score"]
            continue
        deg, m = error(result.transform, T_true, centre)
        assert deg < 0.1 and m < 0.02, (deg, m)


@pytest.mark.slow
def test_true_pose_control_right_or_refused_on_every_path(pair, pair_memo):
    """The source handed over in its true pose: back within 1 deg / 10 cm or refused, with and without the coarse stage."""
    ps, pt, T_true, centre, cfg = pair
    for c in (local(cfg), cfg):
        result, accepted = outcome(ps, pt, c, T_true, pair_memo)
        if accepted:
            deg, m = error(result.transform, T_true, centre)
            assert deg < 1.0 and m < 0.1, (deg, m)
    assert accepted  # this pair is easy: the coarse path keeps the truth


@pytest.mark.slow
def test_unrelated_forests_refused_on_every_path(small_sim, pair):
    """A scan against the mirror image of its neighbour (no rigid transform relates them): exit 3 on every path."""
    ps, _, _, _, cfg = pair
    t = read_cloud(small_sim.scan_paths["P1-S0"], attributes=False)
    mirrored = prepare_cloud(PointCloud(t.xyz * [-1.0, 1.0, 1.0]), "tls", 3, cfg, 1, "target")
    memo = PairMemo()  # one global search for the three paths
    for c, init in ((cfg, None), (local(cfg), None), (cfg, np.eye(4))):
        result, accepted = outcome(ps, mirrored, c, init, memo)
        assert not accepted, (
            c.coarse.enabled,
            init is None,
            result.judge["score"],
            result.judge["rival_score"],
        )


@pytest.mark.slow
def test_cli_no_coarse_exits_3_or_right(small_sim, tmp_path):
    """The issue's reproduction (`align P1-S1 P1-S0 --no-coarse`): never a wrong pose with exit 0."""
    out = tmp_path / "r.json"
    res = runner.invoke(
        app,
        [
            "align",
            str(small_sim.scan_paths["P1-S1"]),
            str(small_sim.scan_paths["P1-S0"]),
            "--no-coarse",
            "--out",
            str(out),
        ],
    )
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    if res.exit_code == 3:
        lines = [line for line in res.output.splitlines() if line.strip()]
        assert len(lines) == 1 and "distinct pose fits" in lines[0] and "--no-coarse" in lines[0], (
            res.output
        )
        assert not out.exists()
        return
    assert res.exit_code == 0, res.output
    truth = load_poses(small_sim.ground_truth_path)
    T_true = np.linalg.inv(truth.transform("P1-S0")) @ truth.transform("P1-S1")
    centre = read_cloud(small_sim.scan_paths["P1-S1"], attributes=False).xyz.mean(axis=0)
    deg, m = error(np.asarray(json.loads(out.read_text())["transform"]), T_true, centre)
    assert deg < 0.1 and m < 0.02, (deg, m)


def _profile(fine: float, wide: float) -> Profile:
    """A residual profile with share `fine` at the smallest scale and `wide` at the others."""
    shares = [fine, wide, wide, wide]
    mean = float(np.mean(shares))
    return Profile(
        scales=[0.02, 0.05, 0.1, 0.25],
        structure_st=shares,
        structure_ts=shares,
        all_st=shares,
        all_ts=shares,
        score=mean,
        score_all=mean,
    )


def test_fine_margin_accepts_a_clear_winner_refuses_a_close_rival():
    """The confidence follows the finest scale: 6x the rival's share there is sure even when the wide
    scales rank the rival level; 1.2x is not, and a rival sharper than the pose gives 0."""
    jc, floor = AlignConfig().judge, AlignConfig().min_confidence
    pose = _profile(0.09, 0.40)
    assert judge.confidence(pose, [_profile(0.015, 0.41)], jc) >= floor
    assert judge.confidence(pose, [_profile(0.075, 0.30)], jc) < floor
    assert judge.confidence(pose, [_profile(0.10, 0.30)], jc) == 0.0
    # every rival counts, not only the best by score: the sharp one decides
    assert judge.confidence(pose, [_profile(0.01, 0.45), _profile(0.08, 0.2)], jc) < floor
    assert judge.confidence(pose, [], jc) == 1.0  # nothing distinct to compare with


def _turned(T: np.ndarray, centre: np.ndarray, deg: float, shift) -> np.ndarray:
    """T turned by `deg` about the vertical through where T puts `centre`, then shifted."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    P = np.eye(4)
    P[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    p = T[:3, :3] @ centre + T[:3, 3]
    P[:3, 3] = p - P[:3, :3] @ p + np.asarray(shift, dtype=float)
    return P @ T


def test_near_miss_refused_by_its_own_basin_when_the_truth_is_withheld(pair):
    """A pose 2.5 deg / 0.3 m off is inside the distinct radius of the truth, so with the truth missing
    from the candidates nothing distinct is sharper (confidence 1 without the basin check); its basin
    starts reach the truth, a sharper pose beside it: confidence 0. The truth keeps its confidence."""
    ps, pt, T_true, _, cfg = pair
    jc = cfg.judge
    T = to_local_transform(T_true, ps.frame, pt.frame)
    near = _turned(T, judge.centre(ps, jc), 2.5, [0.2, -0.2, 0.0])
    assert not judge.distinct(near, T, judge.centre(ps, jc), jc)
    off = jc.model_copy(update={"basin_neighbours": 0})
    assert judge.judge(ps, pt, near, [], off).confidence == 1.0  # the risk the basin closes
    v = judge.judge(ps, pt, near, [], jc)
    assert v.confidence == 0.0 and v.fine_rival_source.startswith("the pose's own basin"), v
    assert v.basin_share > (1 + jc.basin_tolerance) * v.fine_share
    deg, m = judge.separation(v.basin_transform, T, judge.centre(ps, jc))
    assert deg < 1.0 and m < 0.10, (deg, m)  # the sharper pose is the truth (its basin)
    right = judge.judge(ps, pt, T, [], jc)
    assert right.confidence == 1.0 and right.basin_transform is None
    assert right.basin_share <= (1 + jc.basin_tolerance) * right.fine_share


@pytest.fixture(scope="module")
def boxed(spanner_dir):
    """bench_real.py's mls-boxed6m: a ground view cut to 6 m range against a view 8 m away (real MLS)."""
    from plotmosaic.bench.real_cases import build_case
    from plotmosaic.config.align import default_levels

    case = build_case("mls-boxed6m", spanner_dir.parent)
    cfg = AlignConfig()
    ps, pt = prepare_pair(
        case.source, case.target, ("tls", "tls"), (default_levels("tls"),) * 2, cfg
    )
    return ps, pt, case, cfg


def test_boxed_view_truth_accepted_by_its_fine_margin(boxed):
    """The true-pose control of the boxed view: the wide scales rank the global search's wrong poses
    close (score margin far below what the old score-margin confidence needed), the 5 cm scale does
    not, and the closest is too blunt to outscore the truth; the truth comes back, accepted."""
    ps, pt, case, cfg = boxed
    result, accepted = outcome(ps, pt, cfg, case.truth)
    j = result.judge
    assert j["distinct_rivals"] >= 1
    close = max((r for r in j["rivals"] if "score" in r), key=lambda r: r["score"])
    margin = 1.0 - close["score"] / j["score"]
    assert margin < 0.25 * 0.5, margin  # old rule: confidence = margin / 0.5 < 0.25
    # the closest on score fits only by chance: too blunt to outscore the pose
    assert close["sharpness"] < cfg.judge.blunt_min_sharpness <= j["sharpness"], close
    assert j["rival_score"] < close["score"] and j["margin"] > margin
    assert j["fine_margin"] > 0.6, (j["fine_margin"], j["fine_share"], j["fine_rival_share"])
    assert accepted, (result.confidence, j["score"], j["rival_score"], j["sharpness"])
    deg, m = error(result.transform, case.truth, case.source.xyz.mean(axis=0))
    assert deg < 0.1 and m < 0.01, (deg, m)


def test_boxed_view_refused_when_a_copy_fits_as_well(boxed):
    """The same forest twice in the target, 60 m apart: the pose on the copy is a distinct rival as
    sharp as the truth, so the truth is refused (confidence 0), whichever of the two is judged."""
    ps, _, case, cfg = boxed
    from plotmosaic.config.align import default_levels

    shift = np.eye(4)
    shift[0, 3] = 60.0
    xyz = case.target.xyz
    twice = PointCloud(np.vstack([xyz, xyz + shift[:3, 3]]))
    pt2 = prepare_cloud(twice, "tls", default_levels("tls"), cfg, 1, "target")
    T = to_local_transform(case.truth, ps.frame, pt2.frame)
    copy = to_local_transform(shift @ case.truth, ps.frame, pt2.frame)
    for pose, rival in ((T, copy), (copy, T)):
        v = judge.judge(ps, pt2, pose, [judge.Candidate(T=rival, source="copy")], cfg.judge)
        assert v.distinct_rivals == 1 and abs(v.fine_margin) < 0.3, v.fine_margin
        assert v.confidence < cfg.min_confidence, v.confidence


def test_retry_takes_the_sharper_basin_pose_and_never_a_wrong_one(pair):
    """pair.recover: a near miss (2.5 deg / 0.3 m off, truth withheld) is refused by its basin;
    the one retry from the basin's sharper pose lands on the truth with a higher confidence and is
    kept. A wrong pose offered as the better one (40 deg / 3 m off) is finished and judged too, loses
    to the first pose, and the first pose and its verdict stand."""
    import dataclasses

    ps, pt, T_true, _, cfg = pair
    jc, c = cfg.judge, judge.centre(ps, cfg.judge)
    T = to_local_transform(T_true, ps.frame, pt.frame)
    near = _turned(T, c, 2.5, [0.2, -0.2, 0.0])
    memo = PairMemo()  # the verdict and its retry share the refined rivals, as in the pair
    v = judge.judge(ps, pt, near, [], jc, memo)
    assert v.basin_transform is not None and v.confidence < cfg.min_confidence
    none = np.zeros((0, 3))
    empty = {"p": none, "q": none, "n": none, "iterations": 0, "reverse": False}
    first = PairContext(src=ps, tgt=pt, config=cfg, seed=0, say=lambda msg: None, memo=memo)
    judged = recover(first, [], FineResult(T=near, **empty), v)
    T2, v2 = judged.fine.T, judged.verdict
    deg, m = judge.separation(T2, T, c)
    assert deg < SIM_PAIR_MAX_DEG and m < SIM_PAIR_MAX_M, (deg, m)  # recovered: the truth
    assert v2.confidence >= cfg.min_confidence and v2.confidence > v.confidence, v2
    right = judge.judge(ps, pt, T, [], jc)
    wrong = _turned(T, c, 40.0, [3.0, 0.0, 0.0])
    offered = dataclasses.replace(right, basin_transform=wrong)
    fresh = dataclasses.replace(first, memo=PairMemo())
    judged = recover(fresh, [], FineResult(T=T, **empty), offered)
    T3, v3 = judged.fine.T, judged.verdict
    assert np.array_equal(T3, T) and v3 is offered  # the wrong pose is not taken


def test_near_rival_still_sliding_into_the_pose_is_the_pose(pair, monkeypatch):
    """A rival start 5.5 deg / 0.3 m off the truth, refined by a schedule too short to settle, stops
    outside the distinct radius: without more passes it stays a rival of the pose; with them it
    slides into the pose and is no rival. A far rival is refined once, as before."""
    ps, pt, T_true, _, cfg = pair
    c = judge.centre(ps, cfg.judge)
    T = to_local_transform(T_true, ps.frame, pt.frame)
    start = _turned(T, c, 5.5, [0.3, 0.0, 0.0])
    far = _turned(T, c, 40.0, [3.0, 0.0, 0.0])
    short = cfg.judge.model_copy(update={"rival_schedule": [(0.25, 2)], "basin_neighbours": 0})
    once = judge.judge(
        ps,
        pt,
        T,
        [judge.Candidate(T=start, source="near"), judge.Candidate(T=far, source="far")],
        short.model_copy(update={"near_rival_passes": 0}),
    )
    stopped = next(r for r in once.rivals if r["from"] == "near")
    assert stopped["distinct"] and stopped["deg"] <= 2 * short.distinct_deg, stopped
    calls = []
    refine = rivals.refine

    def counted(src, tgt, A, config, into=None, memo=None):
        calls.append(judge.separation(np.asarray(A), T, c)[0])
        return refine(src, tgt, A, config, into, memo)

    monkeypatch.setattr(rivals, "refine", counted)
    more = judge.judge(
        ps,
        pt,
        T,
        [judge.Candidate(T=start, source="near"), judge.Candidate(T=far, source="far")],
        short.model_copy(update={"near_rival_passes": 8}),
    )
    assert not next(r for r in more.rivals if r["from"] == "near")["distinct"]
    assert more.distinct_rivals == 1 and sum(deg > 2 * short.distinct_deg for deg in calls) == 1
    assert more.confidence >= once.confidence


def _pose(deg: float, shift: tuple[float, float, float]) -> np.ndarray:
    """A turn about the vertical by `deg` and a shift (m)."""
    a = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = shift
    return T


def test_agreement_counts_the_poses_within_the_distinct_radius():
    cfg = AlignConfig().judge
    centre = np.array([5.0, 0.0, 1.0])
    poses = [_pose(0, (0, 0, 0)), _pose(1, (0.3, 0, 0)), _pose(40, (0, 0, 0)), _pose(0, (3, 0, 0))]
    expected = [sum(not judge.distinct(A, B, centre, cfg) for B in poses) for A in poses]
    assert judge.agreement(poses, centre, cfg).tolist() == expected == [2, 2, 1, 1]


def test_second_look_starts_from_the_cluster_most_candidates_agree_on():
    """Three near-duplicates (several generators finding one pose) come before lone starts ranked
    above them, the cluster's best-ranked member its start; near-duplicates of a start and of the
    weak pose are not looked from again."""
    cfg = AlignConfig().judge
    centre = np.zeros(3)
    weak, lone_a, lone_b = _pose(90, (0, 0, 0)), _pose(0, (8, 0, 0)), _pose(180, (0, 6, 0))
    cluster = [_pose(30 + d, (2, 2, 0)) for d in (1.6, 0.0, 0.8)]
    names = ["lone a", "near the weak pose", "lone b", *["cluster"] * 3]
    poses = [lone_a, _pose(91, (0.2, 0, 0)), lone_b, *cluster]
    cands = [judge.Candidate(T=T, source=n) for T, n in zip(poses, names)]
    starts = judge.second_look(weak, cands, centre, cfg)
    assert len(starts) == 3
    assert np.allclose(starts[0], cluster[0])
    assert np.allclose(starts[1], lone_a) and np.allclose(starts[2], lone_b)

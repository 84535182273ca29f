"""Calibration of the pose judge (align/judge/) on right and wrong poses of real and simulated pairs.

For every case (a pair with exact or refined truth, each cloud in its own random frame):
  * every hypothesis of the global search and the start are refined like a rival and profiled;
    each refined pose is labelled right (within 1 deg / 10 cm of the truth) or wrong, and its
    margin over the best pose distinct from it is what the judge's confidence is made of;
  * the pipeline itself runs on the default path, --no-coarse from the start the files came in,
    and the true-pose control (source handed over in its true pose, coarse on and off).
Prints score / confidence distributions of right and wrong poses, a reliability table and the
outcomes, and says whether the configured thresholds accept any wrong pose.

    nice -n 10 .venv/bin/python benchmarks/bench_judge.py            # all cases
    nice -n 10 .venv/bin/python benchmarks/bench_judge.py --quick    # sim pairs only
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from plotmosaic.align import judge
from plotmosaic.align.fine import final_icp
from plotmosaic.align.floors import blunt_fit
from plotmosaic.align.pair import Start, global_search, register_prepared
from plotmosaic.align.pipeline import prepare_pair
from plotmosaic.config.align import AlignConfig
from plotmosaic.errors import RegistrationFailed
from plotmosaic.io.frame import to_local_transform
from plotmosaic.io.las import PointCloud, read_cloud
from plotmosaic.poses import load_poses

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RIGHT_DEG, RIGHT_M = 1.0, 0.10
MAX_POSES = 16  # hypotheses per case refined and profiled (refined ones first, by score)


def random_frame(rng: np.random.Generator, centre: np.ndarray, tilt_deg: float = 3.0) -> np.ndarray:
    """A rigid transform putting a view in its own frame: any heading, a small tilt, centred away from the data."""
    R = Rotation.from_euler(
        "zyx", [rng.uniform(0, 360), *rng.uniform(-tilt_deg, tilt_deg, 2)], degrees=True
    ).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ centre + rng.uniform(-50, 50, 3)
    return T


def apply(T: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return xyz @ T[:3, :3].T + T[:3, 3]


def view_pair(points: np.ndarray, a_xy, b_xy, range_a: float, range_b: float, seed: int):
    """Two views: occlusion-aware virtual scans (simulate/from_cloud.py) when available, else range crops."""
    try:
        from plotmosaic.simulate.from_cloud import cut_views

        va = cut_views(points, [a_xy], seed=seed, max_range=range_a)[0]
        vb = cut_views(points, [b_xy], seed=seed + 1, max_range=range_b)[0]
        return va.points, vb.points, np.linalg.inv(vb.truth) @ va.truth, "from_cloud"
    except ImportError:
        rng = np.random.default_rng(seed)
        out = []
        for xy, r in ((a_xy, range_a), (b_xy, range_b)):
            ground = np.percentile(points[np.linalg.norm(points[:, :2] - xy, axis=1) < 2, 2], 2)
            keep = np.linalg.norm(points - [*xy, ground + 1.5], axis=1) < r
            F = random_frame(rng, np.array([*xy, ground + 1.5]))
            out.append((apply(F, points[keep]), F))
        (pa, Fa), (pb, Fb) = out
        return pa, pb, Fb @ np.linalg.inv(Fa), "range crop"


def cases(quick: bool, sim_root: Path):
    """(name, source xyz, target xyz, source kind, target kind, truth source -> target, related)."""
    from plotmosaic.simulate.run import simulate

    sims = {}
    for seed in (0, 1):
        out = sim_root / f"sim{seed}"
        if not (out / "ground_truth.json").exists():
            simulate(out, "small", seed=seed)
        sims[seed] = out
    for seed, pairs in (
        (0, [("S1", "S0"), ("S2", "S0"), ("S3", "S4")]),
        (1, [("S1", "S0"), ("S4", "S2")]),
    ):
        truth = load_poses(sims[seed] / "ground_truth.json")
        for a, b in pairs:
            T = np.linalg.inv(truth.transform(f"P1-{b}")) @ truth.transform(f"P1-{a}")
            yield (
                f"sim{seed} {a}->{b}",
                read_cloud(sims[seed] / "P1" / f"P1-{a}.laz", attributes=False).xyz,
                read_cloud(sims[seed] / "P1" / f"P1-{b}.laz", attributes=False).xyz,
                "tls",
                "tls",
                T,
                True,
            )
    s0 = read_cloud(sims[0] / "P1" / "P1-S1.laz", attributes=False).xyz
    s1 = read_cloud(sims[1] / "P1" / "P1-S0.laz", attributes=False).xyz
    yield "unrelated sim0 S1 vs sim1 S0", s0, s1, "tls", "tls", None, False
    if quick or not DATA.is_dir():
        return
    rng = np.random.default_rng(15)
    pine = read_cloud(DATA / "treels" / "pine_plot.laz", attributes=False).xyz
    c = pine[:, :2].mean(axis=0)
    pa, pb, T, how = view_pair(pine, c + [-3.5, 0.5], c + [3.5, -0.5], 12.0, 12.0, 1)
    yield f"treels views 7 m apart ({how})", pa, pb, "tls", "tls", T, True
    treels_view = pb
    mls = read_cloud(DATA / "spanner" / "MLS_Clip.laz", attributes=False).xyz
    c = mls[:, :2].mean(axis=0)
    pa, pb, T, how = view_pair(mls, c + [-4.0, 0.0], c + [4.0, 0.0], 15.0, 15.0, 2)
    yield f"MLS views 8 m apart ({how})", pa, pb, "mls", "mls", T, True
    pa, pb, T, how = view_pair(mls, c + [-4.0, 0.0], c + [4.0, 0.0], 6.0, 15.0, 3)
    yield f"MLS views 8 m apart, source boxed to 6 m ({how})", pa, pb, "mls", "mls", T, True
    uas = read_cloud(DATA / "spanner" / "UAS_Clip.laz", attributes=False).xyz
    als = read_cloud(DATA / "spanner" / "ALS_Clip.laz", attributes=False).xyz
    F = random_frame(rng, uas.mean(axis=0))
    # truth: the clips' co-registration (UAS and ALS agree to a few cm / ~0.1 deg, see fine part)
    yield (
        "UAS -> ALS (UAS in a random frame)",
        apply(F, uas),
        als,
        "uls",
        "als",
        np.linalg.inv(F),
        True,
    )
    strip = uas[np.abs(uas[:, 0] - uas[:, 0].mean()) < 2.5]
    F = random_frame(rng, strip.mean(axis=0))
    yield "UAS strip 5 m wide -> ALS", apply(F, strip), als, "uls", "als", np.linalg.inv(F), True
    yield "unrelated sim0 S1 vs treels view", s0, treels_view, "tls", "tls", None, False


# trials of bench_real.py's suite, prepared exactly as the suite does (plotmosaic/bench/real_suite.py):
# (case, protocol, trial, coarse settings changed); mls-2views paper trial 3 with six vertical pairs
# returned a pose 115 deg / 6.2 m off with judge confidence 0.297 (generators.md): the known hard wrong case
SUITE_TRIALS = (
    ("mls-boxed6m", "paper", 0, {}),
    ("mls-boxed6m", "paper", 1, {}),
    ("mls-boxed6m", "beyond", 4, {}),
    ("mls-boxed6m", "true", 0, {}),
    ("mls-2views", "paper", 3, {"max_vertical_pairs": 6, "max_target_verticals": 3}),
    ("mls-2views", "paper", 1, {"max_vertical_pairs": 6, "max_target_verticals": 3}),
    ("mls-2views", "paper", 3, {}),
)


# wrong poses found by the pipeline on a suite case, as placements of the case's source in the target
# (source file in the truth -> target file): judged on every trial of that case as extra hypotheses.
# mls-2views: H2's draw 1 (sample_params(paper, 5, 1000)[1], generators.md) with six vertical pairs at
# 5ea5d8a, 107 deg / 13 m off, the truth not among the hypotheses (judge confidence 0.10 then); the
# 115 deg / 6.2 m pose of draw 3 (confidence 0.297) came from a tree never committed: trial 3 at
# 5ea5d8a is found (0.02 deg) and its rows here are the current generators' hypotheses
KNOWN_WRONG = {
    "mls-2views": [
        [
            [-0.286785615, -0.954873598, -0.077268517, 1.764273441],
            [0.934281319, -0.296610223, 0.197840323, 10.975125745],
            [-0.211831133, -0.015452773, 0.977184109, 0.028060996],
            [0.0, 0.0, 0.0, 1.0],
        ]
    ]
}


def suite_trials(cases: list[str], n: int) -> list[tuple]:
    """SUITE_TRIALS, then trials 0..n-1 of the paper and beyond protocols of `cases` not among them."""
    out = list(SUITE_TRIALS)
    for name in cases:
        for proto in ("paper", "beyond"):
            for k in range(n):
                if (name, proto, k, {}) not in out:
                    out.append((name, proto, k, {}))
    return out


def suite_cases(trials):
    """(name, prepared source, prepared target, truth source file -> target file, config) per trial."""
    from plotmosaic.align.prepare import prepare_cloud
    from plotmosaic.bench.protocol import params_to_matrix
    from plotmosaic.bench.real_suite import _case_state, draw
    from plotmosaic.config.align import default_levels
    from plotmosaic.io.frame import apply_transform

    for name, proto, trial, coarse in trials:
        case, aligned, pt, _ = _case_state(name, 0, None)
        P = params_to_matrix(draw(proto, 0, name, trial), aligned.xyz.mean(axis=0))
        moved = PointCloud(apply_transform(P, aligned.xyz), crs=aligned.crs)
        cfg = AlignConfig()
        if coarse:
            cfg = cfg.model_copy(update={"coarse": cfg.coarse.model_copy(update=coarse)})
        kind = case.source_kind.lower()
        ps = prepare_cloud(moved, kind, default_levels(kind), cfg, trial, "source")
        label = f"suite {name} {proto} {trial}" + "".join(f" {k}={v}" for k, v in coarse.items())
        extra = [np.asarray(E) @ np.linalg.inv(P) for E in KNOWN_WRONG.get(name, [])]
        yield label, ps, pt, np.linalg.inv(P), cfg, extra


def label_of(A: np.ndarray, truth_local: np.ndarray | None, centre: np.ndarray) -> str:
    """right: in the truth's basin (the final ICP polishes it); wrong: a distinct pose; near: neither."""
    if truth_local is None:
        return "wrong"
    deg, m = judge.separation(A, truth_local, centre)
    return "wrong" if deg > 3.0 or m > 1.0 else ("right" if deg < 2.0 and m < 0.3 else "near")


def right(T: np.ndarray, truth_local: np.ndarray | None, centre: np.ndarray) -> bool:
    if truth_local is None:
        return False
    deg, m = judge.separation(T, truth_local, centre)
    return deg < RIGHT_DEG and m < RIGHT_M


def prepared(name, xs, xt, ks, kt, T_true, related, cfg: AlignConfig):
    """(name, prepared source, prepared target, truth, config) of a case from cases()."""
    ps, pt = prepare_pair(
        PointCloud(xs),
        PointCloud(xt),
        (ks, kt),
        (3 if ks in ("tls", "mls") else 2, 3 if kt in ("tls", "mls") else 2),
        cfg,
        0,
    )
    return name, ps, pt, T_true, cfg, []


def run_case(
    name,
    ps,
    pt,
    T_true,
    cfg: AlignConfig,
    extra: list,
    rows: list,
    outcomes: list,
    paths: bool = True,
) -> None:
    """`extra`: more poses to judge (source file -> target file), e.g. KNOWN_WRONG."""
    t0 = time.perf_counter()
    truth_local = None if T_true is None else to_local_transform(T_true, ps.frame, pt.frame)
    centre = ps.points.mean(axis=0)
    jc = cfg.judge
    cres = global_search(ps, pt, cfg, 0)
    # every hypothesis and the start, refined the way a rival is, then profiled
    poses = []
    order = sorted(cres.hypotheses, key=lambda h: (not h.refined, -float(h.score or 0.0)))
    for h in order[:MAX_POSES]:
        A = judge.refine(ps, pt, np.asarray(h.T, float), jc)
        poses.append((A, judge.profile(ps, pt, A, jc).score, h.generator))
    start = to_local_transform(np.eye(4), ps.frame, pt.frame)
    A = judge.refine(ps, pt, start, jc)
    poses.append((A, judge.profile(ps, pt, A, jc).score, "start"))
    for E in extra:
        A = judge.refine(ps, pt, to_local_transform(E, ps.frame, pt.frame), jc)
        poses.append((A, judge.profile(ps, pt, A, jc).score, "known wrong"))
    profiles = [judge.profile(ps, pt, A, jc) for A, _, _ in poses]
    labels = [label_of(A, truth_local, centre) for A, _, _ in poses]
    for i, (A, score, gen) in enumerate(poses):
        rivals = [
            s for j, (B, s, _) in enumerate(poses) if j != i and judge.distinct(A, B, centre, jc)
        ]
        best = max(rivals, default=0.0)
        stored = stored_check(ps, pt, A, cfg, truth_local, centre)
        F = stored.pop("final")
        # the pose the pipeline would judge (A after the final ICP) against the refined others
        others = [
            j for j, (B, _, _) in enumerate(poses) if j != i and judge.distinct(F, B, centre, jc)
        ]
        fin = judge.profile(ps, pt, F, jc)
        # its own basin (judge.basin): starts around F, refined; the sharper ones are rivals
        near = [q for _, q in judge.basin(ps, pt, F, jc)] if jc.basin_neighbours else []
        sharper = judge.sharper_neighbours(fin, near, jc)
        mine_fine = judge.fine_share(fin, jc)
        basin_ratio = (
            max((judge.fine_share(q, jc) for q in near), default=0.0) / mine_fine
            if mine_fine > 0
            else float("inf")
        )
        fm = judge.fine_margin(fin, [profiles[j] for j in others] + sharper, jc)
        margin = 1.0 - best / score if score > 0 else -1.0
        deg, m = (None, None) if truth_local is None else judge.separation(A, truth_local, centre)
        label = labels[i]
        # the generators missed the truth (or left it too far off for the rival refinement)
        wrong_others = [profiles[j] for j in others if labels[j] == "wrong"]
        rows.append(
            {
                "case": name,
                "generator": gen,
                "right": label == "right",
                "label": label,
                "deg": deg,
                "m": m,
                "score": score,
                "margin": margin,
                # this pose handed over as a stored pose (E57 use_pose): would it skip the search?
                **stored,
                # the judge's figures of the final-ICP pose against the distinct refined others
                "final_score": fin.score,
                "final_margin": 1.0
                - max((profiles[j].score for j in others), default=0.0) / fin.score
                if fin.score > 0
                else -1.0,
                "final_sharpness": judge.sharpness(fin),
                "fine_margin": fm,
                "basin_ratio": basin_ratio,
                "basin_sharper": len(sharper),
                "fine_margin_wrong_rivals": judge.fine_margin(fin, wrong_others + sharper, jc),
                "fine_margin_wrong_rivals_no_basin": judge.fine_margin(fin, wrong_others, jc),
                "confidence_wrong_rivals": judge.confidence(fin, wrong_others + sharper, jc),
                "confidence_wrong_rivals_no_basin": judge.confidence(fin, wrong_others, jc),
                "final_margin_wrong_rivals": 1.0
                - max((p.score for p in wrong_others), default=0.0) / fin.score
                if fin.score > 0
                else -1.0,
                # what the judge would say of it (its confidence: the fine margin)
                "confidence": judge.confidence(fin, [profiles[j] for j in others] + sharper, jc),
                "final_profile": fin.to_dict(),
                "rival_profiles": [profiles[j].to_dict() for j in others],
            }
        )
    if not paths:
        print(
            f"  {name}: {len(poses)} poses, {time.perf_counter() - t0:.0f} s",
            file=sys.stderr,
            flush=True,
        )
        return
    # the pipeline on its three paths and the true-pose control
    local = cfg.model_copy(deep=True)
    local.coarse.enabled = False
    for path, c, init, stored in (
        ("default", cfg, None, False),
        ("--no-coarse", local, None, False),
        ("true pose, --no-coarse", local, T_true, False),
        ("true pose, --init", cfg, T_true, False),
        ("true pose, stored", cfg, T_true, True),
        ("identity, stored", cfg, np.eye(4), True),
    ):
        if path.startswith("true") and T_true is None:
            continue
        try:
            r = register_prepared(ps, pt, c, init, 0, start=Start.STORED if stored else Start.PRIOR)
            accepted = True
        except RegistrationFailed as exc:
            r, accepted = exc.result, False
        if r is None:
            outcomes.append(
                {
                    "case": name,
                    "path": path,
                    "accepted": False,
                    "right": False,
                    "deg": None,
                    "m": None,
                    "confidence": None,
                    "score": None,
                    "rival": None,
                }
            )
            continue
        T_local = to_local_transform(r.transform, ps.frame, pt.frame)
        deg, m = (
            (None, None) if truth_local is None else judge.separation(T_local, truth_local, centre)
        )
        j = r.judge or {}
        outcomes.append(
            {
                "case": name,
                "path": path,
                "accepted": accepted,
                "right": right(T_local, truth_local, centre),
                "deg": deg,
                "m": m,
                "confidence": r.confidence,
                "score": j.get("score"),
                "rival": j.get("rival_score"),
                "judge_s": r.timings.get("judge"),
                "skipped": "coarse_skipped" in r.steps,
            }
        )
    print(
        f"  {name}: {len(poses)} poses, {time.perf_counter() - t0:.0f} s",
        file=sys.stderr,
        flush=True,
    )


def stored_check(ps, pt, A, cfg: AlignConfig, truth_local, centre) -> dict:
    """The stored-pose check (judge.verify_stored after the fine ICP) from pose A."""
    F = final_icp(ps, pt, A, cfg).T
    v = judge.verify_stored(ps, pt, A, F, cfg.judge)
    return {
        "final": F,
        "stored_verified": v.verified,
        "sharpness": v.sharpness,
        "stored_correction_deg": v.correction_deg,
        "stored_right": right(F, truth_local, centre),
    }


def histogram(values, edges) -> list[int]:
    return np.histogram(np.asarray(values, float), bins=edges)[0].tolist()


def report(rows: list, outcomes: list, cfg: AlignConfig) -> str:
    jc = cfg.judge
    lines = []
    r = [x for x in rows if x["label"] == "right"]
    w = [x for x in rows if x["label"] == "wrong"]
    lines.append(
        f"refined poses: {len(r)} right (within 2 deg / 0.3 m of the truth after the rival refinement),"
        f" {len(w)} wrong (> 3 deg or > 1 m), {len(rows) - len(r) - len(w)} in between (left out),"
        f" over {len({x['case'] for x in rows})} cases\n"
    )
    edges = [-1e9, 0.0, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.8, 1.0]
    lines.append("| confidence bin | right poses | wrong poses | share right |")
    lines.append("|---|---|---|---|")
    cr, cw = (
        histogram([x["confidence"] for x in r], edges[1:]),
        histogram([x["confidence"] for x in w], edges[1:]),
    )
    for k in range(len(edges) - 2):
        n = cr[k] + cw[k]
        lines.append(
            f"| {edges[k + 1]:.2f}-{edges[k + 2]:.2f} | {cr[k]} | {cw[k]} | {cr[k] / n:.2f} |"
            if n
            else f"| {edges[k + 1]:.2f}-{edges[k + 2]:.2f} | 0 | 0 | - |"
        )
    lines.append("")
    lines.append(
        "| case | right: score, fine margin, confidence | best wrong: score, fine margin,"
        " sharpness, confidence |"
    )
    lines.append("|---|---|---|")
    for case in dict.fromkeys(x["case"] for x in rows):
        rr = [x for x in r if x["case"] == case]
        ww = [x for x in w if x["case"] == case]
        a = max(rr, key=lambda x: x["confidence"], default=None)
        b = max(ww, key=lambda x: (x["confidence"], x["fine_margin"]), default=None)
        fa = (
            f"{a['final_score']:.3f}, {a['fine_margin']:.3f}, {a['confidence']:.2f}"
            if a
            else "not found"
        )
        fb = (
            f"{b['final_score']:.3f}, {b['fine_margin']:.3f}, {b['final_sharpness']:.3f},"
            f" {b['confidence']:.2f} ({b['generator']})"
            if b
            else "-"
        )
        lines.append(f"| {case} | {fa} | {fb} |")

    def passes(x: dict) -> bool:  # what check_quality asks of the judge's figures
        return (
            x["confidence"] >= cfg.min_confidence
            and x["final_score"] >= jc.min_score
            and blunt_fit(x["final_sharpness"], x["confidence"], jc) is None
            and x["final_margin"] > 0
        )

    worst = max(w, key=lambda x: x["fine_margin"], default=None)
    if worst is not None:
        lines.append(
            f"\nhighest fine margin of a wrong pose: {worst['fine_margin']:.3f} (confidence"
            f" {worst['confidence']:.2f}, {worst['case']}, {worst['generator']});"
            f" lowest of a right pose: {min(x['fine_margin'] for x in r):.3f}"
            if r
            else ""
        )
    alone = max(w, key=lambda x: x.get("fine_margin_wrong_rivals", -1.0), default=None)
    if alone is not None and "fine_margin_wrong_rivals" in alone:
        lines.append(
            f"against wrong rivals alone (the truth missed): highest fine margin of a wrong pose"
            f" {alone['fine_margin_wrong_rivals']:.3f} ({alone['case']}, {alone['generator']},"
            f" sharpness {alone['final_sharpness']:.3f}); a fine margin of"
            f" {jc.chance_margin + cfg.min_confidence * (jc.full_margin - jc.chance_margin):.2f}"
            f" is confidence {cfg.min_confidence}"
        )

    def passes_alone(x: dict, key: str) -> bool:  # the same against wrong rivals alone
        return (
            x[key] >= cfg.min_confidence
            and x["final_score"] >= jc.min_score
            and blunt_fit(x["final_sharpness"], x[key], jc) is None
            and x["final_margin_wrong_rivals"] > 0
        )

    if w and "confidence_wrong_rivals" in w[0]:
        with_b = [x for x in w if passes_alone(x, "confidence_wrong_rivals")]
        without = [x for x in w if passes_alone(x, "confidence_wrong_rivals_no_basin")]
        lines.append(
            f"against wrong rivals alone, wrong poses passing: {len(with_b)} / {len(w)} with the basin"
            f" check, {len(without)} / {len(w)} without"
            + "".join(
                f"; {x['case']} {x['generator']} {x['deg']:.1f} deg / {x['m']:.2f} m: fine margin"
                f" {x['fine_margin_wrong_rivals_no_basin']:.3f} -> {x['fine_margin_wrong_rivals']:.3f}"
                f" (basin {x['basin_ratio']:.2f}x)"
                for x in without
            )
        )
        ratios = sorted(x["basin_ratio"] for x in r)
        lines.append(
            f"basin ({jc.basin_neighbours} starts, {jc.basin_deg} deg / {jc.basin_m} m x the factor):"
            f" right poses' best start ends at {ratios[0]:.3f}-{ratios[-1]:.3f}x their fine share"
            f" ({sum(x['basin_sharper'] > 0 for x in r)} of {len(r)} beyond the {1 + jc.basin_tolerance:.2f}x"
            f" tolerance); wrong poses: {sum(x['basin_sharper'] > 0 for x in w)} of {len(w)} have a sharper"
            " start"
            if r
            else ""
        )
    # labels are of the rival-refined pose; the pipeline judges it after the final ICP, which may reach the truth
    ended_right = [x for x in w if passes(x) and x["stored_right"]]
    if ended_right:
        lines.append(
            f"of the wrong poses passing, {len(ended_right)} end right after the final ICP (the pose the"
            " judge sees; not wrong acceptances): "
            + ", ".join(f"{x['case']} {x['generator']} {x['deg']:.1f} deg" for x in ended_right)
        )
    lines.append(
        f"wrong poses passing the judge (confidence >= {cfg.min_confidence}, score >="
        f" {jc.min_score}, sharpness >= {jc.min_sharpness} or >= {jc.blunt_min_sharpness} with"
        f" confidence >= {jc.blunt_min_confidence}, score margin > 0):"
        f" {sum(passes(x) for x in w)} / {len(w)}; right poses passing: {sum(passes(x) for x in r)}"
        f" / {len(r)}"
    )
    lines.append(stored_table(rows, jc))
    lines.append(
        "\n| case | path | outcome | error deg / m | confidence | judge score / rival | judge s |"
        " search |"
    )
    lines.append("|---|---|---|---|---|---|---|---|")
    bad = 0
    for o in outcomes:
        verdict = ("right" if o["right"] else "WRONG") if o["accepted"] else "refused (exit 3)"
        bad += o["accepted"] and not o["right"]
        err = "-" if o["deg"] is None else f"{o['deg']:.3f} / {o['m']:.3f}"
        conf = "-" if o["confidence"] is None else f"{o['confidence']:.2f}"
        sc = "-" if o["score"] is None else f"{o['score']:.3f} / {o['rival']:.3f}"
        js = "-" if o.get("judge_s") is None else f"{o['judge_s']:.2f}"
        search = "skipped" if o.get("skipped") else "ran"
        lines.append(
            f"| {o['case']} | {o['path']} | {verdict} | {err} | {conf} | {sc} | {js} | {search} |"
        )
    lines.append(f"\nwrong poses accepted (exit 0): {bad}")
    return "\n".join(lines)


def stored_table(rows: list, jc) -> str:
    """Every refined pose handed over as a stored pose: sharpness after the fine ICP, and whether
    the check passed (a verified wrong one would skip the search with a wrong pose)."""
    edges = [0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.08, 0.1, 0.15, 0.2, 1.0]
    r = [x for x in rows if x["stored_right"]]
    w = [x for x in rows if not x["stored_right"]]
    out = [
        f"\nStored-pose check (every refined pose handed over as a stored pose, fine ICP from it):"
        f" {len(r)} end right, {len(w)} end wrong; min sharpness {jc.stored_min_sharpness},"
        f" max correction {jc.stored_max_correction_deg} deg / {jc.stored_max_correction_m} m\n",
        "| sharpness bin | right | right verified | wrong | wrong verified |",
        "|---|---|---|---|---|",
    ]
    for a, b in zip(edges[:-1], edges[1:]):
        rr = [x for x in r if a <= x["sharpness"] < b]
        ww = [x for x in w if a <= x["sharpness"] < b]
        if rr or ww:
            out.append(
                f"| {a:.2f}-{b:.2f} | {len(rr)} | {sum(x['stored_verified'] for x in rr)} |"
                f" {len(ww)} | {sum(x['stored_verified'] for x in ww)} |"
            )
    worst = max((x["sharpness"] for x in w), default=0.0)
    out.append(
        f"\nhighest sharpness of a wrong pose: {worst:.3f}; wrong poses verified:"
        f" {sum(x['stored_verified'] for x in w)}; lowest sharpness of a right pose:"
        f" {min((x['sharpness'] for x in r), default=float('nan')):.3f}"
    )
    return "\n".join(out)


def refined_truth(uas: np.ndarray, als: np.ndarray, cache: Path) -> np.ndarray:
    """UAS file -> ALS file pose from three independent fine methods (Open3D), ALS onto the dense UAS, over
    0.5 / 0.25 / 0.1 m: point-to-point, point-to-plane, GICP; their mean (they agree to ~0.07 deg / 2 cm)."""
    if cache.exists():
        return np.asarray(json.loads(cache.read_text())["transform"])
    import open3d as o3d

    off = als.mean(axis=0).round()
    U = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(uas - off))
    A = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(als - off))
    U.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.25, max_nn=30))
    A.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=1.0, max_nn=30))
    reg = o3d.pipelines.registration
    crit = reg.ICPConvergenceCriteria(1e-10, 1e-10, 300)
    found = []
    for fn, est in (
        (reg.registration_icp, reg.TransformationEstimationPointToPoint()),
        (reg.registration_icp, reg.TransformationEstimationPointToPlane()),
        (reg.registration_generalized_icp, reg.TransformationEstimationForGeneralizedICP()),
    ):
        T = np.eye(4)
        for d in (0.5, 0.25, 0.1):
            T = fn(A, U, d, T, est, crit).transformation
        found.append(np.linalg.inv(T))
    c = uas.mean(axis=0) - off
    for i in range(3):
        for j in range(i + 1, 3):
            deg, m = judge.separation(found[i], found[j], c)
            print(
                f"  refined truth: methods {i} and {j} differ by {deg:.3f} deg / {100 * m:.2f} cm",
                file=sys.stderr,
            )
    T = np.eye(4)
    T[:3, :3] = Rotation.from_matrix([F[:3, :3] for F in found]).mean().as_matrix()
    T[:3, 3] = np.mean([F[:3, 3] for F in found], axis=0)
    S = np.eye(4)
    S[:3, 3] = off
    T = S @ T @ np.linalg.inv(S)
    cache.write_text(json.dumps({"transform": T.tolist()}))
    return T


def bench_fine(work: Path, n: int) -> str:
    """UAS -> ALS from +-10 deg / +-2 m starts (coarse on: the start is a prior) and from the refined truth
    (--no-coarse), with the final ICP on the dense side (default) and on the sparse ALS planes (before)."""
    uas = read_cloud(DATA / "spanner" / "UAS_Clip.laz", attributes=False).xyz
    als = read_cloud(DATA / "spanner" / "ALS_Clip.laz", attributes=False).xyz
    T_true = refined_truth(uas, als, work / "uas_als_refined_truth.json")
    lines = [
        "| final ICP planes | start | trials | rotation RMSE deg (x / y / z) | translation RMSE cm (x / y / z) | exit 3 |",
        "|---|---|---|---|---|---|",
    ]
    centre = uas.mean(axis=0)
    for label, ratio in (
        ("denser cloud (UAS), default", None),
        ("target (sparse ALS), before", 1e9),
    ):
        cfg = AlignConfig() if ratio is None else AlignConfig(final_reverse_ratio=ratio)
        ps, pt = prepare_pair(PointCloud(uas), PointCloud(als), ("uls", "als"), (2, 2), cfg, 0)
        local = cfg.model_copy(deep=True)
        local.coarse.enabled = False
        rng = np.random.default_rng(4)
        for start, c, count in (
            ("refined truth, --no-coarse", local, 1),
            ("+-10 deg / +-2 m, --init", cfg, n),
        ):
            errs, refused = [], 0
            for _ in range(count):
                P = np.eye(4)
                if count > 1:
                    P[:3, :3] = Rotation.from_euler(
                        "xyz", rng.uniform(-10, 10, 3), degrees=True
                    ).as_matrix()
                    P[:3, 3] = centre - P[:3, :3] @ centre + rng.uniform(-2, 2, 3)
                try:
                    r = register_prepared(ps, pt, c, T_true @ P, 0)
                except RegistrationFailed as exc:
                    refused += 1
                    r = exc.result
                D = np.linalg.inv(T_true) @ r.transform
                errs.append(
                    np.r_[
                        Rotation.from_matrix(D[:3, :3]).as_euler("xyz", degrees=True),
                        D[:3, :3] @ centre + D[:3, 3] - centre,
                    ]
                )
            e = np.sqrt(np.mean(np.square(errs), axis=0))
            lines.append(
                f"| {label} | {start} | {count} | {' / '.join(f'{v:.3f}' for v in e[:3])} | "
                f"{' / '.join(f'{100 * v:.2f}' for v in e[3:])} | {refused} |"
            )
            print(lines[-1], file=sys.stderr, flush=True)
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="simulated pairs only")
    ap.add_argument("--json", type=Path, help="write the raw rows here")
    ap.add_argument("--only", default="", help="run only the cases whose name contains this")
    ap.add_argument("--no-suite", action="store_true", help="leave out the suite's trials")
    ap.add_argument("--suite-only", action="store_true", help="only the suite's trials")
    ap.add_argument(
        "--suite-n", type=int, default=0, help="also trials 0..N-1 (paper, beyond) of --suite-cases"
    )
    ap.add_argument(
        "--suite-cases",
        default="mls-boxed6m,mls-2views,treels-2views,uas-strip-als,sim-understorey",
        help="bench_real.py cases of --suite-n",
    )
    ap.add_argument(
        "--suite-skip",
        type=int,
        default=0,
        help="leave out the first K suite trials (a resumed run)",
    )
    ap.add_argument(
        "--poses-only", action="store_true", help="calibration rows only, not the pipeline paths"
    )
    ap.add_argument(
        "--fine",
        type=int,
        default=0,
        metavar="N",
        help="instead: fine-stage accuracy on UAS -> ALS against a refined truth, N perturbed starts",
    )
    ap.add_argument(
        "--work", type=Path, default=Path(tempfile.gettempdir()) / "plotmosaic-bench-judge"
    )
    args = ap.parse_args()
    cfg = AlignConfig()
    rows, outcomes = [], []
    args.work.mkdir(parents=True, exist_ok=True)
    if args.fine:
        print(bench_fine(args.work, args.fine))
        return
    every = () if args.suite_only else (prepared(*c, cfg) for c in cases(args.quick, args.work))
    trials = suite_trials(args.suite_cases.split(","), args.suite_n)[args.suite_skip :]
    suite = () if args.quick or args.no_suite or not DATA.is_dir() else suite_cases(trials)
    for name, ps, pt, T_true, c, extra in itertools.chain(every, suite):
        if args.only in name:
            run_case(name, ps, pt, T_true, c, extra, rows, outcomes, not args.poses_only)
            if args.json:  # after every case: a long run can be read while it goes
                args.json.write_text(
                    json.dumps({"rows": rows, "outcomes": outcomes}, indent=1, default=float)
                )
    print(report(rows, outcomes, cfg))


if __name__ == "__main__":
    main()

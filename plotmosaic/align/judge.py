"""The pose judge: one verification that every pairwise result goes through (coarse, --init, --no-coarse).

A pose is scored by a residual profile: the share of sample points within several distances
(2-25 cm at the delta0 spacing, stretched for sparse clouds) of the other cloud, on non-flat points
(stems, branches, crowns: flat ground fits anywhere) and on all points, in both directions.
The pose must beat every *distinct* rival (other hypotheses of the global search, the start as
handed over), each refined by a short ICP and profiled the same way: the confidence comes from the
relative margin at the finest scale (`fine_margin`), where a right pose stands out; the wide scales
gather points by chance in a forest and rank wrong rivals close to a right pose. A pose must also be
the sharpest of its own basin: starts a few degrees / decimetres around it, refined the same way, must
not end sharper (`basin`): a near miss (a pose the final ICP left 1-4 deg off, inside the distinct radius
of the truth) has no distinct rival at the truth when the search missed it, but its neighbours reach it.
Every transform here maps source-local to target-local coordinates.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from plotmosaic.align import scene
from plotmosaic.align.icp import nearest, point_to_plane_icp
from plotmosaic.align.memo import CloudMemo, PairMemo
from plotmosaic.align.sampling import sample
from plotmosaic.config.align import IcpStage
from plotmosaic.config.judge import JudgeConfig
from plotmosaic.io.frame import inverse, rotation_deg
from plotmosaic.parallel import in_two_threads


@dataclass
class _Samples:
    everything: np.ndarray  # profile sample of the cloud (its level points: even density)
    structure: np.ndarray  # the non-flat part of it
    spacing: float  # median nearest-neighbour spacing of the delta0 points (m)
    fine: np.ndarray  # source points of a rival's refinement ICP
    centre: np.ndarray  # centroid of the cloud's points: where pose separations are measured


def _samples(cloud, config: JudgeConfig, memo: CloudMemo | None) -> _Samples:
    """Seeded samples of a prepared cloud, kept in `memo` (a scan takes part in several pairs)."""
    key = config.model_dump_json(
        include={"profile_points", "structure_max_planarity", "rival_points"}
    )
    return (memo or CloudMemo()).judge.get(key, lambda: _draw_samples(cloud, config))


def _draw_samples(cloud, config: JudgeConfig) -> _Samples:
    rng = np.random.default_rng(20_261_201)
    pts = cloud.level_points
    planarity = np.nan_to_num(np.asarray(cloud.features)[:, 1], nan=1.0)
    flat = planarity >= config.structure_max_planarity
    every = pts[sample(len(pts), config.profile_points, rng)]
    struct = pts[~flat]
    struct = struct[sample(len(struct), config.profile_points, rng)]
    probe = pts[sample(len(pts), 2_000, rng)]
    d, _ = cloud.tree.query(probe, k=2)
    spacing = float(np.median(d[:, 1])) if len(probe) > 1 else config.reference_spacing
    fine = cloud.fine_points[sample(len(cloud.fine_points), config.rival_points, rng)]
    return _Samples(every, struct, spacing, fine, cloud.points.mean(axis=0))


def spacing(cloud, config: JudgeConfig, memo: CloudMemo | None = None) -> float:
    """Median nearest-neighbour spacing (m) of a prepared cloud's delta0 points."""
    return _samples(cloud, config, memo).spacing


def scale_factor(src, tgt, config: JudgeConfig, memo: PairMemo | None = None) -> float:
    """How much the profile distances stretch: the sparser cloud is judged at its own resolution."""
    memo = memo or PairMemo()
    spacing = max(
        _samples(src, config, memo.source).spacing, _samples(tgt, config, memo.target).spacing
    )
    return float(np.clip(spacing / config.reference_spacing, 1.0, config.max_scale_factor))


def _shares(points: np.ndarray, tree, T: np.ndarray, scales: np.ndarray) -> list[float]:
    if len(points) == 0:
        return [0.0] * len(scales)
    d, _ = nearest(tree, points @ T[:3, :3].T + T[:3, 3], float(scales[-1]))
    return [float(np.mean(d <= s)) for s in scales]


def profile(src, tgt, T: np.ndarray, config: JudgeConfig, memo: PairMemo | None = None) -> dict:
    """Residual profile of pose T: shares of points within each scale, structure and all, both directions.

    `score` is the mean share over the scales and the two directions on structure points.
    """
    memo = memo or PairMemo()
    s, t = _samples(src, config, memo.source), _samples(tgt, config, memo.target)
    scales = np.asarray(config.scales) * scale_factor(src, tgt, config, memo)
    Ti = inverse(T)
    out = {
        "scales": [float(v) for v in scales],
        "structure_st": _shares(s.structure, tgt.tree, T, scales),
        "structure_ts": _shares(t.structure, src.tree, Ti, scales),
        "all_st": _shares(s.everything, tgt.tree, T, scales),
        "all_ts": _shares(t.everything, src.tree, Ti, scales),
    }
    out["score"] = float(np.mean(out["structure_st"] + out["structure_ts"]))
    out["score_all"] = float(np.mean(out["all_st"] + out["all_ts"]))
    return out


def separation(A: np.ndarray, B: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """(rotation deg, displacement m of the source point `centre`) between two poses."""
    return rotation_deg(inverse(B) @ A), float(
        np.linalg.norm((A[:3, :3] - B[:3, :3]) @ centre + A[:3, 3] - B[:3, 3])
    )


def distinct(A: np.ndarray, B: np.ndarray, centre: np.ndarray, config: JudgeConfig) -> bool:
    deg, m = separation(A, B, centre)
    return m > config.distinct_m or deg > config.distinct_deg


def near(A: np.ndarray, B: np.ndarray, centre: np.ndarray, config: JudgeConfig) -> bool:
    """Within `near_rival_radii` distinct radii (both rotation and displacement): A may be B's basin."""
    deg, m = separation(A, B, centre)
    k = config.near_rival_radii
    return m <= k * config.distinct_m and deg <= k * config.distinct_deg


def centre(cloud, config: JudgeConfig, memo: CloudMemo | None = None) -> np.ndarray:
    """Centroid of a prepared cloud's points: pose separations are measured there."""
    return _samples(cloud, config, memo).centre


def refine(
    src,
    tgt,
    T: np.ndarray,
    config: JudgeConfig,
    into: np.ndarray | None = None,
    memo: PairMemo | None = None,
) -> np.ndarray:
    """A rival's short robust point-to-plane ICP, the same for every rival (distances x the scale
    factor), one stage at a time (the same steps as all stages in one call). `into`: a pose this
    rival would only duplicate; the refinement stops once it is within half the distinct radius
    of it after a stage (the later, narrower stages move it centimetres)."""
    memo = memo or PairMemo()
    f = scale_factor(src, tgt, config, memo)
    A = np.asarray(T, dtype=float)
    for k, (d, n) in enumerate(config.rival_schedule):
        res = point_to_plane_icp(
            _samples(src, config, memo.source).fine,
            tgt.points,
            tgt.target_normals,
            A,
            [IcpStage(max_distance=d * f, iterations=n)],
            tree=tgt.tree,
            kernel_floor=min(config.rival_kernel, d) * f,  # a tight stage needs a tight kernel
            tol=1e-4,
        )
        A = res.T
        if into is not None and k < len(config.rival_schedule) - 1:
            deg, m = separation(A, into, centre(src, config, memo.source))
            if m <= 0.5 * config.distinct_m and deg <= 0.5 * config.distinct_deg:
                break
    return A


def _rival_table(config: JudgeConfig, memo: PairMemo) -> dict:
    """Refined rivals by start pose, kept for the pair: every path of a pair (and the second verdict
    after a better rival) refines and scores a start once."""
    return memo.rivals.get(config.model_dump_json(), dict)


def _refined(
    src, tgt, starts: list[np.ndarray], T: np.ndarray, config: JudgeConfig, memo: PairMemo
) -> list:
    """(refined rival, its profile or None when it ran into T) for each start; the missing ones
    refined two at a time (each its own ICP: the same result as one after the other). A rival that
    ends distinct but `near` T is refined again: a weakly held direction can leave it sliding."""
    table = _rival_table(config, memo)
    c = centre(src, config, memo.source)
    todo = []
    for A0 in starts:
        key = np.asarray(A0, dtype=float).tobytes()
        held = table.get(key)
        # missing, or stopped early running into an earlier pose while this T is elsewhere
        if held is None or (held[1] is None and distinct(held[0], T, c, config)):
            todo.append((key, A0))

    def run(job):
        A = refine(src, tgt, job[1], config, into=T, memo=memo)
        for _ in range(config.near_rival_passes):
            if not distinct(A, T, c, config) or not near(A, T, c, config):
                break
            # still sliding into T, or settled beside it
            A = refine(src, tgt, A, config, into=T, memo=memo)
        return A, None if not distinct(A, T, c, config) else profile(src, tgt, A, config, memo)

    for (key, _), done in zip(todo, in_two_threads(run, todo)):
        table[key] = done
    return [table[np.asarray(A0, dtype=float).tobytes()] for A0 in starts]


def neighbours(T: np.ndarray, centre: np.ndarray, factor: float, config: JudgeConfig) -> list:
    """`basin_neighbours` starts around pose T: turned by +-basin_deg about an axis leaning off the
    vertical (headings are what a search gets wrong most) through the source centre, and shifted
    +-basin_m x the scale factor across it; a fixed set (deterministic)."""
    axes = np.array([[0.5, 0.5, 1.0], [-0.5, 0.5, 1.0], [0.5, -0.5, 1.0], [-0.5, -0.5, 1.0]])
    shifts = np.array([[1.0, -1.0, 0.5], [1.0, 1.0, -0.5], [-1.0, 1.0, 0.5], [-1.0, -1.0, -0.5]])
    c = T[:3, :3] @ centre + T[:3, 3]  # the source centre where T puts it (target frame)
    out = []
    for k in range(config.basin_neighbours):
        sign = 1.0 if k % 2 == 0 else -1.0
        axis, shift = axes[(k // 2) % 4], shifts[(k // 2) % 4]
        R = Rotation.from_rotvec(
            sign * np.radians(config.basin_deg) * axis / np.linalg.norm(axis)
        ).as_matrix()
        P = np.eye(4)
        P[:3, :3] = R
        P[:3, 3] = c - R @ c + sign * config.basin_m * factor * shift / np.linalg.norm(shift)
        out.append(P @ T)
    return out


def basin(src, tgt, T: np.ndarray, config: JudgeConfig, memo: PairMemo | None = None) -> list:
    """(refined start, its profile) for each of T's `neighbours`, refined like a rival (to the end:
    where it lands is the point), kept for the pair with the rivals."""
    memo = memo or PairMemo()
    table = _rival_table(config, memo)
    starts = neighbours(
        T, centre(src, config, memo.source), scale_factor(src, tgt, config, memo), config
    )
    keys = [b"basin" + np.asarray(A0, dtype=float).tobytes() for A0 in starts]
    todo = [(k, A0) for k, A0 in zip(keys, starts) if k not in table]

    def run(job):
        A = refine(src, tgt, job[1], config, memo=memo)
        return A, profile(src, tgt, A, config, memo)

    for (key, _), done in zip(todo, in_two_threads(run, todo)):
        table[key] = done
    return [table[k] for k in keys]


def sharper_neighbours(prof: dict, near: list[dict], config: JudgeConfig) -> list[dict]:
    """The basin profiles `near` that end with more than (1 + basin_tolerance) x the pose's fine share:
    rivals of it (one that returns to the pose, or ends blunter, is none)."""
    mine = fine_share(prof, config)
    return [q for q in near if fine_share(q, config) > (1.0 + config.basin_tolerance) * mine]


@dataclass
class Verdict:
    score: float  # judge score of the pose
    rival_score: float  # of the best distinct rival as sharp as blunt_min_sharpness (0: none)
    margin: float  # 1 - rival_score / score (negative: a rival fits better)
    confidence: float  # from the fine margin (`confidence`), 0-1
    fine_share: float  # of the pose (`fine_share`)
    fine_rival_share: float  # the highest of the distinct rivals' (0 when none)
    fine_margin: float  # 1 - fine_rival_share / fine_share
    fine_rival_source: str | None
    sharpness: float  # of the pose (`sharpness`): near 1 when the clouds coincide, low by chance
    profile: dict
    rival_profile: dict | None
    rival_transform: np.ndarray | None  # source local -> target local
    rival_source: str | None
    candidates: int  # rivals refined and scored
    distinct_rivals: int
    seconds: float = 0.0
    rivals: list[dict] = field(default_factory=list)
    basin_share: float = 0.0  # highest fine share a basin start ended with (0 when none ran)
    basin_transform: np.ndarray | None = None  # that start, refined, when it is a rival (sharper)

    @property
    def rival_better(self) -> bool:
        return self.margin < 0

    def to_dict(self) -> dict:
        return {
            "score": self.score,
            "rival_score": self.rival_score,
            "margin": self.margin,
            "confidence": self.confidence,
            "fine_share": self.fine_share,
            "fine_rival_share": self.fine_rival_share,
            "fine_margin": self.fine_margin,
            "fine_rival_source": self.fine_rival_source,
            "sharpness": self.sharpness,
            "profile": self.profile,
            "rival_profile": self.rival_profile,
            "rival_transform": None
            if self.rival_transform is None
            else np.asarray(self.rival_transform).tolist(),
            "rival_source": self.rival_source,
            "candidates": self.candidates,
            "distinct_rivals": self.distinct_rivals,
            "seconds": self.seconds,
            "rivals": self.rivals,
            "basin_share": self.basin_share,
            "basin_transform": None
            if self.basin_transform is None
            else np.asarray(self.basin_transform).tolist(),
        }


def _shortlist(
    T: np.ndarray, candidates: list[tuple[np.ndarray, str]], centre: np.ndarray, config: JudgeConfig
) -> list[tuple[np.ndarray, str]]:
    """Candidates distinct from T and from each other, in the order given, at most `max_rivals`."""
    kept: list[tuple[np.ndarray, str]] = []
    for A, name in candidates:
        A = np.asarray(A, dtype=float)
        if len(kept) >= config.max_rivals:
            break
        if not np.isfinite(A).all() or not distinct(A, T, centre, config):
            continue
        if all(distinct(A, B, centre, config) for B, _ in kept):
            kept.append((A, name))
    return kept


def judge(
    src,
    tgt,
    T: np.ndarray,
    candidates: list[tuple[np.ndarray, str]],
    config: JudgeConfig,
    memo: PairMemo | None = None,
) -> Verdict:
    """Score pose T against the distinct rivals among `candidates` ((transform, where from), source local ->
    target local), each refined first; a rival that ends within the distinct radius of T is T itself.
    T's `basin` starts that end sharper than T (`sharper_neighbours`) are rivals of the fine margin too;
    rivals blunter than `blunt_min_sharpness` are rivals of the fine margin only, not of the score.
    Refined rivals are kept in the pair's `memo` (`_refined`). A source or target that is not a forest
    scene (`scene.check`) is refused first (RegistrationFailed): no pose between them is right."""
    memo = memo or PairMemo()
    scene.check(src, tgt, config, memo)
    t0 = time.perf_counter()
    c = centre(src, config, memo.source)
    mine = profile(src, tgt, T, config, memo)
    best, best_T, best_name, best_prof, table, profs = 0.0, None, None, None, [], []
    fine_best, fine_name = 0.0, None
    shortlist = _shortlist(T, candidates, c, config)
    refined = _refined(src, tgt, [A0 for A0, _ in shortlist], T, config, memo)
    for (_, name), (A, prof) in zip(shortlist, refined):
        deg, m = separation(A, T, c)
        if m <= config.distinct_m and deg <= config.distinct_deg:
            table.append({"from": name, "distinct": False, "deg": deg, "m": m})
            continue
        fine, sharp = fine_share(prof, config), sharpness(prof)
        profs.append(prof)
        table.append(
            {
                "from": name,
                "distinct": True,
                "deg": deg,
                "m": m,
                "score": prof["score"],
                "fine": fine,
                "sharpness": sharp,
            }
        )
        # a rival too blunt to be accepted itself fits only by chance: it may not outscore the pose
        # (docs/method.md#judge-settings), but it stays a rival of the fine margin
        if prof["score"] > best and sharp >= config.blunt_min_sharpness:
            best, best_T, best_name, best_prof = prof["score"], A, name, prof
        if fine > fine_best:
            fine_best, fine_name = fine, name
    near = basin(src, tgt, T, config, memo) if config.basin_neighbours else []
    sharper = sharper_neighbours(mine, [q for _, q in near], config)
    basin_T, basin_best = None, 0.0
    for k, (A, prof) in enumerate(near):
        deg, m = separation(A, T, c)
        fine, rival = fine_share(prof, config), any(prof is q for q in sharper)
        table.append({"from": f"basin {k}", "distinct": rival, "deg": deg, "m": m, "fine": fine})
        if rival and fine > basin_best:
            basin_T, basin_best = A, fine
        if rival and fine > fine_best:
            fine_best, fine_name = fine, f"the pose's own basin (start {k})"
    fine_rivals = profs + sharper
    score = mine["score"]
    margin = 1.0 - best / score if score > 0 else -1.0
    return Verdict(
        score=score,
        rival_score=best,
        margin=float(margin),
        confidence=confidence(mine, fine_rivals, config),
        fine_share=fine_share(mine, config),
        fine_rival_share=fine_best,
        fine_margin=fine_margin(mine, fine_rivals, config),
        fine_rival_source=fine_name,
        sharpness=sharpness(mine),
        profile=mine,
        rival_profile=best_prof,
        rival_transform=best_T,
        rival_source=best_name,
        candidates=len(shortlist),
        distinct_rivals=len(profs),
        seconds=time.perf_counter() - t0,
        rivals=table,
        basin_share=max((fine_share(q, config) for _, q in near), default=0.0),
        basin_transform=basin_T,
    )


def fine_share(prof: dict, config: JudgeConfig) -> float:
    """Mean share of structure points within the `fine_scales` smallest scales, both directions:
    where a right pose stands out (chance alignments gather points only at the wide scales)."""
    k = config.fine_scales
    return float(np.mean(prof["structure_st"][:k] + prof["structure_ts"][:k]))


def fine_margin(prof: dict, rivals: list[dict], config: JudgeConfig) -> float:
    """1 - the best rival's fine share / the pose's (1 without rivals, -1 when the pose has none)."""
    mine = fine_share(prof, config)
    best = max((fine_share(r, config) for r in rivals), default=0.0)
    return 1.0 - best / mine if mine > 0 else -1.0


def confidence(prof: dict, rivals: list[dict], config: JudgeConfig) -> float:
    """The judge's confidence in pose `prof` over the distinct `rivals` (profiles), 0-1: its fine
    margin, from the margin chance alignments reach (0) to `full_margin` (1)."""
    m = fine_margin(prof, rivals, config)
    return float(
        np.clip((m - config.chance_margin) / (config.full_margin - config.chance_margin), 0, 1)
    )


def sharpness(prof: dict) -> float:
    """Share within the smallest scale over share within the largest, structure points, both
    directions: near 1 when the clouds coincide, low when they only come close by chance."""
    near = prof["structure_st"][0] + prof["structure_ts"][0]
    far = prof["structure_st"][-1] + prof["structure_ts"][-1]
    return float(near / far) if far > 0 else 0.0


def verify_stored(
    src, tgt, T: np.ndarray, A: np.ndarray, config: JudgeConfig, memo: PairMemo | None = None
) -> dict:
    """Does the stored pose T (source local -> target local) hold? A, the fine ICP from it, must
    barely move it and fit sharply (`sharpness`) with at least `min_score`. Returns the figures and
    `verified`; `failed` names the checks that did not pass."""
    memo = memo or PairMemo()
    deg, m = separation(A, T, centre(src, config, memo.source))
    prof = profile(src, tgt, A, config, memo)
    sharp = sharpness(prof)
    checks = {
        "correction": deg <= config.stored_max_correction_deg
        and m <= config.stored_max_correction_m,
        "sharpness": sharp >= config.stored_min_sharpness,
        "score": prof["score"] >= config.min_score,
    }
    return {
        "verified": all(checks.values()),
        "failed": [k for k, ok in checks.items() if not ok],
        "correction_deg": deg,
        "correction_m": m,
        "sharpness": sharp,
        "score": prof["score"],
        "profile": prof,
    }

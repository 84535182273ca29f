"""ForestAlign pairwise registration (paper Algorithm 1) as one function over short stages.

prepare (voxel, normals, levels) -> match levels (eq. 3) -> incremental ICP from the least
complex level, adding levels -> final ICP on everything at delta -> quality + information.
All geometry runs in local frames; the result is converted to the files' own coordinates.
"""

from __future__ import annotations

import json
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from plotmosaic import __version__
from plotmosaic.align import judge as judge_mod
from plotmosaic.align import scene
from plotmosaic.align.coarse import coarse_align
from plotmosaic.align.complexity import match_levels
from plotmosaic.align.figures import save_levels as write_levels
from plotmosaic.align.icp import Mirror, evaluate, information_matrix, point_to_plane_icp
from plotmosaic.align.prepare import PreparedCloud, prepare_cloud
from plotmosaic.align.sampling import sample
from plotmosaic.config.align import KINDS, AlignConfig, IcpStage, default_levels
from plotmosaic.config.judge import JudgeConfig
from plotmosaic.errors import InputError, RegistrationFailed
from plotmosaic.io.atomic import write_text_atomic
from plotmosaic.io.frame import inverse, rotation_deg, to_global_transform, to_local_transform
from plotmosaic.io.las import PointCloud, read_cloud
from plotmosaic.parallel import both

METHOD = "forestalign"


@dataclass
class PairResult:
    transform: np.ndarray  # 4x4, source file coordinates -> target file coordinates
    fitness: float
    inlier_rmse: float
    overlap: float
    information: np.ndarray  # 6x6, xi = (wx, wy, wz, vx, vy, vz) on the right of `transform`
    levels: dict  # {"source": [...], "target": [...], "matching": {s: t}, "steps": [...]}
    seconds: float
    source_kind: str = "tls"
    target_kind: str = "tls"
    source_offset: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    target_offset: list = field(default_factory=lambda: [0.0, 0.0, 0.0])
    sigma: float = float("nan")  # point-to-plane residual std behind `information`
    coarse: dict | None = None
    confidence: float | None = None  # the judge's: margin over the best distinct rival pose, 0-1
    judge: dict | None = None  # the judge's profile figures of this pose and of its best rival
    timings: dict = field(default_factory=dict)
    config: dict = field(default_factory=dict)
    method: str = METHOD
    version: str = __version__
    source_path: str | None = (
        None  # the two files, when registered from files (`plotmosaic report RESULT.json`)
    )
    target_path: str | None = None

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "version": self.version,
            "transform": np.asarray(self.transform, dtype=float).tolist(),
            "fitness": self.fitness,
            "inlier_rmse": self.inlier_rmse,
            "overlap": self.overlap,
            "information": np.asarray(self.information, dtype=float).tolist(),
            "sigma": self.sigma,
            "levels": self.levels,
            "seconds": self.seconds,
            "timings": self.timings,
            "source_kind": self.source_kind,
            "target_kind": self.target_kind,
            "source_offset": list(self.source_offset),
            "target_offset": list(self.target_offset),
            "confidence": self.confidence,
            "judge": self.judge,
            "coarse": self.coarse,
            "config": self.config,
            "source_path": self.source_path,
            "target_path": self.target_path,
        }

    @classmethod
    def from_dict(cls, d: dict) -> PairResult:
        return cls(
            transform=np.asarray(d["transform"], dtype=float),
            fitness=float(d["fitness"]),
            inlier_rmse=float(d["inlier_rmse"]),
            overlap=float(d["overlap"]),
            information=np.asarray(d["information"], dtype=float),
            levels=d.get("levels", {}),
            seconds=float(d.get("seconds", 0.0)),
            source_kind=d.get("source_kind", "tls"),
            target_kind=d.get("target_kind", "tls"),
            source_offset=d.get("source_offset", [0.0, 0.0, 0.0]),
            target_offset=d.get("target_offset", [0.0, 0.0, 0.0]),
            sigma=float(
                d.get("sigma", float("nan")) if d.get("sigma") is not None else float("nan")
            ),
            coarse=d.get("coarse"),
            confidence=d.get("confidence"),
            judge=d.get("judge"),  # absent from results cached before the judge
            timings=d.get("timings", {}),
            config=d.get("config", {}),
            method=d.get("method", METHOD),
            version=d.get("version", __version__),
            source_path=d.get("source_path"),
            target_path=d.get("target_path"),
        )

    def save(self, path: str | Path) -> Path:
        return write_text_atomic(path, json.dumps(self.to_dict(), indent=1))

    @classmethod
    def load(cls, path: str | Path) -> PairResult:
        return cls.from_dict(json.loads(Path(path).read_text()))


def _kind(kind: str, which: str) -> str:
    k = str(kind).lower()
    if k not in KINDS:
        raise InputError(f"{which} kind {kind!r} not one of {', '.join(KINDS)}")
    return k


def _level_table(p: PreparedCloud, matching: dict[int, int], as_source: bool) -> list[dict]:
    inv = {t: s for s, t in matching.items()}
    rows = []
    for st in p.level_stats:
        lv = st["level"]
        matched = matching.get(lv) if as_source else inv.get(lv)
        rows.append({**st, "matched": matched})
    return rows


def incremental_steps(matching: dict[int, int]) -> list[tuple[list[int], list[int]]]:
    """Cumulative (source levels, target levels) per step, least complex source level first."""
    steps, src, tgt = [], [], []
    for s in sorted(matching):
        src.append(s)
        tgt.append(matching[s])
        steps.append((list(src), list(tgt)))
    return steps


def global_search(src: PreparedCloud, tgt: PreparedCloud, config: AlignConfig, seed: int):
    """The coarse stage from anywhere (no prior), remembered per pair: the default path's pose and the
    rivals of a local result (--no-coarse, --init) are the same search."""
    key = (config.coarse.model_dump_json(exclude={"enabled"}), seed)
    memo = src.__dict__.get("_global_search")
    if memo is None or memo[0]() is not tgt or memo[1] != key:
        # one pair kept, the target by weak reference: a cache of prepared clouds stays the only owner
        memo = (weakref.ref(tgt), key, coarse_align(src, tgt, config.coarse, seed, prior=None))
        src.__dict__["_global_search"] = memo
    return memo[2]


def _candidates(hypotheses: list[dict], start: np.ndarray) -> list[tuple[np.ndarray, str]]:
    """Rival poses: every hypothesis (refined ones first, by score), then the start as handed over."""
    order = sorted(
        range(len(hypotheses)),
        key=lambda i: (
            not hypotheses[i].get("refined", False),
            -float(hypotheses[i].get("score") or 0.0),
        ),
    )
    out = [
        (
            np.asarray(hypotheses[i]["transform"], dtype=float),
            f"{hypotheses[i].get('generator', 'coarse')} hypothesis {i}",
        )
        for i in order
    ]
    return out + [(start, "start")]


def _fine_schedule(src: PreparedCloud, tgt: PreparedCloud, config: AlignConfig):
    """(stages, Tukey floor) of the final ICP: `final_schedule`, then a tight polish stage
    (final_polish_*) with a narrower kernel: a 10 cm last stage with a 10 cm kernel leaves TLS pairs
    0.03 deg off in yaw, and pairs the near half of a stem or branch seen by one scanner with the
    other half seen by the other scanner, which pulls every baseline short (~1 cm per 18 m pair on
    the `large` preset). Between two terrestrial scans (`final_polish_fixed_kinds`) the polish is
    the same however sparse they are (their plane residuals are range noise, millimetres); with an
    airborne or mobile cloud it is stretched by the judge's scale factor and left out where it would
    be looser than the last stage."""
    fixed = (
        src.kind in config.final_polish_fixed_kinds and tgt.kind in config.final_polish_fixed_kinds
    )
    f = 1.0 if fixed else judge_mod.scale_factor(src, tgt, config.judge)
    d = config.final_polish_distance * f
    stages = list(config.final_schedule)
    if config.final_polish_iterations == 0 or not stages or d >= stages[-1].max_distance:
        return stages, config.robust_kernel
    stages.append(IcpStage(max_distance=d, iterations=config.final_polish_iterations))
    return stages, min(config.robust_kernel, config.final_polish_kernel * f)


def final_icp(src: PreparedCloud, tgt: PreparedCloud, T: np.ndarray, config: AlignConfig):
    """Final point-to-plane ICP with the planes of the denser cloud, or of both for two clouds of
    `final_symmetric_kinds` of comparable density (neither side `final_reverse_ratio` sparser), with
    the side test where both scanners are known; (T, p, q, n) with the last forward correspondences
    in local coordinates: source points p, target points q, target-side normals n."""
    s_sp, t_sp = judge_mod.spacing(src, config.judge), judge_mod.spacing(tgt, config.judge)
    schedule, kernel = _fine_schedule(src, tgt, config)
    # both scanners known (align/viewpoint.py): matches between the two faces of a stem are left out
    views = (
        None if src.viewpoint is None or tgt.viewpoint is None else (src.viewpoint, tgt.viewpoint)
    )
    if t_sp > config.final_reverse_ratio * s_sp:
        # sparse target (ALS under a drone or ground scan): register it onto the dense source's planes
        res = point_to_plane_icp(
            tgt.fine_points,
            src.points,
            src.target_normals,
            inverse(T),
            schedule,
            tree=src.tree,
            kernel_floor=kernel,
            tol=config.final_tol,
            viewpoints=None if views is None else views[::-1],
        )
        T = inverse(res.T)
        p, q = src.points[res.target_index], tgt.fine_points[res.source_index]
        n = (
            src.target_normals(res.target_index) @ T[:3, :3].T
        )  # the same planes, in target coordinates
        return T, p, q, n, res.iterations, True
    symmetric = (
        src.kind in config.final_symmetric_kinds and tgt.kind in config.final_symmetric_kinds
    )
    res = point_to_plane_icp(
        src.fine_points,
        tgt.points,
        tgt.target_normals,
        T,
        schedule,
        tree=tgt.tree,
        kernel_floor=kernel,
        tol=config.final_tol,
        mirror=Mirror(tgt.fine_points, src.points, src.tree, src.target_normals)
        if symmetric
        else None,
        viewpoints=views,
    )
    return (
        res.T,
        src.fine_points[res.source_index],
        tgt.points[res.target_index],
        tgt.target_normals(res.target_index),
        res.iterations,
        False,
    )


def register_prepared(
    src: PreparedCloud,
    tgt: PreparedCloud,
    config: AlignConfig,
    init: np.ndarray | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    stored: bool = False,
) -> PairResult:
    """Registration of two prepared clouds; `init` (source file -> target file) is a prior for the
    coarse stage, or the start itself with the coarse stage off. `stored`: `init` is a pose stored
    in the scan files (E57 `use_pose`): when it verifies (judge.verify_stored) the search is skipped,
    else it is a prior like any other."""
    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    if config.judge.enabled:  # the judge refuses a scene that is not a forest: before the search
        scene.check(src, tgt, config.judge)
    coarse = None
    T = to_local_transform(
        np.eye(4) if init is None else np.asarray(init, dtype=float), src.frame, tgt.frame
    )
    T_start = T.copy()
    hypotheses: list[dict] = []
    check, fine = None, None
    if stored and init is not None and config.judge.enabled:
        # the fine stage from the stored pose is the check: a right one barely moves and fits sharply
        say("verifying the stored pose")
        t = time.perf_counter()
        fine = final_icp(src, tgt, T, config)
        check = judge_mod.verify_stored(src, tgt, T, fine[0], config.judge)
        check["seconds"] = time.perf_counter() - t
    skipped = check is not None and check["verified"]
    if skipped:
        # no search, so no rivals either; the level stage neither (the fine ICP is done)
        coarse = {"skipped": "stored pose verified", "stored_pose": _stored_record(check)}
    elif config.coarse.enabled:
        # with an initial guess the coarse stage searches around it and keeps it if it verifies best:
        # ICP alone from a guess 10 deg / 2 m off can settle in a wrong minimum that still looks fit
        say("coarse alignment")
        if init is not None:
            cres = coarse_align(src, tgt, config.coarse, seed, prior=T)
        else:
            cres = global_search(src, tgt, config, seed)
        T = np.asarray(cres.transform, dtype=float)
        coarse = cres.to_dict()
        hypotheses = list(cres.hypotheses)
        if check is not None:
            coarse["stored_pose"] = _stored_record(check)
    if (
        config.judge.enabled
        and config.judge.global_rivals
        and not skipped
        and (init is not None or not config.coarse.enabled)
    ):
        # a local result (from --init or --no-coarse) has no rivals of its own: the global search gives them
        say("searching for rival poses")
        hypotheses += global_search(src, tgt, config, seed).hypotheses
    T_init = T.copy()
    t_coarse = time.perf_counter()

    rng = np.random.default_rng(seed)
    if skipped:
        steps, start_fit, level_fit, reverted = [], None, None, False
        matching = _matching(src, tgt)
        t_levels = time.perf_counter()
        T, p, q, n, iterations, reverse = fine
    else:
        T, steps, start_fit, level_fit, reverted, matching = _level_stage(
            src, tgt, config, T, coarse is not None, rng
        )
        t_levels = time.perf_counter()
        say("final ICP")
        T, p, q, n, iterations, reverse = final_icp(src, tgt, T, config)
    t_final = time.perf_counter()

    verdict = None
    if config.judge.enabled:
        say("judging the pose against its rivals")
        candidates = _candidates(hypotheses, T_start)
        verdict = judge_mod.judge(src, tgt, T, candidates, config.judge)
        if not skipped:
            T, p, q, n, iterations, reverse, verdict = _recover(
                src, tgt, config, candidates, (T, p, q, n, iterations, reverse), verdict, say
            )
    t_judge = time.perf_counter()

    say("quality")
    # fitness / RMSE / overlap on seeded subsamples of the query side: same figures to ~0.1 %, a
    # fraction of the nearest-neighbour queries on 8M-point scans
    s_q = src.points[sample(len(src.points), config.quality_max_points, rng)]
    t_q = tgt.points[sample(len(tgt.points), config.quality_max_points, rng)]
    fitness, rmse, n_s = evaluate(s_q, tgt.tree, T, config.quality_distance)
    _, _, n_t = evaluate(t_q, src.tree, np.linalg.inv(T), config.quality_distance)
    ov = float((n_s + n_t) / max(1, len(s_q) + len(t_q)))
    # information from the final point-to-plane problem (its last correspondences), in file coordinates
    T_file = to_global_transform(T, src.frame, tgt.frame)
    if len(p):
        info, sigma = information_matrix(src.frame.to_global(p), tgt.frame.to_global(q), n, T_file)
    else:
        info, sigma = np.zeros((6, 6)), float("nan")
    t_end = time.perf_counter()

    moved = T @ np.linalg.inv(T_init)
    result = PairResult(
        transform=T_file,
        fitness=fitness,
        inlier_rmse=rmse,
        overlap=ov,
        information=info,
        sigma=sigma,
        levels={
            "source": _level_table(src, matching, True),
            "target": _level_table(tgt, matching, False),
            "matching": {str(k): v for k, v in matching.items()},
            "steps": steps,
            "fitness_before": start_fit,
            "fitness_after": level_fit,
            "reverted": reverted,
        },
        seconds=t_end - t0,
        source_kind=src.kind,
        target_kind=tgt.kind,
        source_offset=[float(v) for v in src.frame.offset],
        target_offset=[float(v) for v in tgt.frame.offset],
        coarse=coarse,
        confidence=None if verdict is None else verdict.confidence,
        judge=None if verdict is None else _judge_record(verdict, src, tgt),
        timings={
            **({"coarse_skipped": "stored pose verified"} if skipped else {}),
            "coarse": t_coarse - t0,
            "levels_icp": t_levels - t_coarse,
            "final_icp": t_final - t_levels,
            "final_iterations": iterations,
            "final_planes": "source" if reverse else "target",
            "judge": t_judge - t_final,
            "quality": t_end - t_judge,
            "correction_deg": rotation_deg(moved),
            "correction_m": float(np.linalg.norm(moved[:3, 3])),
        },
        config=config.model_dump(),
    )
    check_quality(result, config, local=not config.coarse.enabled or init is not None)
    return result


def _recover(src, tgt, config: AlignConfig, candidates, fine, verdict, say):
    """At most one retry when the judge found a better pose than the final ICP's: a distinct rival
    that scores better (only with the coarse stage on: after --no-coarse a distinct pose is not the
    local result asked for, the refusal says so), or a sharper end of the pose's own basin (every
    route: it lies within the basin radius, a local correction). The final ICP runs from it and the
    judge again, the first pose among the candidates; the second pose is kept only if its verdict is
    better (score when a rival won, confidence otherwise), else the first and its verdict stand.
    Returns (T, p, q, n, iterations, reverse, verdict)."""
    rival = verdict.rival_better and config.coarse.enabled
    better = verdict.rival_transform if rival else verdict.basin_transform
    if better is None:
        return (*fine, verdict)
    say("final ICP from a better rival" if rival else "final ICP from the pose's sharper basin")
    second_fine = final_icp(src, tgt, better, config)
    T2 = second_fine[0]
    second = judge_mod.judge(src, tgt, T2, candidates + [(fine[0], "first pose")], config.judge)
    keep = second.score > verdict.score if rival else second.confidence > verdict.confidence
    return (*second_fine, second) if keep else (*fine, verdict)


def blunt_fit(sharp: float | None, confidence: float | None, jc: JudgeConfig) -> str | None:
    """Why a pose fits too bluntly to be accepted, or None. Sharp (>= min_sharpness): fine. Between
    blunt_min_sharpness and min_sharpness (noisy sensors, e.g. MLS onto a drone cloud): only a clear
    winner over every distinct rival. Below: chance. Results cached before sharpness: no figure."""
    if sharp is None or sharp >= jc.min_sharpness:
        return None
    conf = -1.0 if confidence is None else confidence
    if sharp >= jc.blunt_min_sharpness:
        if conf >= jc.blunt_min_confidence:
            return None
        return (
            f"blunt fit: sharpness {sharp:.3f} < {jc.min_sharpness} and confidence {conf:.2f} <"
            f" {jc.blunt_min_confidence} (a blunt fit must beat every distinct rival clearly)"
        )
    return (
        f"blunt fit: sharpness {sharp:.3f} < {jc.blunt_min_sharpness} (points come close"
        " to the other cloud only by chance at this pose)"
    )


def _stored_record(check: dict) -> dict:
    """verify_stored's figures for PairResult.coarse (no transform: the result has it)."""
    keep = ("verified", "failed", "correction_deg", "correction_m", "sharpness", "score", "seconds")
    return {k: check[k] for k in keep}


def _judge_record(verdict, src: PreparedCloud, tgt: PreparedCloud) -> dict:
    """The judge's figures for PairResult, the rival's transform in file coordinates."""
    d = verdict.to_dict()
    if verdict.rival_transform is not None:
        d["rival_transform"] = to_global_transform(
            verdict.rival_transform, src.frame, tgt.frame
        ).tolist()
    return d


def _matching(src: PreparedCloud, tgt: PreparedCloud) -> dict[int, int]:
    return match_levels(
        [s["match_value"] for s in src.level_stats],
        [s["match_value"] for s in tgt.level_stats],
        compress=False,
    )


def _level_stage(
    src: PreparedCloud,
    tgt: PreparedCloud,
    config: AlignConfig,
    T: np.ndarray,
    after_coarse: bool,
    rng: np.random.Generator,
):
    """Incremental ICP over the matched levels; reverted when it ends worse than it started."""
    T_init = T.copy()
    matching = _matching(src, tgt)
    steps = []
    for j, (ls, lt) in enumerate(incremental_steps(matching)):
        sp, _ = src.subset(ls)
        tp, tn = tgt.subset(lt)
        if len(sp) < 10 or len(tp) < 10:
            continue
        sp = sp[sample(len(sp), config.level_max_source_points, rng)]
        schedule = config.level_schedule[min(j, len(config.level_schedule) - 1)]
        if (
            after_coarse
        ):  # a verified coarse pose is within decimetres: the widest stages only cost time
            schedule = [
                st for st in schedule if st.max_distance <= config.level_max_distance_after_coarse
            ] or schedule[-1:]
        res = point_to_plane_icp(
            sp, tp, tn, T, schedule, min_eig_ratio=config.min_eig_ratio, tol=config.level_tol
        )
        T = res.T
        steps.append(
            {
                "source_levels": ls,
                "target_levels": lt,
                "source_points": len(sp),
                "target_points": len(tp),
                "fitness": res.fitness,
                "rmse": res.rmse,
                "constrained_dof": res.rank,
                "iterations": res.iterations,
            }
        )
    # never leave the level stage worse than it started: from a verified coarse pose, levels that
    # are not what they should be (plain vMF on dense scans mixes stems and foliage) can slide away
    probe = src.level_points[sample(len(src.level_points), config.level_max_source_points, rng)]
    start_fit = evaluate(probe, tgt.tree, T_init, config.quality_distance)[0]
    level_fit = evaluate(probe, tgt.tree, T, config.quality_distance)[0]
    reverted = bool(steps) and level_fit < config.level_keep_ratio * start_fit
    if reverted:
        T = T_init.copy()
    return T, steps, start_fit, level_fit, reverted, matching


def check_quality(result: PairResult, config: AlignConfig, local: bool = False) -> None:
    """Refuse a transform the figures do not support (exit 3), never return it silently.

    `local`: the pose came from a start (--no-coarse or --init), which the message names when a rival wins.
    """
    problems = []
    if not np.isfinite(result.transform).all():
        problems.append("transform is not finite")
    if result.fitness < config.min_fitness:
        problems.append(f"fitness {result.fitness:.3f} < {config.min_fitness}")
    if result.overlap < config.min_overlap:
        problems.append(f"overlap {result.overlap:.3f} < {config.min_overlap}")
    if not result.inlier_rmse <= config.max_inlier_rmse:
        problems.append(f"inlier RMSE {result.inlier_rmse:.3f} m > {config.max_inlier_rmse} m")
    j = result.judge
    if j is not None:
        if j["score"] < config.judge.min_score:
            problems.append(
                f"judge score {j['score']:.3f} < {config.judge.min_score} (the clouds hardly fit anywhere)"
            )
        blunt = blunt_fit(j.get("sharpness"), result.confidence, config.judge)
        if blunt:
            problems.append(blunt)
        if (
            j["margin"] <= 0
        ):  # also with min_confidence 0 (register-plot): this pose is not the best one found
            hint = ": rerun without --no-coarse" if local and not config.coarse.enabled else ""
            problems.append(
                f"a distinct pose fits as well or better (judge score {j['rival_score']:.3f}"
                f" against {j['score']:.3f}, from {j['rival_source']}){hint}"
            )
        elif result.confidence is not None and result.confidence < config.min_confidence:
            fine = ""
            if "fine_share" in j:  # results cached before the fine margin lack it
                fine = (
                    f"; share within {j['profile']['scales'][0]:.2f} m {j['fine_share']:.3f},"
                    f" rival {j['fine_rival_share']:.3f} from {j.get('fine_rival_source')}"
                )
            problems.append(
                f"ambiguous: a distinct pose fits almost as well at the finest scale (confidence"
                f" {result.confidence:.2f} < {config.min_confidence}{fine}; judge score"
                f" {j['score']:.3f}, rival {j['rival_score']:.3f})"
            )
    if problems:
        err = RegistrationFailed(
            "pair cannot be registered: "
            + "; ".join(problems)
            + f" (fitness {result.fitness:.3f}, overlap {result.overlap:.3f}, inlier RMSE {result.inlier_rmse:.3f} m"
            f" at {config.quality_distance} m)"
        )
        err.result = result
        raise err


def prepare_pair(
    source: PointCloud,
    target: PointCloud,
    source_kind: str,
    target_kind: str,
    levels_source: int,
    levels_target: int,
    config: AlignConfig,
    seed: int = 0,
) -> tuple[PreparedCloud, PreparedCloud]:
    """Both clouds prepared at once (source with `seed`, target with `seed + 1`)."""
    return both(
        lambda job: prepare_cloud(*job),
        (source, source_kind, levels_source, config, seed, "source"),
        (target, target_kind, levels_target, config, seed + 1, "target"),
    )


def align_clouds(
    source: PointCloud,
    target: PointCloud,
    source_kind: str = "tls",
    target_kind: str = "tls",
    config: AlignConfig | None = None,
    init: np.ndarray | None = None,
    levels_source: int | None = None,
    levels_target: int | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    save_levels: Path | None = None,
) -> PairResult:
    """Register `source` onto `target`; the result maps source file coordinates to target file coordinates.

    `save_levels`: a folder for the levels as LAZ + PNG (written before ICP, so also on failure).
    """
    config = config or AlignConfig()
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    sk, tk = _kind(source_kind, "source"), _kind(target_kind, "target")
    say("preparing source and target")
    src, tgt = prepare_pair(
        source,
        target,
        sk,
        tk,
        levels_source or default_levels(sk),
        levels_target or default_levels(tk),
        config,
        seed,
    )
    if save_levels is not None:
        say("saving levels")
        write_levels(save_levels, src, tgt, source.crs, target.crs)
    t1 = time.perf_counter()
    result = register_prepared(src, tgt, config, init, seed, progress)
    result.timings = {
        "prepare": t1 - t0,
        "prepare_source": src.seconds,
        "prepare_target": tgt.seconds,
        **result.timings,
    }
    result.seconds = time.perf_counter() - t0
    return result


def align_files(
    source_path,
    target_path,
    source_kind: str = "tls",
    target_kind: str = "tls",
    config: AlignConfig | None = None,
    init: np.ndarray | None = None,
    levels_source: int | None = None,
    levels_target: int | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    save_levels: Path | None = None,
) -> PairResult:
    """`align_clouds` on two LAS/LAZ files (coordinates only)."""
    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    say("reading source and target")
    source, target = both(lambda path: read_cloud(path, attributes=False), source_path, target_path)
    t_read = time.perf_counter() - t0
    result = align_clouds(
        source,
        target,
        source_kind,
        target_kind,
        config,
        init,
        levels_source,
        levels_target,
        seed,
        progress,
        save_levels,
    )
    result.timings = {"read": t_read, **result.timings}
    result.seconds = time.perf_counter() - t0
    result.source_path, result.target_path = (
        str(Path(source_path).resolve()),
        str(Path(target_path).resolve()),
    )
    return result

"""One pair's registration, top down (paper Algorithm 1 with the judge around it): verify a stored
pose, search (coarse stage, or the rivals of a local start), level stage, final ICP, judge, quality,
floors. All geometry runs in local frames; the result is in the files' own coordinates."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum

import numpy as np

from plotmosaic.align import judge as judge_mod
from plotmosaic.align import scene
from plotmosaic.align.coarse import CoarseResult, coarse_align
from plotmosaic.align.coarse.clouds import AIRBORNE
from plotmosaic.align.coarse.hypothesis import Hypothesis
from plotmosaic.align.fine import FineResult, final_icp
from plotmosaic.align.floors import check_quality
from plotmosaic.align.freespace import FreeSpace
from plotmosaic.align.judge import Candidate, Verdict
from plotmosaic.align.level_icp import LevelResult, level_stage, levels_record, no_level_stage
from plotmosaic.align.memo import PairMemo
from plotmosaic.align.prepare import PreparedCloud
from plotmosaic.align.quality import Quality, measure
from plotmosaic.align.result import PairResult
from plotmosaic.config.align import AlignConfig
from plotmosaic.errors import RegistrationFailed
from plotmosaic.io.frame import rotation_deg, to_global_transform, to_local_transform

Say = Callable[[str], None]


class Start(str, Enum):
    """How a pair's `init` is used."""

    PRIOR = "prior"  # a prior of the coarse stage (or the start itself with it off)
    STORED = "stored"  # verified first (a pose stored in the scans); searched when it does not hold
    ONLY = "only"  # verified, refused when it does not hold (a placement's prior: thin pairs are
    # left to the scan's map, where a search could find no more)


@dataclass(frozen=True, kw_only=True, eq=False)
class PairContext:
    """What every step of one pair's registration works on: the two clouds, the settings, the
    seed, where progress goes, and what the pair computes once (its memo, owned by the pair)."""

    src: PreparedCloud
    tgt: PreparedCloud
    config: AlignConfig
    seed: int
    say: Say
    memo: PairMemo

    @property
    def space(self) -> FreeSpace | None:
        return free_space(self.src, self.tgt, self.config, self.memo)


def free_space(
    src: PreparedCloud, tgt: PreparedCloud, config: AlignConfig, memo: PairMemo
) -> FreeSpace | None:
    """The pair's free space where a scanner is known; none with an airborne cloud (its strips see
    the canopy from above, at another season: its returns are not the scanner's view)."""
    if src.kind in AIRBORNE or tgt.kind in AIRBORNE:
        return None
    return FreeSpace.of_pair(src, tgt, config.free_space, memo)


def register_prepared(
    src: PreparedCloud,
    tgt: PreparedCloud,
    config: AlignConfig,
    init: np.ndarray | None = None,
    seed: int = 0,
    progress: Say | None = None,
    start: Start = Start.PRIOR,
    memo: PairMemo | None = None,
) -> PairResult:
    """Registration of two prepared clouds; `init` (source file -> target file) is used as `start`
    says: a prior for the coarse stage (or the start itself with the coarse stage off), or a pose
    to verify first (judge.verify_stored: the search is skipped when it holds; when it does not,
    a stored pose is a prior like any other and a placement's is refused). `memo`: what this pair
    computes once, kept by its owner across calls (a run registering a scan in several pairs)."""
    pair = PairContext(
        src=src, tgt=tgt, config=config, seed=seed, say=progress or _silent, memo=memo or PairMemo()
    )
    clock = _Clock()
    if config.judge.enabled:  # the judge refuses a scene that is not a forest: before the search
        scene.check(src, tgt, config.judge, pair.memo)
    T = to_local_transform(
        np.eye(4) if init is None else np.asarray(init, dtype=float), src.frame, tgt.frame
    )
    handed = T.copy()
    check = None
    if start is not Start.PRIOR and init is not None and config.judge.enabled:
        check = verify_stored_pose(pair, T)
        if start is Start.ONLY and not check.verified:
            raise RegistrationFailed(
                "pair cannot be registered: not verified at its prior (failed "
                + ", ".join(check.record["failed"])
                + "): too thin a pair, left to the scans' maps"
            )
    search = search_pose(pair, T, init is not None, check)
    clock.mark("coarse")
    rng = np.random.default_rng(seed)
    if search.skipped:  # the stored pose's fine ICP stands: no level stage, no second fine stage
        levels = no_level_stage(src, tgt, search.T)
        clock.mark("levels_icp")
        fine = check.fine
    else:
        levels = level_stage(src, tgt, config, search.T, search.coarse is not None, rng)
        clock.mark("levels_icp")
        pair.say("final ICP")
        fine = final_icp(src, tgt, levels.T, config, pair.memo)
    clock.mark("final_icp")
    judged = judge_pose(pair, fine, handed, search)
    clock.mark("judge")
    pair.say("quality")
    quality = measure(src, tgt, config, judged.fine, rng)
    clock.mark("quality")
    result = pair_result(pair, search, levels, judged, quality, clock)
    check_quality(result, config, local=not config.coarse.enabled or init is not None)
    return result


@dataclass(frozen=True, kw_only=True, eq=False)
class StoredCheck:
    """A stored pose checked: the fine ICP from it and whether it verified."""

    fine: FineResult
    verified: bool
    record: dict  # judge.StoredVerdict.record, PairResult.coarse["stored_pose"]


@dataclass(frozen=True, kw_only=True, eq=False)
class Search:
    """Where the level stage starts, and the hypotheses the judge weighs the pose against."""

    T: np.ndarray  # source local -> target local
    coarse: dict | None  # PairResult.coarse (None: the coarse stage did not run)
    hypotheses: tuple[Hypothesis, ...]
    skipped: bool  # a verified stored pose: no search and no level stage


@dataclass(frozen=True, kw_only=True, eq=False)
class Judged:
    """The pose the judge let stand, with its last fine stage, and its verdict."""

    fine: FineResult
    verdict: Verdict | None  # None: the judge is off


def verify_stored_pose(pair: PairContext, T: np.ndarray) -> StoredCheck:
    """The fine stage from the stored pose is the check: a right one barely moves and fits sharply."""
    src, tgt, config, memo = pair.src, pair.tgt, pair.config, pair.memo
    pair.say("verifying the stored pose")
    t = time.perf_counter()
    fine = final_icp(src, tgt, T, config, memo)
    check = judge_mod.verify_stored(src, tgt, T, fine.T, config.judge, memo)
    return StoredCheck(
        fine=fine, verified=check.verified, record=check.record(time.perf_counter() - t)
    )


def search_pose(
    pair: PairContext, T: np.ndarray, has_init: bool, check: StoredCheck | None
) -> Search:
    """The coarse stage, around `T` when a start was given, else from anywhere; nothing after a
    verified stored pose. A local result (--init, --no-coarse) takes its rivals from the global search."""
    src, tgt, config, seed, memo = pair.src, pair.tgt, pair.config, pair.seed, pair.memo
    skipped = check is not None and check.verified
    coarse, hypotheses = None, ()
    if skipped:
        # no search, so no rivals either; the level stage neither (the fine ICP is done)
        coarse = {"skipped": "stored pose verified", "stored_pose": check.record}
    elif config.coarse.enabled:
        # with an initial guess the coarse stage searches around it and keeps it if it verifies best:
        # ICP alone from a guess 10 deg / 2 m off can settle in a wrong minimum that still looks fit
        pair.say("coarse alignment")
        if has_init:
            cres = coarse_align(src, tgt, config.coarse, seed, prior=T, memo=memo, space=pair.space)
        else:
            cres = global_search(src, tgt, config, seed, memo)
        T = np.asarray(cres.transform, dtype=float)
        coarse = cres.to_dict()
        hypotheses = cres.hypotheses
        if check is not None:
            coarse["stored_pose"] = check.record
    rivals = config.judge.enabled and config.judge.global_rivals
    if rivals and not skipped and (has_init or not config.coarse.enabled):
        pair.say("searching for rival poses")
        hypotheses += global_search(src, tgt, config, seed, memo).hypotheses
    return Search(T=T, coarse=coarse, hypotheses=hypotheses, skipped=skipped)


def global_search(
    src: PreparedCloud,
    tgt: PreparedCloud,
    config: AlignConfig,
    seed: int,
    memo: PairMemo | None = None,
) -> CoarseResult:
    """The coarse stage from anywhere (no prior), kept in the pair's memo: the default path's pose
    and the rivals of a local result (--no-coarse, --init) are the same search."""
    memo = memo or PairMemo()
    key = (config.coarse.model_dump_json(exclude={"enabled"}), seed)
    space = free_space(src, tgt, config, memo)
    return memo.search.get(
        key,
        lambda: coarse_align(src, tgt, config.coarse, seed, prior=None, memo=memo, space=space),
    )


def judge_pose(pair: PairContext, fine: FineResult, start: np.ndarray, search: Search) -> Judged:
    """The judge's verdict on the pose against every hypothesis and the start; after a search, one
    retry from a better pose the judge found (`recover`)."""
    if not pair.config.judge.enabled:
        return Judged(fine=fine, verdict=None)
    pair.say("judging the pose against its rivals")
    candidates = _candidates(search.hypotheses, start)
    verdict = judge_mod.judge(
        pair.src, pair.tgt, fine.T, candidates, pair.config.judge, pair.memo, pair.space
    )
    if search.skipped:
        return Judged(fine=fine, verdict=verdict)
    judged = recover(pair, candidates, fine, verdict)
    return look_again(pair, candidates, judged)


def recover(
    pair: PairContext, candidates: list[Candidate], fine: FineResult, verdict: Verdict
) -> Judged:
    """At most one retry when the judge found a better pose than the final ICP's: a distinct rival
    that scores better (only with the coarse stage on: after --no-coarse a distinct pose is not the
    local result asked for, the refusal says so), or a sharper end of the pose's own basin (every
    route: it lies within the basin radius, a local correction). The final ICP runs from it and the
    judge again, the first pose among the candidates; the second pose is kept only if its verdict is
    better (score when a rival won, confidence otherwise), else the first and its verdict stand."""
    src, tgt, config, memo = pair.src, pair.tgt, pair.config, pair.memo
    rival = verdict.rival_better and config.coarse.enabled
    better = verdict.rival_transform if rival else verdict.basin_transform
    if better is None:
        return Judged(fine=fine, verdict=verdict)
    pair.say(
        "final ICP from a better rival" if rival else "final ICP from the pose's sharper basin"
    )
    second_fine = final_icp(src, tgt, better, config, memo)
    second = judge_mod.judge(
        src,
        tgt,
        second_fine.T,
        [*candidates, Candidate(T=fine.T, source="first pose")],
        config.judge,
        memo,
        pair.space,
    )
    keep = second.score > verdict.score if rival else second.confidence > verdict.confidence
    if keep:
        return Judged(fine=second_fine, verdict=second)
    return Judged(fine=fine, verdict=verdict)


def weak(verdict: Verdict, config: AlignConfig) -> bool:
    """Whether a verdict would be refused (the floors of check_quality on the judge's figures):
    beaten, below the judge's floor, blunt, or less confident than `min_confidence` (register-plot
    keeps an unsure pair as an edge its loops decide on: only a refusal is weak there)."""
    jc = config.judge
    blunt = verdict.sharpness < jc.blunt_min_sharpness or (
        verdict.sharpness < jc.min_sharpness and verdict.confidence < jc.blunt_min_confidence
    )
    return (
        verdict.margin <= 0
        or verdict.score < jc.min_score
        or blunt
        or verdict.confidence < config.min_confidence
    )


def look_again(pair: PairContext, candidates: list[Candidate], judged: Judged) -> Judged:
    """A verdict that would be refused gets a second look (judge.second_look): from each distinct
    candidate in turn, the level stage, the final ICP and the judge with its one retry, as the first
    pose had them (the retry's basin starts carry a pose a few degrees off onto the truth beside
    it); the first result that would not be refused and is `clear` replaces the first pose, else the
    first verdict stands. A look that comes back to a pose already weighed (the first pose, an
    earlier look's: `judge.same`) stops there: its verdict is known. The rivals are refined once
    for the pair (the memo): a look pays for its own ICPs."""
    src, tgt, config, memo = pair.src, pair.tgt, pair.config, pair.memo
    if not config.coarse.enabled or not weak(judged.verdict, config):
        return judged
    c = judge_mod.centre(src, config.judge, memo.source)
    starts = judge_mod.second_look(judged.fine.T, candidates, c, config.judge)
    pair.say(f"a second look from {len(starts)} other candidates")
    rivals = [*candidates, Candidate(T=judged.fine.T, source="first pose")]
    weighed = [judged.fine.T]

    def known(T: np.ndarray | None) -> bool:
        return T is not None and any(judge_mod.same(T, W, c, config.judge) for W in weighed)

    for A in starts:  # the first that holds: the most agreed-on candidates first
        rng = np.random.default_rng(0)
        level = level_stage(src, tgt, config, A, False, rng).T
        if known(level):
            continue
        fine = final_icp(src, tgt, level, config, memo)
        if known(fine.T):
            continue
        verdict = judge_mod.judge(src, tgt, fine.T, rivals, config.judge, memo, pair.space)
        weighed.append(fine.T)
        if verdict.rival_better and known(verdict.rival_transform):
            continue  # beaten by a pose already weighed: its retry would end there
        found = recover(pair, rivals, fine, verdict)
        weighed.append(found.fine.T)
        if not weak(found.verdict, config) and clear(found.verdict, config):
            return found
    return judged


def clear(verdict: Verdict, config: AlignConfig) -> bool:
    """Whether a second look's verdict stands: every look is one more chance for a chance alignment
    to pass, so a pose it finds must beat its rivals by `second_look_min_confidence`."""
    return verdict.confidence >= config.judge.second_look_min_confidence


def pair_result(
    pair: PairContext,
    search: Search,
    levels: LevelResult,
    judged: Judged,
    quality: Quality,
    clock: _Clock,
) -> PairResult:
    """Every step's figures gathered in a PairResult."""
    src, tgt = pair.src, pair.tgt
    fine, verdict, spans = judged.fine, judged.verdict, clock.spans
    moved = fine.T @ np.linalg.inv(search.T)
    return PairResult(
        transform=quality.transform,
        fitness=quality.fitness,
        fitness_reverse=quality.fitness_reverse,
        inlier_rmse=quality.rmse,
        overlap=quality.overlap,
        information=quality.information,
        sigma=quality.sigma,
        levels=levels_record(src, tgt, levels),
        seconds=clock.total,
        source_kind=src.kind,
        target_kind=tgt.kind,
        source_offset=[float(v) for v in src.frame.offset],
        target_offset=[float(v) for v in tgt.frame.offset],
        coarse=search.coarse,
        confidence=None if verdict is None else verdict.confidence,
        judge=None if verdict is None else _judge_record(verdict, src, tgt),
        timings=dict(spans),
        steps={
            **({"coarse_skipped": "stored pose verified"} if search.skipped else {}),
            "final_iterations": fine.iterations,
            "final_planes": "source" if fine.reverse else "target",
            "correction_deg": rotation_deg(moved),
            "correction_m": float(np.linalg.norm(moved[:3, 3])),
        },
        config=pair.config.model_dump(),
    )


class _Clock:
    """Seconds each step took, from the registration's start."""

    def __init__(self) -> None:
        self.start = self.last = time.perf_counter()
        self.spans: dict[str, float] = {}

    def mark(self, step: str) -> None:
        now = time.perf_counter()
        self.spans[step], self.last = now - self.last, now

    @property
    def total(self) -> float:
        return self.last - self.start


def _silent(msg: str) -> None:
    pass


def _candidates(hypotheses: tuple[Hypothesis, ...], start: np.ndarray) -> list[Candidate]:
    """Rival poses: every hypothesis (refined ones first, by score), then the start as handed over."""
    order = sorted(
        range(len(hypotheses)),
        key=lambda i: (
            not hypotheses[i].refined,
            hypotheses[i].through,
            -float(hypotheses[i].score or 0.0),
        ),
    )
    out = [
        Candidate(
            T=np.asarray(hypotheses[i].T, dtype=float),
            source=f"{hypotheses[i].generator} hypothesis {i}",
        )
        for i in order
    ]
    return [*out, Candidate(T=start, source="start")]


def _judge_record(verdict: Verdict, src: PreparedCloud, tgt: PreparedCloud) -> dict:
    """The judge's figures for PairResult, the rival's transform in file coordinates."""
    d = verdict.to_dict()
    if verdict.rival_transform is not None:
        d["rival_transform"] = to_global_transform(
            verdict.rival_transform, src.frame, tgt.frame
        ).tolist()
    return d

"""The verdict on a pose: its profile against the distinct rivals' and its basin's, the margins and
the confidence; and the check of a pose stored in the scan files.

Every transform here maps source-local to target-local coordinates.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from plotmosaic.align import scene
from plotmosaic.align.freespace import FreeSpace
from plotmosaic.align.judge.profile import (
    Profile,
    agreement,
    centre,
    confidence,
    distinct,
    fine_margin,
    fine_share,
    profile,
    separation,
    sharpness,
)
from plotmosaic.align.judge.rivals import basin, refined, sharper_neighbours
from plotmosaic.align.memo import PairMemo
from plotmosaic.align.spacing import samples
from plotmosaic.config.judge import JudgeConfig


@dataclass(frozen=True, kw_only=True, eq=False)
class Verdict:
    """The judge's figures on a pose (source local -> target local) and on its best rivals."""

    score: float  # judge score of the pose
    rival_score: float  # of the best distinct rival as sharp as blunt_min_sharpness (0: none)
    margin: float  # 1 - rival_score / score (negative: a rival fits better)
    confidence: float  # from the fine margin (`confidence`), 0-1
    fine_share: float  # of the pose (`fine_share`)
    fine_rival_share: float  # the highest of the distinct rivals' (0 when none)
    fine_margin: float  # 1 - fine_rival_share / fine_share
    fine_rival_source: str | None
    sharpness: float  # of the pose (`sharpness`): near 1 when the clouds coincide, low by chance
    profile: Profile
    rival_profile: Profile | None
    rival_transform: np.ndarray | None  # source local -> target local
    rival_source: str | None
    candidates: int  # rivals refined and scored
    distinct_rivals: int
    seconds: float = 0.0
    rivals: list[dict] = field(default_factory=list)
    basin_share: float = 0.0  # highest fine share a basin start ended with (0 when none ran)
    basin_transform: np.ndarray | None = None  # that start, refined, when it is a rival (sharper)
    seen_through: float | None = None  # of the pose (align/freespace.py; None: no scanner known)

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
            "profile": self.profile.to_dict(),
            "rival_profile": None if self.rival_profile is None else self.rival_profile.to_dict(),
            "rival_transform": None
            if self.rival_transform is None
            else np.asarray(self.rival_transform).tolist(),
            "rival_source": self.rival_source,
            "candidates": self.candidates,
            "distinct_rivals": self.distinct_rivals,
            "seconds": self.seconds,
            "rivals": self.rivals,
            "seen_through": self.seen_through,
            "basin_share": self.basin_share,
            "basin_transform": None
            if self.basin_transform is None
            else np.asarray(self.basin_transform).tolist(),
        }


@dataclass(frozen=True, kw_only=True, eq=False)
class Candidate:
    """A pose the judge weighs a pose against, before its refinement."""

    T: np.ndarray  # source local -> target local
    source: str  # where it came from, as the verdict names it


def _shortlist(
    T: np.ndarray, candidates: list[Candidate], centre: np.ndarray, config: JudgeConfig
) -> list[Candidate]:
    """Candidates distinct from T and from each other, in the order given, at most `max_rivals`."""
    kept: list[Candidate] = []
    for cand in candidates:
        A = np.asarray(cand.T, dtype=float)
        if len(kept) >= config.max_rivals:
            break
        if not np.isfinite(A).all() or not distinct(A, T, centre, config):
            continue
        if all(distinct(A, k.T, centre, config) for k in kept):
            kept.append(Candidate(T=A, source=cand.source))
    return kept


@dataclass(frozen=True, kw_only=True, eq=False)
class _Rival:
    """A pose the judge weighs T against: a distinct rival (with its profile), or a start of T's
    basin that ended sharper than T (a rival of the fine margin only)."""

    name: str
    T: np.ndarray
    fine: float  # its fine share
    prof: Profile | None = None  # None: a basin start
    sharp: float = 0.0


def _first_best(rivals: list[_Rival], key) -> _Rival | None:
    """The first rival whose `key` is the highest, when that is above 0 (None otherwise)."""
    best, top = None, 0.0
    for r in rivals:
        if key(r) > top:
            best, top = r, key(r)
    return best


def judge(
    src,
    tgt,
    T: np.ndarray,
    candidates: list[Candidate],
    config: JudgeConfig,
    memo: PairMemo | None = None,
    space: FreeSpace | None = None,
) -> Verdict:
    """Score pose T against the distinct rivals among `candidates`, each refined first; a rival that ends within the distinct radius of T is T itself.
    A rival the pair's free space rules out (`space`: it puts points where a scanner saw through) is
    no rival, unless T is ruled out too: then the free space says nothing of this pair.
    T's `basin` starts that end sharper than T (`sharper_neighbours`) are rivals of the fine margin too;
    rivals blunter than `blunt_min_sharpness` are rivals of the fine margin only, not of the score.
    Refined rivals are kept in the pair's `memo` (`rivals.refined`). A source or target that is not a
    forest scene (`scene.check`) is refused first (RegistrationFailed): no pose between them is right."""
    memo = memo or PairMemo()
    scene.check(src, tgt, config, memo)
    t0 = time.perf_counter()
    c = centre(src, config, memo.source)
    mine = profile(src, tgt, T, config, memo)
    seen = _seen_through(src, tgt, config, memo, space)
    mine_through = seen(T)
    # the free space speaks only for a sharp pose it clearly allows: a blunt one fits by chance,
    # and one near the limit is no better placed than the rivals it would rule out
    speaks = (
        mine_through is not None
        and mine_through <= space.config.pose_max_share
        and sharpness(mine) >= config.min_sharpness
    )
    shortlist = _shortlist(T, candidates, c, config)
    done = refined(src, tgt, [cand.T for cand in shortlist], T, config, memo)
    table: list[dict] = []  # Verdict.rivals
    rivals: list[_Rival] = []
    shares: list[float | None] = []  # each rival's seen-through share, where the free space speaks
    for name, (A, prof) in zip((cand.source for cand in shortlist), done):
        deg, m = separation(A, T, c)
        if m <= config.distinct_m and deg <= config.distinct_deg:
            table.append({"from": name, "distinct": False, "deg": deg, "m": m})
            continue
        r = _Rival(name=name, T=A, fine=fine_share(prof, config), prof=prof, sharp=sharpness(prof))
        rivals.append(r)
        shares.append(seen(A) if speaks else None)
        row = {"score": prof.score, "fine": r.fine, "sharpness": r.sharp}
        table.append({"from": name, "distinct": True, "deg": deg, "m": m, **row})
    out = [i for i, share in enumerate(shares) if speaks and space.beyond(share)]
    # ruled out only where the pose beats them beyond chance at the finest scale (their share at
    # most 1 - chance_margin of its own): a pose that does not is not singled out by what is left
    # (a self-similar stand whose rivals were all ruled out let a sharp pose 9 m off through)
    below = (1.0 - config.chance_margin) * fine_share(mine, config)
    if out and all(rivals[i].fine <= below for i in out):
        rows = [row for row in table if row.get("distinct")]
        for i in out:
            rows[i].update(distinct=False, seen_through=shares[i])  # ruled out by the scene
        rivals = [r for i, r in enumerate(rivals) if i not in out]
    near = basin(src, tgt, T, config, memo) if config.basin_neighbours else []
    sharper = sharper_neighbours(mine, [q for _, q in near], config)
    basins: list[_Rival] = []
    for k, (A, prof) in enumerate(near):
        deg, m = separation(A, T, c)
        rival = any(prof is q for q in sharper)
        fine = fine_share(prof, config)
        table.append({"from": f"basin {k}", "distinct": rival, "deg": deg, "m": m, "fine": fine})
        if rival:
            basins.append(_Rival(name=f"the pose's own basin (start {k})", T=A, fine=fine))
    # a rival too blunt to be accepted itself fits only by chance: it may not outscore the pose
    # (docs/method.md#judge-settings), but it stays a rival of the fine margin
    sharp = [r for r in rivals if r.sharp >= config.blunt_min_sharpness]
    best = _first_best(sharp, lambda r: r.prof.score)
    finest = _first_best(rivals + basins, lambda r: r.fine)
    basin_best = _first_best(basins, lambda r: r.fine)  # the sharpest basin start that is a rival
    fine_rivals = [r.prof for r in rivals] + sharper
    score, rival_score = mine.score, 0.0 if best is None else best.prof.score
    margin = 1.0 - rival_score / score if score > 0 else -1.0
    return Verdict(
        score=score,
        rival_score=rival_score,
        margin=float(margin),
        confidence=confidence(mine, fine_rivals, config),
        fine_share=fine_share(mine, config),
        fine_rival_share=0.0 if finest is None else finest.fine,
        fine_margin=fine_margin(mine, fine_rivals, config),
        fine_rival_source=None if finest is None else finest.name,
        sharpness=sharpness(mine),
        profile=mine,
        rival_profile=None if best is None else best.prof,
        rival_transform=None if best is None else best.T,
        rival_source=None if best is None else best.name,
        candidates=len(shortlist),
        distinct_rivals=len(rivals),
        seconds=time.perf_counter() - t0,
        rivals=table,
        basin_share=max((fine_share(q, config) for _, q in near), default=0.0),
        basin_transform=None if basin_best is None else basin_best.T,
        seen_through=mine_through,
    )


def _seen_through(src, tgt, config: JudgeConfig, memo: PairMemo, space: FreeSpace | None):
    """pose -> its free-space share on the judge's structure samples (None: nothing to tell)."""
    if space is None:
        return lambda T: None
    s, t = samples(src, config, memo.source), samples(tgt, config, memo.target)
    return lambda T: space.share(s.structure, t.structure, T)


def second_look(
    T: np.ndarray, candidates: list[Candidate], centre: np.ndarray, config: JudgeConfig
) -> list[np.ndarray]:
    """A weak pose's second look: the distinct candidates, each the best-ranked of those near it,
    as starts of a full level stage and final ICP each; those most candidates agree on first (ties in
    the order given), at most `second_look_rivals`. A low-overlap pair's truth is often a start a few
    degrees off that the rivals' short ICP cannot bring in; several generators and slices find it,
    so it comes as a cluster of starts."""
    poses = [A for A in (np.asarray(c.T, dtype=float) for c in candidates) if np.isfinite(A).all()]
    votes = agreement(poses, centre, config)
    kept: list[int] = []
    for i, A in enumerate(poses):
        if all(distinct(A, B, centre, config) for B in [T, *(poses[k] for k in kept)]):
            kept.append(i)
    kept.sort(key=lambda i: -votes[i])
    return [poses[i] for i in kept[: config.second_look_rivals]]


@dataclass(frozen=True, kw_only=True, eq=False)
class StoredVerdict:
    """Whether a stored pose holds, and the figures of the fine ICP from it."""

    verified: bool
    failed: tuple[str, ...]  # the checks that did not pass
    correction_deg: float  # how far the fine ICP moved it
    correction_m: float
    sharpness: float
    score: float
    profile: Profile

    def record(self, seconds: float) -> dict:
        """Its figures for PairResult.coarse (no transform: the result has it)."""
        return {
            "verified": self.verified,
            "failed": list(self.failed),
            "correction_deg": self.correction_deg,
            "correction_m": self.correction_m,
            "sharpness": self.sharpness,
            "score": self.score,
            "seconds": seconds,
        }


def verify_stored(
    src, tgt, T: np.ndarray, A: np.ndarray, config: JudgeConfig, memo: PairMemo | None = None
) -> StoredVerdict:
    """Does the stored pose T (source local -> target local) hold? A, the fine ICP from it, must
    barely move it and fit sharply (`sharpness`) with at least `stored_min_score`."""
    memo = memo or PairMemo()
    deg, m = separation(A, T, centre(src, config, memo.source))
    prof = profile(src, tgt, A, config, memo)
    sharp = sharpness(prof)
    checks = {
        "correction": deg <= config.stored_max_correction_deg
        and m <= config.stored_max_correction_m,
        "sharpness": sharp >= config.stored_min_sharpness,
        "score": prof.score >= config.stored_min_score,
    }
    return StoredVerdict(
        verified=all(checks.values()),
        failed=tuple(k for k, ok in checks.items() if not ok),
        correction_deg=deg,
        correction_m=m,
        sharpness=sharp,
        score=prof.score,
        profile=prof,
    )

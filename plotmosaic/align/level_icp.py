"""The level stage: incremental ICP over the matched complexity levels (paper eq. 3 and Algorithm 1),
least complex source level first, never ending worse than it started."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.align.complexity import match_levels
from plotmosaic.align.icp import IcpOptions, evaluate, point_to_plane_icp
from plotmosaic.align.prepare import PreparedCloud
from plotmosaic.align.sampling import sample
from plotmosaic.config.align import AlignConfig


@dataclass(frozen=True, kw_only=True, eq=False)
class LevelResult:
    """The level stage's pose and the figures PairResult.levels reports."""

    T: np.ndarray  # source local -> target local
    matching: dict[int, int]  # source level -> target level
    steps: list[dict]
    start_fit: float | None  # fitness of a probe at the stage's start (None: the stage did not run)
    level_fit: float | None  # and at its end
    reverted: bool  # it ended worse than it started: the start stands


def level_matching(src: PreparedCloud, tgt: PreparedCloud) -> dict[int, int]:
    return match_levels(
        [s["match_value"] for s in src.level_stats],
        [s["match_value"] for s in tgt.level_stats],
        compress=False,
    )


def incremental_steps(matching: dict[int, int]) -> list[tuple[list[int], list[int]]]:
    """Cumulative (source levels, target levels) per step, least complex source level first."""
    steps, src, tgt = [], [], []
    for s in sorted(matching):
        src.append(s)
        tgt.append(matching[s])
        steps.append((list(src), list(tgt)))
    return steps


def no_level_stage(src: PreparedCloud, tgt: PreparedCloud, T: np.ndarray) -> LevelResult:
    """The matching alone, for a pose that skips the level stage (a verified stored pose)."""
    return LevelResult(
        T=T,
        matching=level_matching(src, tgt),
        steps=[],
        start_fit=None,
        level_fit=None,
        reverted=False,
    )


def level_stage(
    src: PreparedCloud,
    tgt: PreparedCloud,
    config: AlignConfig,
    T: np.ndarray,
    after_coarse: bool,
    rng: np.random.Generator,
) -> LevelResult:
    """Incremental ICP over the matched levels; reverted when it ends worse than it started."""
    T_init = T.copy()
    matching = level_matching(src, tgt)
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
        options = IcpOptions(
            stages=tuple(schedule), min_eig_ratio=config.min_eig_ratio, tol=config.level_tol
        )
        res = point_to_plane_icp(sp, tp, tn, T, options)
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
    return LevelResult(
        T=T,
        matching=matching,
        steps=steps,
        start_fit=start_fit,
        level_fit=level_fit,
        reverted=reverted,
    )


def level_table(p: PreparedCloud, matching: dict[int, int], as_source: bool) -> list[dict]:
    """PreparedCloud.level_stats with the level each one is matched to."""
    inv = {t: s for s, t in matching.items()}
    rows = []
    for st in p.level_stats:
        lv = st["level"]
        matched = matching.get(lv) if as_source else inv.get(lv)
        rows.append({**st, "matched": matched})
    return rows


def levels_record(src: PreparedCloud, tgt: PreparedCloud, levels: LevelResult) -> dict:
    """PairResult.levels: both clouds' level tables, the matching and the stage's steps."""
    return {
        "source": level_table(src, levels.matching, True),
        "target": level_table(tgt, levels.matching, False),
        "matching": {str(k): v for k, v in levels.matching.items()},
        "steps": levels.steps,
        "fitness_before": levels.start_fit,
        "fitness_after": levels.level_fit,
        "reverted": levels.reverted,
    }

"""Rivals of a pose, refined the same way: a short robust ICP from each start, kept per pair so every
verdict of the pair refines a start once; and the starts around a pose that probe its own basin.

Every transform here maps source-local to target-local coordinates.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from plotmosaic.align.icp import IcpOptions, MovingNearest, point_to_plane_icp
from plotmosaic.align.judge.profile import (
    Profile,
    centre,
    distinct,
    fine_share,
    near,
    profile,
    separation,
)
from plotmosaic.align.memo import PairMemo
from plotmosaic.align.spacing import samples, scale_factor
from plotmosaic.config.align import IcpStage
from plotmosaic.config.judge import JudgeConfig
from plotmosaic.parallel import in_two_threads


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
    search = MovingNearest(tgt.tree)  # the correspondences carry over from stage to stage
    for k, (d, n) in enumerate(config.rival_schedule):
        options = IcpOptions(
            stages=(IcpStage(max_distance=d * f, iterations=n),),
            kernel_floor=min(config.rival_kernel, d) * f,  # a tight stage needs a tight kernel
            tol=1e-4,
        )
        res = point_to_plane_icp(
            samples(src, config, memo.source).fine,
            tgt.points,
            tgt.target_normals,
            A,
            options,
            search,
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


def refined(
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


def sharper_neighbours(prof: Profile, near: list[Profile], config: JudgeConfig) -> list[Profile]:
    """The basin profiles `near` that end with more than (1 + basin_tolerance) x the pose's fine share:
    rivals of it (one that returns to the pose, or ends blunter, is none)."""
    mine = fine_share(prof, config)
    return [q for q in near if fine_share(q, config) > (1.0 + config.basin_tolerance) * mine]

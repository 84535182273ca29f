"""Residual profiles: the share of a cloud's sample points within several distances of the other
cloud at a pose, the figures the judge reads from them, and how far apart two poses are.

Every transform here maps source-local to target-local coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.align.icp import nearest
from plotmosaic.align.memo import CloudMemo, PairMemo
from plotmosaic.align.spacing import samples, scale_factor
from plotmosaic.config.judge import JudgeConfig
from plotmosaic.io.frame import inverse, rotation_deg


def _shares(points: np.ndarray, tree, T: np.ndarray, scales: np.ndarray) -> list[float]:
    if len(points) == 0:
        return [0.0] * len(scales)
    d, _ = nearest(tree, points @ T[:3, :3].T + T[:3, 3], float(scales[-1]))
    return [float(np.mean(d <= s)) for s in scales]


@dataclass(frozen=True, kw_only=True, eq=False)
class Profile:
    """A pose's residual profile: the shares of sample points within each scale of the other cloud,
    on structure points and on all, both directions (st: source points near the target)."""

    scales: list[float]  # m, the judge's scales stretched by the pair's scale factor
    structure_st: list[float]
    structure_ts: list[float]
    all_st: list[float]
    all_ts: list[float]
    score: float  # the mean share over the scales and both directions, structure points
    score_all: float  # the same on all points

    def to_dict(self) -> dict:
        """Its figures in RESULT.json (judge.profile, judge.rival_profile)."""
        return {
            "scales": self.scales,
            "structure_st": self.structure_st,
            "structure_ts": self.structure_ts,
            "all_st": self.all_st,
            "all_ts": self.all_ts,
            "score": self.score,
            "score_all": self.score_all,
        }


def profile(src, tgt, T: np.ndarray, config: JudgeConfig, memo: PairMemo | None = None) -> Profile:
    """Residual profile of pose T."""
    memo = memo or PairMemo()
    s, t = samples(src, config, memo.source), samples(tgt, config, memo.target)
    scales = np.asarray(config.scales) * scale_factor(src, tgt, config, memo)
    Ti = inverse(T)
    structure_st = _shares(s.structure, tgt.tree, T, scales)
    structure_ts = _shares(t.structure, src.tree, Ti, scales)
    all_st = _shares(s.everything, tgt.tree, T, scales)
    all_ts = _shares(t.everything, src.tree, Ti, scales)
    return Profile(
        scales=[float(v) for v in scales],
        structure_st=structure_st,
        structure_ts=structure_ts,
        all_st=all_st,
        all_ts=all_ts,
        score=float(np.mean(structure_st + structure_ts)),
        score_all=float(np.mean(all_st + all_ts)),
    )


def separation(A: np.ndarray, B: np.ndarray, centre: np.ndarray) -> tuple[float, float]:
    """(rotation deg, displacement m of the source point `centre`) between two poses."""
    return rotation_deg(inverse(B) @ A), float(
        np.linalg.norm((A[:3, :3] - B[:3, :3]) @ centre + A[:3, 3] - B[:3, 3])
    )


def _within(
    A: np.ndarray, B: np.ndarray, centre: np.ndarray, config: JudgeConfig, k: float
) -> bool:
    """Within `k` distinct radii of each other, in rotation and in displacement."""
    deg, m = separation(A, B, centre)
    return m <= k * config.distinct_m and deg <= k * config.distinct_deg


def distinct(A: np.ndarray, B: np.ndarray, centre: np.ndarray, config: JudgeConfig) -> bool:
    deg, m = separation(A, B, centre)
    return m > config.distinct_m or deg > config.distinct_deg


def agreement(poses: list[np.ndarray], centre: np.ndarray, config: JudgeConfig) -> np.ndarray:
    """For each pose, how many of `poses` (itself included) lie within its distinct radius."""
    if not poses:
        return np.zeros(0, dtype=int)
    T = np.stack(poses)
    R = T[:, :3, :3]
    p = R @ centre + T[:, :3, 3]  # where each pose puts the source centre
    m = np.linalg.norm(p[:, None, :] - p[None, :, :], axis=2)
    cos = (np.einsum("iab,jab->ij", R, R) - 1.0) / 2.0  # trace(Rj^T Ri): the angle between them
    deg = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return ((m <= config.distinct_m) & (deg <= config.distinct_deg)).sum(axis=1)


def same(A: np.ndarray, B: np.ndarray, centre: np.ndarray, config: JudgeConfig) -> bool:
    """Within `weighed_radius` of the distinct radius: the same pose as far as the judge goes."""
    return _within(A, B, centre, config, config.weighed_radius)


def near(A: np.ndarray, B: np.ndarray, centre: np.ndarray, config: JudgeConfig) -> bool:
    """Within `near_rival_radii` distinct radii (both rotation and displacement): A may be B's basin."""
    return _within(A, B, centre, config, config.near_rival_radii)


def centre(cloud, config: JudgeConfig, memo: CloudMemo | None = None) -> np.ndarray:
    """Centroid of a prepared cloud's points: pose separations are measured there."""
    return samples(cloud, config, memo).centre


def fine_share(prof: Profile, config: JudgeConfig) -> float:
    """Mean share of structure points within the `fine_scales` smallest scales, both directions:
    where a right pose stands out (chance alignments gather points only at the wide scales)."""
    k = config.fine_scales
    return float(np.mean(prof.structure_st[:k] + prof.structure_ts[:k]))


def fine_margin(prof: Profile, rivals: list[Profile], config: JudgeConfig) -> float:
    """1 - the best rival's fine share / the pose's (1 without rivals, -1 when the pose has none)."""
    mine = fine_share(prof, config)
    best = max((fine_share(r, config) for r in rivals), default=0.0)
    return 1.0 - best / mine if mine > 0 else -1.0


def confidence(prof: Profile, rivals: list[Profile], config: JudgeConfig) -> float:
    """The judge's confidence in pose `prof` over the distinct `rivals` (profiles), 0-1: its fine
    margin, from the margin chance alignments reach (0) to `full_margin` (1)."""
    m = fine_margin(prof, rivals, config)
    return float(
        np.clip((m - config.chance_margin) / (config.full_margin - config.chance_margin), 0, 1)
    )


def sharpness(prof: Profile) -> float:
    """Share within the smallest scale over share within the largest, structure points, both
    directions: near 1 when the clouds coincide, low when they only come close by chance."""
    near = prof.structure_st[0] + prof.structure_ts[0]
    far = prof.structure_st[-1] + prof.structure_ts[-1]
    return float(near / far) if far > 0 else 0.0

"""A prepared cloud's point spacing, the scale factor it sets for a pair, and the seeded samples
the spacing is measured on.

The fine ICP and the judge both stretch their distances by the sparser cloud's spacing. The spacing
probe is drawn from the one seeded stream that also draws the judge's profile samples (the same
draws in the same order, so every figure stays the same); the samples live here with it, below
both the fine stage and the judge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.align.memo import CloudMemo, PairMemo
from plotmosaic.align.sampling import sample
from plotmosaic.config.judge import JudgeConfig

SEED = 20_261_201
PROBE_POINTS = 2_000  # points whose nearest neighbour measures the spacing


@dataclass(frozen=True, kw_only=True, eq=False)
class CloudSamples:
    """Seeded samples of a prepared cloud."""

    everything: np.ndarray  # profile sample of the cloud (its level points: even density)
    structure: np.ndarray  # the non-flat part of it
    spacing: float  # median nearest-neighbour spacing of the delta0 points (m)
    fine: np.ndarray  # source points of a rival's refinement ICP
    centre: np.ndarray  # centroid of the cloud's points: where pose separations are measured


def samples(cloud, config: JudgeConfig, memo: CloudMemo | None = None) -> CloudSamples:
    """Seeded samples of a prepared cloud, kept in `memo` (a scan takes part in several pairs)."""
    key = config.model_dump_json(
        include={"profile_points", "structure_max_planarity", "rival_points"}
    )
    return (memo or CloudMemo()).judge.get(key, lambda: _draw(cloud, config))


def _draw(cloud, config: JudgeConfig) -> CloudSamples:
    rng = np.random.default_rng(SEED)
    pts = cloud.level_points
    planarity = np.nan_to_num(np.asarray(cloud.features)[:, 1], nan=1.0)
    flat = planarity >= config.structure_max_planarity
    every = pts[sample(len(pts), config.profile_points, rng)]
    struct = pts[~flat]
    struct = struct[sample(len(struct), config.profile_points, rng)]
    probe = pts[sample(len(pts), PROBE_POINTS, rng)]
    d, _ = cloud.tree.query(probe, k=2)
    spacing = float(np.median(d[:, 1])) if len(probe) > 1 else config.reference_spacing
    fine = cloud.fine_points[sample(len(cloud.fine_points), config.rival_points, rng)]
    return CloudSamples(
        everything=every,
        structure=struct,
        spacing=spacing,
        fine=fine,
        centre=cloud.points.mean(axis=0),
    )


def spacing(cloud, config: JudgeConfig, memo: CloudMemo | None = None) -> float:
    """Median nearest-neighbour spacing (m) of a prepared cloud's delta0 points."""
    return samples(cloud, config, memo).spacing


def scale_factor(src, tgt, config: JudgeConfig, memo: PairMemo | None = None) -> float:
    """How much a pair's distances stretch: the sparser cloud is judged at its own resolution."""
    memo = memo or PairMemo()
    wider = max(spacing(src, config, memo.source), spacing(tgt, config, memo.target))
    return float(np.clip(wider / config.reference_spacing, 1.0, config.max_scale_factor))

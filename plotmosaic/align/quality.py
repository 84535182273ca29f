"""A pose's figures in file coordinates: fitness, RMSE and overlap on seeded subsamples, and the
information of its final point-to-plane problem."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.align.fine import FineResult
from plotmosaic.align.icp import evaluate, information_matrix
from plotmosaic.align.prepare import PreparedCloud
from plotmosaic.align.sampling import sample
from plotmosaic.config.align import AlignConfig
from plotmosaic.io.frame import to_global_transform


@dataclass(frozen=True, kw_only=True, eq=False)
class Quality:
    """The pose's figures in file coordinates."""

    transform: np.ndarray  # source file -> target file
    fitness: float  # share of source points near the target
    fitness_reverse: float  # share of target points near the source
    rmse: float
    overlap: float
    information: np.ndarray  # 6x6, from the final point-to-plane problem
    sigma: float  # point-to-plane residual std behind `information`


def measure(
    src: PreparedCloud,
    tgt: PreparedCloud,
    config: AlignConfig,
    fine: FineResult,
    rng: np.random.Generator,
) -> Quality:
    """Fitness, RMSE and overlap at `quality_distance`, and the information of the pose."""
    T = fine.T
    # fitness / RMSE / overlap on seeded subsamples of the query side: the same figures for a
    # fraction of the nearest-neighbour queries on dense scans
    s_q = src.points[sample(len(src.points), config.quality_max_points, rng)]
    t_q = tgt.points[sample(len(tgt.points), config.quality_max_points, rng)]
    fitness, rmse, n_s = evaluate(s_q, tgt.tree, T, config.quality_distance)
    fitness_reverse, _, n_t = evaluate(t_q, src.tree, np.linalg.inv(T), config.quality_distance)
    overlap = float((n_s + n_t) / max(1, len(s_q) + len(t_q)))
    # information from the final point-to-plane problem (its last correspondences), in file coordinates
    T_file = to_global_transform(T, src.frame, tgt.frame)
    if len(fine.p):
        p, q = src.frame.to_global(fine.p), tgt.frame.to_global(fine.q)
        info, sigma = information_matrix(p, q, fine.n, T_file)
    else:
        info, sigma = np.zeros((6, 6)), float("nan")
    return Quality(
        transform=T_file,
        fitness=fitness,
        fitness_reverse=fitness_reverse,
        rmse=rmse,
        overlap=overlap,
        information=info,
        sigma=sigma,
    )

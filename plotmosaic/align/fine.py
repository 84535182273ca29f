"""The fine stage: point-to-plane ICP on every point at the finest spacing, and its schedule."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.align.icp import IcpOptions, Mirror, MovingNearest, nearest, point_to_plane_icp
from plotmosaic.align.memo import PairMemo
from plotmosaic.align.prepare import PreparedCloud
from plotmosaic.align.sampling import sample
from plotmosaic.align.spacing import scale_factor, spacing
from plotmosaic.config.align import AlignConfig, IcpStage
from plotmosaic.io.frame import inverse

LENS_SEED = 7  # the overlap samples' own stream: the same pose, the same samples


@dataclass(frozen=True, kw_only=True, eq=False)
class FineResult:
    """The final ICP's pose and its last forward correspondences, in local coordinates."""

    T: np.ndarray  # source local -> target local
    p: np.ndarray  # source points
    q: np.ndarray  # target points
    n: np.ndarray  # target-side normals
    iterations: int
    reverse: bool  # the source's planes were used (sparse target)


def fine_schedule(
    src: PreparedCloud, tgt: PreparedCloud, config: AlignConfig, memo: PairMemo | None = None
):
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
    f = 1.0 if fixed else scale_factor(src, tgt, config.judge, memo)
    d = config.final_polish_distance * f
    stages = list(config.final_schedule)
    if config.final_polish_iterations == 0 or not stages or d >= stages[-1].max_distance:
        return stages, config.robust_kernel
    stages.append(IcpStage(max_distance=d, iterations=config.final_polish_iterations))
    return stages, min(config.robust_kernel, config.final_polish_kernel * f)


def final_icp(
    src: PreparedCloud,
    tgt: PreparedCloud,
    T: np.ndarray,
    config: AlignConfig,
    memo: PairMemo | None = None,
) -> FineResult:
    """Final point-to-plane ICP with the planes of the denser cloud, or of both for two clouds of
    `final_symmetric_kinds` of comparable density (neither side `final_reverse_ratio` sparser), with
    the side test where both scanners are known."""
    memo = memo or PairMemo()
    s_sp = spacing(src, config.judge, memo.source)
    t_sp = spacing(tgt, config.judge, memo.target)
    schedule, kernel = fine_schedule(src, tgt, config, memo)
    options = IcpOptions(stages=tuple(schedule), kernel_floor=kernel, tol=config.final_tol)
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
            options,
            MovingNearest(src.tree),
            viewpoints=None if views is None else views[::-1],
        )
        T = inverse(res.T)
        p, q = src.points[res.target_index], tgt.fine_points[res.source_index]
        n = (
            src.target_normals(res.target_index) @ T[:3, :3].T
        )  # the same planes, in target coordinates
        return FineResult(T=T, p=p, q=q, n=n, iterations=res.iterations, reverse=True)
    symmetric = (
        src.kind in config.final_symmetric_kinds and tgt.kind in config.final_symmetric_kinds
    )

    def run(T0: np.ndarray, forward: np.ndarray, backward: np.ndarray) -> FineResult:
        res = point_to_plane_icp(
            forward,
            tgt.points,
            tgt.target_normals,
            T0,
            options,
            MovingNearest(tgt.tree),
            mirror=Mirror(backward, src.points, src.tree, src.target_normals)
            if symmetric
            else None,
            viewpoints=views,
        )
        return FineResult(
            T=res.T,
            p=forward[res.source_index],
            q=tgt.points[res.target_index],
            n=tgt.target_normals(res.target_index),
            iterations=res.iterations,
            reverse=False,
        )

    fine = run(T, src.fine_points, tgt.fine_points)
    if config.lens_max_share == 0:
        return fine
    d, _ = nearest(tgt.tree, _moved(src.fine_points, fine.T), config.lens_distance)
    if np.isfinite(d).mean() >= config.lens_max_share:
        return fine
    # a thin overlap: the fine samples, drawn over the whole scans, put few points where the clouds
    # meet, and those few leave the pose loose; again from there on samples of the shared part
    forward, backward = lens_samples(src, tgt, fine.T, config)
    if len(forward) <= len(fine.p):
        return fine
    again = run(fine.T, forward, backward)
    return again if len(again.p) > len(fine.p) else fine


def _moved(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def lens_samples(
    src: PreparedCloud, tgt: PreparedCloud, T: np.ndarray, config: AlignConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Seeded samples of each cloud's points within `lens_distance` of the other at pose T (source
    local -> target local): where the two clouds overlap, at most final_max_source_points each."""
    rng = np.random.default_rng(LENS_SEED)
    Ti = inverse(T)
    out = []
    for points, tree, A in ((src.points, tgt.tree, T), (tgt.points, src.tree, Ti)):
        d, _ = nearest(tree, _moved(points, A), config.lens_distance)
        near = points[np.isfinite(d)]
        out.append(near[sample(len(near), config.final_max_source_points, rng)])
    return out[0], out[1]

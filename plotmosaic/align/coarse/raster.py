"""The raster generator: heading searched exhaustively, the horizontal shift by masked FFT
correlation of forest rasters (stems, canopy, terrain), per vertical pair."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import fft

from plotmosaic.align.coarse.clouds import (
    AIRBORNE,
    Levelled,
    Levels,
    homogeneous,
    hypothesis_transform,
    unlevelled,
)
from plotmosaic.align.coarse.hypothesis import Start
from plotmosaic.align.peaks import Peak, angle_diff, distinct_peaks
from plotmosaic.align.rasters import CHANNELS, MaskedNCC, column_bins, rasterise
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.parallel import in_two_threads


def weights(source_kind: str, target_kind: str, config: CoarseConfig) -> dict[str, float]:
    """The channels' weights: an airborne cloud on either side sees the canopy from above."""
    if source_kind in AIRBORNE or target_kind in AIRBORNE:
        return dict(config.weights_airborne)
    return dict(config.weights_ground)


def pyramid(source_kind: str, target_kind: str, config: CoarseConfig) -> int:
    """How many raster cells wide the first heading pass's cells are: coarser only where a cloud is
    airborne (canopy and terrain weigh most, smooth at that scale; stems are a cell wide)."""
    if source_kind in AIRBORNE or target_kind in AIRBORNE:
        return config.heading_pyramid
    return 1


class _Correlation:
    """The target's rasters on a cell no finer than `max_fft` allows, the masked NCC over them, and
    the best shifts of the source turned to a heading (`peaks`). `prior` (levelled source ->
    levelled target): shifts only within `prior_shift_m` of where it puts the source centroid."""

    def __init__(
        self,
        src: Levelled,
        tgt: Levelled,
        weights: dict[str, float],
        config: CoarseConfig,
        prior: np.ndarray | None,
    ) -> None:
        centre = src.feats.xy.mean(axis=0)
        radius = float(np.linalg.norm(src.feats.xy - centre, axis=1).max()) + 1.0
        t_min, t_max = tgt.feats.xy.min(axis=0) - 1.0, tgt.feats.xy.max(axis=0) + 1.0
        cell = config.cell
        while True:
            t_shape = tuple(np.ceil((t_max - t_min) / cell).astype(int) + 1)
            s_side = int(np.ceil(2 * radius / cell)) + 1
            if max(fft.next_fast_len(t + s_side, real=True) for t in t_shape) <= config.max_fft:
                break
            cell *= config.cell_growth
        self.s_shape = (s_side, s_side)
        self.s_origin = centre - radius
        self.src_bins = column_bins(src.feats, cell / 4)
        tgt_bins = column_bins(tgt.feats, cell / 4)
        target = rasterise(tgt_bins.xy, tgt_bins, cell, t_min, t_shape, config.blur_cells)
        area_t = target.masks["canopy"].sum()
        # headings run in two threads instead of the FFT's own workers
        self.ncc = MaskedNCC(target, self.s_shape, min_overlap=1, workers=1)
        area_s = (
            rasterise(self.src_bins.xy, self.src_bins, cell, self.s_origin, self.s_shape, 0)
            .masks["canopy"]
            .sum()
        )
        self.area = min(area_s, area_t)
        self.min_cells = config.min_overlap * self.area
        self.rel = self.src_bins.xy - centre
        self.centre, self.cell, self.weights, self.config = centre, cell, weights, config
        self.allowed = self.prior_yaw = None
        if prior is not None:
            c3 = np.array([*centre, float(np.median(src.feats.z))])
            self.prior_yaw = float(np.arctan2(prior[1, 0], prior[0, 0]))
            prior_t = (prior[:3, :3] @ c3 + prior[:3, 3])[:2] - centre
            shape = self.ncc.shape
            rows, cols = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
            shift = np.stack(
                [
                    np.where(rows < shape[0] // 2, rows, rows - shape[0]),
                    np.where(cols < shape[1] // 2, cols, cols - shape[1]),
                ],
                axis=-1,
            )
            t_xy = target.origin - self.s_origin + shift * cell
            self.allowed = np.linalg.norm(t_xy - prior_t, axis=-1) <= config.prior_shift_m

    def _scores(self, source) -> tuple[np.ndarray, np.ndarray]:
        """(weighted score of every shift, overlap share), -1 where the overlap is too small."""
        config, weights, min_cells = self.config, self.weights, self.min_cells
        total = 0.0
        overlap = None
        for name, (score, ov) in self.ncc.scores(
            source, [n for n in CHANNELS if weights[n] != 0]
        ).items():
            if name == "canopy":
                overlap = ov
            if name == "terrain":  # a handful of shared ground cells proves nothing
                score = np.where(
                    ov >= max(min_cells * config.terrain_min_share, config.terrain_min_cells),
                    score,
                    0.0,
                )
            total = total + weights[name] * score
        total = total / sum(weights.values())
        frac = overlap / max(self.area, 1.0)
        total = np.where(
            overlap >= min_cells, total * np.clip(frac, 0, 1) ** config.overlap_exponent, -1.0
        )
        if self.allowed is not None:
            total = np.where(self.allowed, total, -1.0)
        return total, frac

    def peaks(self, yaw: float) -> list[Peak]:
        """The best `peaks_per_yaw` shifts of the source turned by `yaw`, each suppressing its
        neighbourhood."""
        config, rel, centre, cell = self.config, self.rel, self.centre, self.cell
        c, s_ = np.cos(yaw), np.sin(yaw)
        xy = np.empty_like(rel)
        xy[:, 0] = c * rel[:, 0] - s_ * rel[:, 1] + centre[0]
        xy[:, 1] = s_ * rel[:, 0] + c * rel[:, 1] + centre[1]
        source = rasterise(xy, self.src_bins, cell, self.s_origin, self.s_shape, config.blur_cells)
        total, frac = self._scores(source)
        found = []
        for _ in range(config.peaks_per_yaw):
            k = np.unravel_index(int(np.argmax(total)), total.shape)
            if total[k] <= 0:
                break
            t_xy = self.ncc.shift_to_translation(k, source)
            found.append(
                Peak(
                    score=float(total[k]),
                    yaw=float(yaw),
                    t_xy=t_xy,
                    overlap=float(min(frac[k], 1.0)),
                )
            )
            r = max(1, int(round(config.peak_suppression_m / cell)))
            rows = np.arange(k[0] - r, k[0] + r + 1) % total.shape[0]
            cols = np.arange(k[1] - r, k[1] + r + 1) % total.shape[1]
            total[np.ix_(rows, cols)] = -1.0
        return found


def search(
    src: Levelled,
    tgt: Levelled,
    weights: dict[str, float],
    config: CoarseConfig,
    prior: np.ndarray | None = None,
    pyramid: int = 1,
) -> list[Peak]:
    """Exhaustive heading search; masked-NCC shift per heading; the best distinct peaks.

    `prior` (levelled source -> levelled target): search only headings within `prior_yaw_deg` of
    it and shifts within `prior_shift_m` of where it puts the source centroid. With `pyramid` > 1
    the headings are first scored on cells `pyramid` times larger, and only the best
    `pyramid_headings` of them searched on the raster cell.
    """
    corr = _Correlation(src, tgt, weights, config, prior)
    # coarse-to-fine in heading: the full circle at yaw_step_deg, then half steps either side of
    # the best headings (a peak is several steps wide once the rasters are blurred)
    step = np.radians(config.yaw_step_deg)
    yaws = [float(y) for y in np.arange(0.0, 2 * np.pi, step)]
    if prior is not None:
        yaws = [
            y for y in yaws if angle_diff(y, corr.prior_yaw) <= np.radians(config.prior_yaw_deg)
        ] + [float(corr.prior_yaw % (2 * np.pi))]
    if pyramid > 1 and len(yaws) > config.pyramid_headings:
        rough = config.model_copy(update={"cell": corr.cell * pyramid})
        coarse = _Correlation(src, tgt, weights, rough, prior)
        yaws = _best_headings(_peaks(coarse, yaws), step, config.pyramid_headings)
    candidates = _peaks(corr, yaws)
    refine = [
        float((yaw + d) % (2 * np.pi))
        for yaw in _best_headings(candidates, step, config.refine_headings)
        for d in (-0.5 * step, 0.5 * step)
    ]
    candidates += _peaks(corr, refine)
    candidates.sort(key=lambda c: -c.score)
    return distinct_peaks(
        candidates,
        config.distinct_yaw_deg,
        config.distinct_shift_m,
        config.hypotheses,
        centre=corr.centre,
        cell=corr.cell,
    )


def _peaks(corr: _Correlation, yaws: list[float]) -> list[Peak]:
    """Every heading's peaks; rasterising and FFTs release the GIL, so two headings at a time."""
    return [c for found in in_two_threads(corr.peaks, yaws) for c in found]


def _best_headings(candidates: list[Peak], step: float, most: int) -> list[float]:
    """The headings of the best `most` peaks more than 1.5 steps apart (a peak's heading neighbours
    score nearly as high: one heading stands for them)."""
    best: list[float] = []
    for c in sorted(candidates, key=lambda c: -c.score):
        if len(best) >= most:
            break
        if all(angle_diff(c.yaw, y) > 1.5 * step for y in best):
            best.append(c.yaw)
    return best


def raster_starts(
    src: Levels,
    tgt: Levels,
    pairs,
    weights,
    config: CoarseConfig,
    prior: np.ndarray | None,
    first: int = 0,
    pyramid: int = 1,
) -> tuple[list[Start], float | None]:
    """Starts of the raster search per vertical pair, and the raster cell used.

    `first`: the index of `pairs[0]` among all vertical pairs (pair 0 gets the most hypotheses);
    `pyramid`: see `search` (the narrow scene's finer search never coarsens)."""
    out, cell = [], None
    for k, (vs, vt) in enumerate(pairs, start=first):
        ls, lt = src.level(vs, config), tgt.level(vt, config)
        prior_l = None if prior is None else homogeneous(lt.R) @ prior @ homogeneous(ls.R.T)
        hyps = search(ls, lt, weights, config, prior_l, pyramid)[
            : config.hypotheses if k == 0 else config.secondary_hypotheses
        ]
        ground_tree = tgt.ground_tree(vt, config)
        if k == 0:
            hyps = hyps + _small_scene(ls, lt, weights, config, prior_l)
        for h in hyps:
            cell = h.cell if cell is None else cell
            A = hypothesis_transform(
                ls, lt, ground_tree, config, yaw=h.yaw, t_xy=h.t_xy, centre=h.centre
            )
            out.append(
                Start(
                    T=unlevelled(A, ls, lt),
                    generator="raster",
                    vertical=f"{vs.name}/{vt.name}" + (" fine" if h.fine else ""),
                    score=h.score,
                    yaw=h.yaw,
                    overlap=h.overlap,
                )
            )
    return out, cell


def _small_scene(
    ls: Levelled, lt: Levelled, weights, config: CoarseConfig, prior_l: np.ndarray | None
) -> list[Peak]:
    """A narrow scene (a 12 m understorey view is 12 cells at 1 m) also gets a finer-cell search
    beside, never instead of, the usual one: finer cells alone found a wrong pose with full confidence."""
    side = float(np.ptp(ls.feats.xy, axis=0).min())
    if side >= config.small_scene_cells * config.cell or config.cell <= config.min_cell:
        return []
    fine = config.model_copy(update={"cell": max(config.min_cell, side / config.small_scene_cells)})
    return [
        replace(h, fine=True)
        for h in search(ls, lt, weights, fine, prior_l)[: config.secondary_hypotheses]
    ]

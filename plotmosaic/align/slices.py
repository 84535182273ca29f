"""Height-slice occupancy search: heading x horizontal shift scored on fine cells of the points.

Under a vertical hypothesis only heading and shift remain (the height comes from the ground). The
1 m forest rasters blur a sparse ground view into a few stem blobs, and their terrain channel
correlates with itself at wrong poses on a slope. Here each levelled cloud is cut into slices of
height above its own rough DTM (de-trended: a slope no longer matches itself) and each slice is a
binary occupancy image at a fine cell. For every heading, FFT correlation gives for every shift

    score = hits / sqrt(n_s * n_t) * (n_s / S) ** overlap_exponent

hits: source slice cells on target cells of the same slice; n_s: source slice cells over columns the
target saw; n_t: target slice cells over columns the source saw; S: all source slice cells. So a pose
is scored only on what both views observed (partial overlap), and small overlaps score lower.
"""

from __future__ import annotations

import numpy as np
from scipy import fft

from plotmosaic.align.peaks import Peak, distinct_peaks
from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.parallel import in_two_threads


def _images(
    xy: np.ndarray, layer: np.ndarray, n_layers: int, origin, shape, cell
) -> tuple[np.ndarray, np.ndarray]:
    """(slice occupancy images (n_layers, *shape), columns seen at all) of points with slice `layer` (-1: none)."""
    ij = np.floor((xy - origin) / cell).astype(np.int64)
    ok = (ij >= 0).all(axis=1) & (ij[:, 0] < shape[0]) & (ij[:, 1] < shape[1])
    flat = ij[ok, 0] * shape[1] + ij[ok, 1]
    seen = np.zeros(shape[0] * shape[1], np.float32)
    seen[flat] = 1.0
    occ = np.zeros((n_layers, shape[0] * shape[1]), np.float32)
    lay = layer[ok]
    keep = lay >= 0
    occ[lay[keep], flat[keep]] = 1.0
    return occ.reshape(n_layers, *shape), seen.reshape(shape)


def slice_search(
    src_points: np.ndarray,
    src_hag: np.ndarray,
    tgt_points: np.ndarray,
    tgt_hag: np.ndarray,
    config: CoarseConfig,
) -> list[Peak]:
    """Best distinct (yaw, t_xy about `centre`) poses of the levelled source on the levelled target,
    as peaks in the raster search's convention (source xy rotated by yaw about centre, then shifted
    by t_xy)."""
    edges = np.asarray(config.slice_edges, float)
    n_layers = len(edges) - 1

    def layers(hag):
        k = np.searchsorted(edges, hag, side="right") - 1
        return np.where((k >= 0) & (k < n_layers), k, -1)

    sxy, txy = src_points[:, :2], tgt_points[:, :2]
    centre = sxy.mean(axis=0)
    radius = float(np.linalg.norm(sxy - centre, axis=1).max())
    search = _Correlation(
        sxy - centre, layers(src_hag), txy, layers(tgt_hag), n_layers, centre, radius, config
    )
    yaws = [float(y) for y in np.arange(0.0, 2 * np.pi, np.radians(config.slice_yaw_deg))]
    candidates = sorted(
        (c for found in in_two_threads(search.peaks, yaws) for c in found),
        key=lambda c: -c.score,
    )
    return distinct_peaks(
        candidates,
        config.slice_distinct_yaw_deg,
        config.slice_distinct_m,
        config.slice_hypotheses,
        centre=centre,
        cell=search.cell,
    )


class _Correlation:
    """The target's slice images on a grid fine enough and no larger than `slice_max_fft`, their
    transforms, and the best shifts of the source turned to a heading (`peaks`)."""

    def __init__(
        self,
        rel: np.ndarray,
        lay_s: np.ndarray,
        txy: np.ndarray,
        lay_t: np.ndarray,
        n_layers: int,
        centre: np.ndarray,
        radius: float,
        config: CoarseConfig,
    ) -> None:
        cell = config.slice_cell
        while True:
            t_min = txy.min(axis=0) - cell
            t_shape = tuple(np.ceil((txy.max(axis=0) + cell - t_min) / cell).astype(int) + 1)
            s_side = int(np.ceil(2 * (radius + cell) / cell)) + 1
            shape = tuple(fft.next_fast_len(t + s_side, real=True) for t in t_shape)
            if max(shape) <= config.slice_max_fft:
                break
            cell *= config.cell_growth
        self.rel, self.lay_s, self.n_layers, self.centre = rel, lay_s, n_layers, centre
        self.cell, self.t_min, self.s_side, self.shape = cell, t_min, s_side, shape
        self.s_origin = centre - radius - cell
        self.config = config
        T, t_seen = _images(txy, lay_t, n_layers, t_min, t_shape, cell)
        self.FT, self.FT_seen, self.FT_any = self._f(T), self._f(t_seen), self._f(T.sum(axis=0))
        self.r_sup = max(1, int(round(config.slice_suppression_m / cell)))

    def _f(self, a):
        # headings run in two threads instead of the FFT's own workers
        return fft.rfft2(a, s=self.shape, axes=(-2, -1), workers=1)

    def _to_t(self, k) -> np.ndarray:
        shape = self.shape
        s = np.array([k[i] if k[i] < shape[i] // 2 else k[i] - shape[i] for i in range(2)])
        return self.t_min - self.s_origin + s * self.cell

    def peaks(self, yaw: float) -> list[Peak]:
        """The best `slice_peaks_per_yaw` shifts of the source turned by `yaw`, each suppressing
        its neighbourhood."""
        config, rel, shape = self.config, self.rel, self.shape
        min_cells = config.slice_min_cells
        c, s_ = np.cos(yaw), np.sin(yaw)
        xy = np.column_stack([c * rel[:, 0] - s_ * rel[:, 1], s_ * rel[:, 0] + c * rel[:, 1]])
        S, s_seen = _images(
            xy + self.centre,
            self.lay_s,
            self.n_layers,
            self.s_origin,
            (self.s_side, self.s_side),
            self.cell,
        )
        total = float(S.sum())
        if total < min_cells:
            return []
        FS = np.conj(self._f(S))
        # sum_x a(x) b(x + t) for every shift t is irfft(conj(A) B) (padded: no wrap-around)
        hits, n_s, n_t = fft.irfft2(
            np.stack(
                [
                    (FS * self.FT).sum(axis=0),
                    FS.sum(axis=0) * self.FT_seen,
                    np.conj(self._f(s_seen)) * self.FT_any,
                ]
            ),
            s=shape,
            axes=(-2, -1),
            workers=1,
        )
        with np.errstate(divide="ignore", invalid="ignore"):
            score = np.where(
                (n_s >= min_cells) & (n_t >= min_cells),
                hits
                / np.sqrt(np.maximum(n_s, 1.0) * np.maximum(n_t, 1.0))
                * np.clip(n_s / total, 0.0, 1.0) ** config.overlap_exponent,
                0.0,
            )
        found = []
        r_sup = self.r_sup
        for _ in range(config.slice_peaks_per_yaw):
            k = np.unravel_index(int(np.argmax(score)), score.shape)
            if score[k] <= 0:
                break
            found.append(
                Peak(
                    score=float(score[k]),
                    yaw=yaw,
                    t_xy=self._to_t(k),
                    overlap=float(min(n_s[k] / total, 1.0)),
                )
            )
            rows = np.arange(k[0] - r_sup, k[0] + r_sup + 1) % shape[0]
            cols = np.arange(k[1] - r_sup, k[1] + r_sup + 1) % shape[1]
            score[np.ix_(rows, cols)] = -1.0
        return found

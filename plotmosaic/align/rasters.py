"""2D forest rasters of a levelled cloud, and masked normalised cross-correlation between them.

Channels (each with its own validity mask; cut-offs in CoarseConfig):
  stems   - occupancy of vertical surfaces 0.5-4 m above ground (what TLS sees best)
  canopy  - occupancy of vegetation more than 3 m above ground (what ALS sees best)
  terrain - ground height (both see it; carries heading through the slope and position through relief)

The masked NCC (Padfield, "Masked object registration in the Fourier domain", 2012) only
compares cells both clouds observed, which is what partial TLS overlap needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import fft, ndimage
from scipy.spatial import cKDTree

from plotmosaic.config.coarse import CoarseConfig
from plotmosaic.parallel import inner_workers

CHANNELS = ("stems", "canopy", "terrain")
# window values held at once by the sparse DTM's rank filter (32 MB of float64)
SPARSE_BLOCK_VALUES = 1 << 22


@dataclass(frozen=True)
class PointFeatures:
    """Per-point quantities that do not change under a rotation about z."""

    xy: np.ndarray  # (N, 2) levelled horizontal coordinates
    z: np.ndarray
    stem: np.ndarray  # bool
    canopy: np.ndarray  # bool
    ground: np.ndarray  # bool


def ground_model(
    xy: np.ndarray, z: np.ndarray, cell: float = 1.0, config: CoarseConfig | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A rough DTM: lowest point per cell, cells standing far above their neighbours dropped.

    Returns (dtm, origin, filled) where `filled` marks cells with a ground estimate.
    """
    c = config or CoarseConfig()
    origin = xy.min(axis=0) - cell
    ij = np.floor((xy - origin) / cell).astype(np.int64)
    shape = tuple(ij.max(axis=0) + 2)
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    low = np.full(shape[0] * shape[1], np.inf)
    np.minimum.at(low, flat, z)
    low = low.reshape(shape)
    filled = np.isfinite(low)
    # the lowest return of a cell seen only through a crown or beside a stem is not ground:
    # compare with the neighbourhood's low quantile and drop cells well above it
    ref = ndimage.percentile_filter(
        low, c.dtm_percentile, size=c.dtm_window, mode="constant", cval=np.inf
    )
    ok = filled & ~(low > ref + c.dtm_max_step)
    dtm = np.where(ok, low, np.nan)
    # fill holes from the nearest valid cell so every point gets a height above ground
    if ok.any():
        idx = ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True)
        dtm = dtm[tuple(idx)]
    else:
        dtm = np.full(shape, float(np.median(z)))
    return dtm, origin, ok


def height_above_ground(
    points: np.ndarray, cell: float = 1.0, config: CoarseConfig | None = None
) -> np.ndarray:
    """Each point's height above the rough DTM of its (levelled) cloud.

    A DTM of more than `dtm_dense_cells` cells is built on the occupied cells only (`sparse_ground`),
    so its memory follows the points, not the extent (a few far points spread over kilometres)."""
    c = config or CoarseConfig()
    xy, z = points[:, :2], points[:, 2]
    origin = xy.min(axis=0) - cell
    ij = np.floor((xy - origin) / cell).astype(np.int64)
    if float(np.prod((ij.max(axis=0) + 2).astype(float))) > c.dtm_dense_cells:
        return z - sparse_ground(ij, z, c)
    dtm, origin, _ = ground_model(xy, z, cell, c)
    return z - dtm[ij[:, 0], ij[:, 1]]


def sparse_ground(ij: np.ndarray, z: np.ndarray, c: CoarseConfig) -> np.ndarray:
    """`ground_model`'s DTM at each point's cell `ij`, computed on the occupied cells only.

    The same lowest point per cell, the same rank of the same window (empty cells count as +inf, as
    in the dense filter) and a hole filled from a nearest valid cell (a tie may pick another one)."""
    w = c.dtm_window
    ii = ij - ij.min(axis=0) + w  # room for the window's offsets on every side: keys never alias
    stride = int(ii[:, 1].max()) + w + 1
    keys, inv = np.unique(ii[:, 0] * stride + ii[:, 1], return_inverse=True)
    low = np.full(len(keys), np.inf)
    np.minimum.at(low, inv, z)
    # ndimage's rank for this percentile and window size (see scipy.ndimage.percentile_filter)
    size = w * w
    rank = size - 1 if c.dtm_percentile == 100.0 else int(float(size) * c.dtm_percentile / 100.0)
    offsets = [
        di * stride + dj
        for di in range(-(w // 2), w - w // 2)
        for dj in range(-(w // 2), w - w // 2)
    ]
    ref = np.empty(len(keys))
    block = max(1, SPARSE_BLOCK_VALUES // size)
    for s in range(0, len(keys), block):
        k = keys[s : s + block]
        window = np.full((len(k), size), np.inf)
        for o, off in enumerate(offsets):
            pos = np.minimum(np.searchsorted(keys, k + off), len(keys) - 1)
            hit = keys[pos] == k + off
            window[hit, o] = low[pos[hit]]
        ref[s : s + block] = np.partition(window, rank, axis=1)[:, rank]
    ok = ~(low > ref + c.dtm_max_step)
    if not ok.any():
        return np.full(len(z), float(np.median(z)))
    cells = np.column_stack([keys // stride, keys % stride]).astype(np.float64)
    ground = low.copy()
    holes = np.flatnonzero(~ok)
    if len(holes):
        good = np.flatnonzero(ok)
        nearest = cKDTree(cells[good]).query(cells[holes])[1]
        ground[holes] = low[good[nearest]]
    return ground[inv.ravel()]


def point_features(
    points: np.ndarray,
    normals: np.ndarray,
    cell: float = 1.0,
    config: CoarseConfig | None = None,
    hag: np.ndarray | None = None,
) -> PointFeatures:
    c = config or CoarseConfig()
    hag = height_above_ground(points, cell, c) if hag is None else hag
    vertical_surface = np.abs(normals[:, 2]) < c.vertical_normal_z
    return PointFeatures(
        xy=points[:, :2],
        z=points[:, 2],
        stem=vertical_surface & (hag > c.stem_min_hag) & (hag < c.stem_max_hag),
        canopy=hag > c.canopy_min_hag,
        ground=(hag < c.ground_max_hag) & (np.abs(normals[:, 2]) > c.ground_normal_z),
    )


def column_bins(feats: PointFeatures, size: float) -> PointFeatures:
    """One entry per occupied `size` x `size` column: its flags OR-ed, z the mean of its ground points.

    Rasters need only occupancy and ground height, so a heading search can rotate these few
    entries (a quarter-cell apart) instead of every point.
    """
    ij = np.floor(feats.xy / size).astype(np.int64)
    ij -= ij.min(axis=0)
    _, inv = np.unique(ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1], return_inverse=True)
    n = int(inv.max()) + 1
    count = np.bincount(inv, minlength=n)
    xy = np.column_stack([np.bincount(inv, feats.xy[:, i], n) / count for i in range(2)])
    g_n = np.bincount(inv, feats.ground, n)
    g_z = np.bincount(inv, feats.z * feats.ground, n)
    z = np.where(g_n > 0, g_z / np.maximum(g_n, 1), np.bincount(inv, feats.z, n) / count)
    return PointFeatures(
        xy=xy,
        z=z,
        stem=np.bincount(inv, feats.stem, n) > 0,
        canopy=np.bincount(inv, feats.canopy, n) > 0,
        ground=g_n > 0,
    )


@dataclass(frozen=True)
class Raster:
    origin: np.ndarray  # world xy of cell (0, 0)'s corner
    cell: float
    images: dict[str, np.ndarray]
    masks: dict[str, np.ndarray]


def rasterise(
    xy: np.ndarray,
    feats: PointFeatures,
    cell: float,
    origin: np.ndarray,
    shape: tuple[int, int],
    blur: float,
) -> Raster:
    ij = np.floor((xy - origin) / cell).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 1] >= 0) & (ij[:, 0] < shape[0]) & (ij[:, 1] < shape[1])
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    size = shape[0] * shape[1]

    def count(mask):
        m = mask & inside
        return np.bincount(flat[m], minlength=size).reshape(shape).astype(np.float64)

    seen = (count(np.ones(len(xy), bool)) > 0).astype(np.float64)
    images, masks = {}, {}
    for name in ("stems", "canopy"):
        occ = (count(getattr(feats, name[:-1] if name == "stems" else name)) > 0).astype(np.float64)
        images[name] = ndimage.gaussian_filter(occ, blur) if blur > 0 else occ
        masks[name] = seen  # one array: MaskedNCC transforms a shared mask once
    g = feats.ground & inside
    n_g = np.bincount(flat[g], minlength=size).reshape(shape)
    s_g = np.bincount(flat[g], weights=feats.z[g], minlength=size).reshape(shape)
    has = n_g > 0
    terrain = np.zeros(shape)
    terrain[has] = s_g[has] / n_g[has]
    if (
        has.any()
    ):  # NCC ignores a constant; without it the heights' squares cost float32 FFTs their precision
        terrain[has] -= terrain[has].mean()
    images["terrain"] = terrain
    masks["terrain"] = has.astype(np.float64)
    return Raster(np.asarray(origin, float), cell, images, masks)


class MaskedNCC:
    """Masked NCC of many source rasters against one fixed target raster (target FFTs cached).

    Channels that share a mask array (stems and canopy: "the cell was seen") share its transforms,
    and each call runs its transforms as one batch (two FFT calls instead of dozens).
    """

    def __init__(
        self,
        target: Raster,
        source_shape: tuple[int, int],
        min_overlap: float,
        workers: int | None = None,
    ):
        self.target, self.workers = target, workers if workers is not None else inner_workers()
        ht, wt = next(iter(target.images.values())).shape
        hs, ws = source_shape
        self.shape = (fft.next_fast_len(ht + hs, real=True), fft.next_fast_len(wt + ws, real=True))
        self.min_overlap = min_overlap
        self._t = self._spectra(target, list(target.images))

    def _f(self, arrays: list[np.ndarray]) -> np.ndarray:
        # float32: half the time of float64, and ample for picking peaks of occupancy / centred heights
        return fft.rfft2(
            np.stack(arrays).astype(np.float32), s=self.shape, axes=(-2, -1), workers=self.workers
        )

    def _spectra(self, raster: Raster, names, conjugate: bool = False) -> dict[str, tuple]:
        """{channel: (mask id, FFT of mask, of masked image, of its square)}, one batched transform
        (conjugated with `conjugate`); a mask array shared by channels is transformed once."""
        masks = _distinct_masks(raster, names)
        images = [raster.images[n] * raster.masks[n] for n in names]
        spectra = self._f(list(masks.values()) + [a for f in images for a in (f, f * f)])
        if conjugate:
            spectra = np.conj(spectra)  # once, not once per product it enters
        slot = {key: i for i, key in enumerate(masks)}
        return {
            n: (
                id(raster.masks[n]),
                spectra[slot[id(raster.masks[n])]],
                spectra[len(masks) + 2 * i],
                spectra[len(masks) + 2 * i + 1],
            )
            for i, n in enumerate(names)
        }

    def scores(self, source: Raster, names) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """{channel: (NCC, overlap in cells)} for every shift of `source` over the target."""
        src = self._spectra(source, names, conjugate=True)
        # sum_x a(x) b(x + s) for every shift s is irfft(conj(A) B) (padded: no wrap-around overlaps);
        # a mask pair's overlap row, then each channel's five rows
        overlap_of, base, rows = {}, {}, 0
        for name in names:
            if (src[name][0], self._t[name][0]) not in overlap_of:
                overlap_of[src[name][0], self._t[name][0]] = rows
                rows += 1
            base[name], rows = rows, rows + 5
        first = next(iter(self._t.values()))[1]
        products = np.empty((rows, *first.shape), dtype=first.dtype)
        for name in names:
            s_mask, fm1, ff, fff = src[name]
            t_mask, fm2, fg, fgg = self._t[name]
            if overlap_of[s_mask, t_mask] == base[name] - 1:  # the mask pair's first channel
                np.multiply(fm1, fm2, out=products[base[name] - 1])
            pairs = ((ff, fm2), (fm1, fg), (fff, fm2), (fm1, fgg), (ff, fg))
            for k, (a, b) in enumerate(pairs):
                np.multiply(a, b, out=products[base[name] + k])
        corr = fft.irfft2(products, s=self.shape, axes=(-2, -1), workers=self.workers)
        out = {}
        for name in names:
            overlap = np.round(corr[overlap_of[src[name][0], self._t[name][0]]])
            s_f, s_g, s_ff, s_gg, s_fg = corr[base[name] : base[name] + 5]
            with np.errstate(divide="ignore", invalid="ignore"):
                num = s_fg - s_f * s_g / overlap
                den = np.sqrt(
                    np.clip(s_ff - s_f**2 / overlap, 0, None)
                    * np.clip(s_gg - s_g**2 / overlap, 0, None)
                )
                ncc = np.where((overlap >= self.min_overlap) & (den > 1e-9), num / den, 0.0)
            out[name] = (np.clip(ncc, -1.0, 1.0), overlap)
        return out

    def __call__(self, source: Raster, name: str) -> tuple[np.ndarray, np.ndarray]:
        return self.scores(source, [name])[name]

    def shift_to_translation(self, k: tuple[int, int], source: Raster) -> np.ndarray:
        """Cell shift (wrapped index) -> xy translation taking source coordinates onto target ones."""
        s = np.array(
            [
                k[0] if k[0] < self.shape[0] // 2 else k[0] - self.shape[0],
                k[1] if k[1] < self.shape[1] // 2 else k[1] - self.shape[1],
            ]
        )
        return self.target.origin - source.origin + s * self.target.cell


def _distinct_masks(raster: Raster, names) -> dict[int, np.ndarray]:
    """The mask arrays of the channels, each once (keyed by identity, in first-use order)."""
    out: dict[int, np.ndarray] = {}
    for name in names:
        out.setdefault(id(raster.masks[name]), raster.masks[name])
    return out

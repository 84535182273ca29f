"""MaskedNCC's batched scores: every channel's NCC and overlap to the bit of the plain formula,
each correlation its own transform (Padfield 2012), whatever the channels share."""

from __future__ import annotations

import numpy as np
from scipy import fft, ndimage

from plotmosaic.align.rasters import MaskedNCC, Raster


def _raster(rng: np.random.Generator, shape: tuple[int, int], origin: float) -> Raster:
    seen = (ndimage.gaussian_filter(rng.random(shape), 3) > 0.48).astype(np.float64)
    ground = (rng.random(shape) > 0.3).astype(np.float64)
    images = {
        "stems": ndimage.gaussian_filter((rng.random(shape) > 0.9).astype(float), 1.0),
        "canopy": ndimage.gaussian_filter((rng.random(shape) > 0.6).astype(float), 1.0),
        "terrain": rng.normal(0.0, 2.0, shape) * ground,
    }
    # stems and canopy share one mask array, as `rasterise` builds them
    masks = {"stems": seen, "canopy": seen, "terrain": ground}
    return Raster(np.array([origin, -origin]), 1.0, images, masks)


def _plain(ncc: MaskedNCC, source: Raster, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The masked NCC of one channel, one transform per spectrum and per correlation."""

    def f(a):
        return fft.rfft2(a.astype(np.float32)[None], s=ncc.shape, axes=(-2, -1))[0]

    def corr(a, b):
        return fft.irfft2((np.conj(a) * b)[None], s=ncc.shape, axes=(-2, -1))[0]

    fs, gs = (r.images[name] * r.masks[name] for r in (source, ncc.target))
    m1, m2 = f(source.masks[name]), f(ncc.target.masks[name])
    ff, fff, fg, fgg = f(fs), f(fs * fs), f(gs), f(gs * gs)
    overlap = np.round(corr(m1, m2))
    s_f, s_g, s_ff, s_gg, s_fg = (
        corr(ff, m2),
        corr(m1, fg),
        corr(fff, m2),
        corr(m1, fgg),
        corr(ff, fg),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        num = s_fg - s_f * s_g / overlap
        den = np.sqrt(
            np.clip(s_ff - s_f**2 / overlap, 0, None) * np.clip(s_gg - s_g**2 / overlap, 0, None)
        )
        out = np.where((overlap >= ncc.min_overlap) & (den > 1e-9), num / den, 0.0)
    return np.clip(out, -1.0, 1.0), overlap


def test_batched_scores_are_the_plain_formula_to_the_bit():
    rng = np.random.default_rng(7)
    target = _raster(rng, (70, 90), 0.0)
    ncc = MaskedNCC(target, (60, 50), min_overlap=200, workers=1)
    for k, names in enumerate([["stems", "canopy", "terrain"], ["terrain", "stems"], ["canopy"]]):
        source = _raster(rng, (60, 50), 10.0 * k)
        got = ncc.scores(source, names)
        assert list(got) == names
        for name in names:
            want = _plain(ncc, source, name)
            assert got[name][0].dtype == want[0].dtype and got[name][1].dtype == want[1].dtype
            assert got[name][0].tobytes() == want[0].tobytes()
            assert got[name][1].tobytes() == want[1].tobytes()
            assert np.abs(got[name][0]).max() > 0.05  # scores, not an empty overlap

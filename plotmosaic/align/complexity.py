"""Structural-complexity levels (paper Sec. 2.1-2.2): grouping, SC per level (eq. 2), matching (eq. 3).

Two grouping signals, selectable with `AlignConfig.complexity`:
- "vmf": the paper's path, a K-component mixture of (axial) vMF distributions on the normals.
- "vmf+eigen": the same mixture, each component also carrying a diagonal Gaussian over local
  features of the 0.5 m neighbourhood (linearity, planarity, scattering, verticality of the main
  axis; normals.level_shape). Normals alone cannot tell a stem's horizontal normals from foliage's
  random ones; the features can (a stem is a vertical line at 0.5 m, ground a level plane, foliage
  a scatter), while the vMF part keeps ground (vertical normals) apart from stems.
Both fit EM on a subsample drawn at the delta0 cloud's density (`weights`), as the paper fits all
delta0 points, and label every point of the (spatially even) level sample.
"vmf": SC of level k is eq. 2 (averaged per point so scans of different density compare), levels
ordered from the most compact (highest SC) and matched on log-compressed SC.
"vmf+eigen": complexity of a level is its entropy under the joint model (vMF part + features),
used both to order and to match; eq. 2 SC is still reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from plotmosaic.align import vmf
from plotmosaic.align.normals import LEVEL_FEATURE_NAMES
from plotmosaic.config.align import VmfConfig

VAR_FLOOR = 1e-4


@dataclass(frozen=True, kw_only=True)
class LevelFit:
    """How the levels are fitted: how many, on which grouping signal, the mixture's settings, the seed."""

    k: int
    mode: str  # AlignConfig.complexity: "vmf" or "vmf+eigen"
    config: VmfConfig
    seed: int


@dataclass(frozen=True, kw_only=True, eq=False)
class Levels:
    labels: np.ndarray  # (N,) 0..K-1, 0 = least complex
    stats: list[dict]  # per level: size, kappa, mu, weight, sc, sc_sum, complexity, features


def _gauss_log(f: np.ndarray, resp: np.ndarray):
    """Refit per-component diagonal Gaussians on the features; return (N, K) log densities and params."""
    nk = resp.sum(axis=0) + 1e-12
    mean = (resp.T @ f) / nk[:, None]
    var = np.maximum((resp.T @ f**2) / nk[:, None] - mean**2, VAR_FLOOR)
    return _gauss_logpdf(f, mean, var), mean, var


def _gauss_logpdf(f: np.ndarray, mean: np.ndarray, var: np.ndarray) -> np.ndarray:
    """(N, K) log densities of diagonal Gaussians (column loops: short-axis reductions are slow in numpy)."""
    logp = np.empty((len(f), len(mean)))
    for j in range(len(mean)):
        acc = np.full(len(f), -0.5 * float(np.log(2 * np.pi * var[j]).sum()))
        for c in range(f.shape[1]):
            acc -= 0.5 * (f[:, c] - mean[j, c]) ** 2 / var[j, c]
        logp[:, j] = acc
    return logp


def _sq_dist(z: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N, K) squared distances (column loops, as in _gauss_logpdf)."""
    out = np.zeros((len(z), len(c)))
    for j in range(len(c)):
        for d in range(z.shape[1]):
            out[:, j] += (z[:, d] - c[j, d]) ** 2
    return out


def _kmeans_resp(z: np.ndarray, k: int, rng: np.random.Generator, iters: int = 30) -> np.ndarray:
    """Seeded k-means++ on a small descriptor, as hard initial responsibilities."""
    centres = [z[rng.integers(len(z))]]
    for _ in range(1, k):
        d = _sq_dist(z, np.array(centres)).min(axis=1)
        centres.append(
            z[rng.choice(len(z), p=d / d.sum())] if d.sum() > 0 else z[rng.integers(len(z))]
        )
    c = np.array(centres)
    for _ in range(iters):
        lab = np.argmin(_sq_dist(z, c), axis=1)
        counts = np.bincount(lab, minlength=k)
        sums = np.stack(
            [np.bincount(lab, weights=z[:, d], minlength=k) for d in range(z.shape[1])], axis=1
        )
        c = np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], c)
    resp = np.full((len(z), k), 1e-3)
    resp[np.arange(len(z)), lab] = 1.0
    return resp / resp.sum(axis=1, keepdims=True)


def fit_levels(
    normals: np.ndarray,
    features: np.ndarray,
    k: int,
    mode: str,
    config: VmfConfig,
    seed: int,
    valid: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> Levels:
    """Group points into k complexity levels; EM on a seeded subsample, then every point labelled.

    Points without a plane (`valid` False; by default scattering == 1) have no normal: they stay out
    of the fit and join the most complex level. `weights`: the subsample is drawn with probability
    proportional to them (how many points each one stands for).
    """
    valid = features[:, 2] < 1.0 if valid is None else np.asarray(valid, dtype=bool)
    if valid.sum() < max(10, 3 * k):
        valid = np.ones(len(normals), dtype=bool)
    w = None if weights is None else np.asarray(weights, dtype=np.float64)[valid]
    fit = LevelFit(k=k, mode=mode, config=config, seed=seed)
    levels = _fit_valid(normals[valid], features[valid], w, fit)
    labels = np.full(len(normals), levels.stats[-1]["level"] if levels.stats else 0, dtype=np.int64)
    labels[valid] = levels.labels
    if not valid.all():
        last = levels.stats[-1]
        last["size"] = int((labels == last["level"]).sum())
        last["no_plane"] = int((~valid).sum())
    return Levels(labels=labels, stats=levels.stats)


def _fit_valid(
    normals: np.ndarray, features: np.ndarray, weights: np.ndarray | None, fit: LevelFit
) -> Levels:
    """`fit_levels` on the points that have a plane."""
    k, mode, config, seed = fit.k, fit.mode, fit.config, fit.seed
    n = len(normals)
    rng = np.random.default_rng(seed)
    p = None if weights is None or weights.sum() <= 0 else weights / weights.sum()
    idx = (
        np.sort(rng.choice(n, size=config.sample_size, replace=False, p=p))
        if n > config.sample_size
        else np.arange(n)
    )
    x, f = normals[idx], features[idx]
    if k <= 1:
        # a single component needs no restarts
        mix = vmf.fit_vmf_mixture(x, 1, config.model_copy(update={"n_init": 1}), seed)
        labels = np.zeros(n, dtype=np.int64)
        labels, stats = _order(normals, features, labels, mix.mu, mix.kappa, mix.weights, mode)
        return Levels(labels=labels, stats=stats)
    if mode == "vmf":
        mix = vmf.fit_vmf_mixture(x, k, config, seed)
        mu, kappa, weights = mix.mu, mix.kappa, mix.weights
        labels = mix.predict(normals)
    elif mode == "vmf+eigen":
        best = None
        # descriptor for the start: |n_z| (ground vs stems) and the eigen-features
        z = np.column_stack([np.abs(x[:, 2]), f])
        for _ in range(max(1, config.n_init)):
            resp0 = _kmeans_resp(z, k, rng)

            def extra(resp):
                return _gauss_log(f, resp)[0]

            mu, kappa, weights, resp, ll, _ = vmf.em(
                x, resp0, extra, config.max_iter, config.tol, config.kappa_max
            )
            if best is None or ll > best[-1]:
                best = (mu, kappa, weights, resp, ll)
        mu, kappa, weights, resp, _ = best
        _, gmean, gvar = _gauss_log(f, resp)
        labels = np.empty(n, dtype=np.int64)
        for s in range(0, n, 1_000_000):
            ns, fs = normals[s : s + 1_000_000], features[s : s + 1_000_000]
            joint = (
                vmf.log_density(ns, mu, kappa)
                + np.log(weights + 1e-300)[None]
                + _gauss_logpdf(fs, gmean, gvar)
            )
            labels[s : s + 1_000_000] = np.argmax(joint, axis=1)
    else:
        raise ValueError(f"unknown complexity signal {mode!r}")
    labels, stats = _order(normals, features, labels, mu, kappa, weights, mode)
    return Levels(labels=labels, stats=stats)


def structural_complexity(normals: np.ndarray, mu: np.ndarray, kappa: float) -> tuple[float, float]:
    """Eq. 2 for one level: sum_i p log p with p the level's vMF density; (per-point mean, sum)."""
    if len(normals) == 0:
        return float("nan"), 0.0
    logp = vmf.log_density(normals, mu[None], np.array([kappa]))[:, 0]
    plogp = np.exp(logp) * logp
    return float(plogp.mean()), float(plogp.sum())


def level_entropy(normals: np.ndarray, features: np.ndarray, mu: np.ndarray, kappa: float) -> float:
    """Entropy (nats) of a level under the joint model: -mean log vMF(n) + Gaussian entropy of the features.

    Higher = more complex. Foliage and stems both have spread-out normals (similar kappa, similar eq. 2
    SC) but foliage's features vary far more, so this separates them where SC alone ties.
    """
    if len(normals) < 2:
        return float("inf")
    h_vmf = -float(vmf.log_density(normals, mu[None], np.array([kappa]))[:, 0].mean())
    var = np.maximum(features.var(axis=0), VAR_FLOOR)
    return h_vmf + float(0.5 * np.log(2 * np.pi * np.e * var).sum())


def _stats(normals, features, labels, mu, kappa, weights, mode="vmf") -> list[dict]:
    out = []
    for j in range(len(kappa)):
        sel = labels == j
        sc, sc_sum = structural_complexity(normals[sel], mu[j], kappa[j])
        if mode == "vmf":  # the paper: eq. 2, compared on a log scale (see compress_sc)
            complexity = -sc if np.isfinite(sc) else float("inf")
            match_value = float(compress_sc(np.array(sc))) if np.isfinite(sc) else float("nan")
        else:
            complexity = level_entropy(normals[sel], features[sel], mu[j], kappa[j])
            match_value = complexity if np.isfinite(complexity) else float("nan")
        out.append(
            {
                "size": int(sel.sum()),
                "kappa": float(kappa[j]),
                "mu": [float(v) for v in mu[j]],
                "weight": float(weights[j]),
                "sc": sc,
                "sc_sum": sc_sum,
                "complexity": complexity,
                "match_value": match_value,
                "features": {
                    name: float(features[sel, i].mean()) if sel.any() else float("nan")
                    for i, name in enumerate(LEVEL_FEATURE_NAMES[: features.shape[1]])
                },
            }
        )
    return out


def _order(normals, features, labels, mu, kappa, weights, mode="vmf"):
    """Relabel so level 0 is the least complex; empty levels go last."""
    stats = _stats(normals, features, labels, mu, kappa, weights, mode)
    order = sorted(range(len(stats)), key=lambda j: stats[j]["complexity"])
    remap = np.empty(len(order), dtype=np.int64)
    remap[order] = np.arange(len(order))
    new = [stats[j] for j in order]
    for i, s in enumerate(new):
        s["level"] = i
    return remap[labels], new


def compress_sc(sc: np.ndarray) -> np.ndarray:
    """sign(SC) log(1 + |SC|): SC grows like kappa log kappa for compact levels, so the same ground
    seen by TLS (kappa ~ 180) and ALS (kappa ~ 120) differs by more than stems differ from foliage
    on the raw scale; on this scale the distances in eq. 3 follow the ordering of complexity."""
    return np.sign(sc) * np.log1p(np.abs(sc))


def match_levels(
    sc_source: list[float], sc_target: list[float], compress: bool = True
) -> dict[int, int]:
    """Eq. 3: one-to-one assignment minimising sum |SC_s(k) - SC_t(k')| (exact, Hungarian).

    `compress`: compare eq. 2 values on the log scale of `compress_sc` (False: values already are).

    With different K (e.g. TLS 3 vs ALS 2) the rectangular problem matches min(Ks, Kt) levels and
    leaves the rest out of the incremental stage (they still join the final ICP).
    Returns {source level: target level}.
    """
    s = np.asarray(sc_source, dtype=np.float64)
    t = np.asarray(sc_target, dtype=np.float64)
    if compress:
        s, t = compress_sc(s), compress_sc(t)
    cost = np.abs(s[:, None] - t[None, :])
    cost[~np.isfinite(cost)] = 1e12  # empty levels match only when nothing else is left
    rows, cols = linear_sum_assignment(cost)
    return {int(r): int(c) for r, c in zip(rows, cols)}


def level_purity(levels: np.ndarray, truth: np.ndarray, k: int) -> list[dict]:
    """Per level: size, majority class, and purity = share of that class (for simulator labels)."""
    out = []
    for j in range(k):
        sel = truth[levels == j]
        if len(sel) == 0:
            out.append(
                {"level": j, "size": 0, "majority": None, "purity": float("nan"), "classes": {}}
            )
            continue
        vals, counts = np.unique(sel, return_counts=True)
        out.append(
            {
                "level": j,
                "size": int(len(sel)),
                "majority": int(vals[np.argmax(counts)]),
                "purity": float(counts.max() / len(sel)),
                "classes": {int(v): float(c / len(sel)) for v, c in zip(vals, counts)},
            }
        )
    return out

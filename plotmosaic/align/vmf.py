"""Mixture of von Mises-Fisher distributions on axial data (surface normals), fitted by EM.

Normals are axial: n and -n describe the same plane, and the sign Open3D returns is arbitrary.
Folding them onto one hemisphere would cut the horizontal normals of stems in two along the
equator, so instead each component is the antipodally symmetric vMF

    f(x | mu, kappa) = c3(kappa) * cosh(kappa mu.x),  c3(kappa) = kappa / (4 pi sinh kappa),

i.e. an equal mixture of vMF(mu) and vMF(-mu). EM treats the sign as one more hidden variable:
the E-step weighs x by tanh(kappa mu.x) (its expected sign) and the M-step is Banerjee et al.
(2005)'s: mu = normalised weighted resultant, kappa ~ R(3 - R^2) / (1 - R^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plotmosaic.config.align import VmfConfig

LOG_4PI = np.log(4.0 * np.pi)


def logsumexp_rows(a: np.ndarray) -> np.ndarray:
    """(N, 1) log sum_k exp a[:, k] for a few columns K (a column loop: numpy's reductions over a
    short last axis, and scipy's logsumexp, are slow here)."""
    m = a[:, 0].copy()
    for j in range(1, a.shape[1]):
        np.maximum(m, a[:, j], out=m)
    m[~np.isfinite(m)] = 0.0
    total = np.zeros(len(a))
    for j in range(a.shape[1]):
        total += np.exp(a[:, j] - m)
    return (m + np.log(total))[:, None]


def log_c3(kappa: np.ndarray) -> np.ndarray:
    """log of the vMF normaliser in 3-D, stable for small and large kappa."""
    kappa = np.asarray(kappa, dtype=np.float64)
    # kappa / sinh(kappa) = 2 kappa exp(-kappa) / (1 - exp(-2 kappa)); -> 1 as kappa -> 0
    small = kappa < 1e-6
    k = np.where(small, 1.0, kappa)
    val = np.log(2.0 * k) - k - np.log1p(-np.exp(-2.0 * k)) - LOG_4PI
    return np.where(small, -LOG_4PI, val)


def log_cosh(a: np.ndarray) -> np.ndarray:
    a = np.abs(a)
    return a + np.log1p(np.exp(-2.0 * a)) - np.log(2.0)


def log_density(x: np.ndarray, mu: np.ndarray, kappa: np.ndarray) -> np.ndarray:
    """(N, K) log f(x_i | mu_k, kappa_k) of the symmetric vMF."""
    return log_c3(kappa)[None, :] + log_cosh((x @ mu.T) * kappa[None, :])


def kappa_from_r(r: np.ndarray, kappa_max: float) -> np.ndarray:
    r = np.clip(r, 1e-9, 1.0 - 1e-9)
    return np.clip(r * (3.0 - r * r) / (1.0 - r * r), 1e-3, kappa_max)


@dataclass(frozen=True)
class VmfMixture:
    mu: np.ndarray  # (K, 3) unit mean axes
    kappa: np.ndarray  # (K,)
    weights: np.ndarray  # (K,)
    log_likelihood: float  # mean per point on the fitting sample
    iterations: int

    def component_log_density(self, x: np.ndarray) -> np.ndarray:
        return log_density(x, self.mu, self.kappa)

    def predict(self, x: np.ndarray, chunk: int = 1_000_000) -> np.ndarray:
        """Hard labels for every point (chunked so 10M points stay light on memory)."""
        out = np.empty(len(x), dtype=np.int64)
        for s in range(0, len(x), chunk):
            xs = x[s : s + chunk]
            out[s : s + chunk] = np.argmax(
                self.component_log_density(xs) + np.log(self.weights)[None, :], axis=1
            )
        return out


def m_step(x: np.ndarray, resp: np.ndarray, mu: np.ndarray, kappa: np.ndarray, kappa_max: float):
    """Weighted Banerjee M-step with the hidden sign's expectation tanh(kappa mu.x)."""
    nk = resp.sum(axis=0) + 1e-12
    sign = np.tanh((x @ mu.T) * kappa[None, :])  # (N, K)
    resultant = (resp * sign).T @ x  # (K, 3)
    norm = np.linalg.norm(resultant, axis=1) + 1e-12
    mu_new = resultant / norm[:, None]
    kappa_new = kappa_from_r(norm / nk, kappa_max)
    return mu_new, kappa_new, nk / nk.sum()


def _init_axes(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ on axes: spread the initial means by 1 - (x.mu)^2."""
    mu = [x[rng.integers(len(x))]]
    for _ in range(1, k):
        d = 1.0 - np.max((x @ np.array(mu).T) ** 2, axis=1)
        p = np.clip(d, 0, None)
        p = p / p.sum() if p.sum() > 0 else None
        mu.append(x[rng.choice(len(x), p=p)])
    return np.array(mu)


def em(
    x: np.ndarray,
    resp: np.ndarray,
    log_extra,
    max_iter: int,
    tol: float,
    kappa_max: float,
    mu=None,
    kappa=None,
):
    """EM from initial responsibilities. `log_extra(resp) -> (N, K)` adds other per-component
    log-densities (eigen-features in the joint model) and refits them; None for plain vMF."""
    k = resp.shape[1]
    if mu is None:
        mu = np.tile([0.0, 0.0, 1.0], (k, 1))
        kappa = np.ones(k)
        # one sign-free pass: resultant of the axis outer products' principal direction
        for j in range(k):
            scatter = (resp[:, j, None] * x).T @ x
            mu[j] = np.linalg.eigh(scatter)[1][:, -1]
    prev = -np.inf
    it = 0
    ll = -np.inf
    for it in range(1, max_iter + 1):  # noqa: B007 (returned: iterations used)
        mu, kappa, weights = m_step(x, resp, mu, kappa, kappa_max)
        joint = log_density(x, mu, kappa) + np.log(weights + 1e-300)[None, :]
        if log_extra is not None:
            joint = joint + log_extra(resp)
        norm = logsumexp_rows(joint)
        resp = np.exp(joint - norm)
        ll = float(norm.mean())
        if abs(ll - prev) <= tol * max(1.0, abs(ll)):
            break
        prev = ll
    return mu, kappa, weights, resp, ll, it


def fit_vmf_mixture(
    x: np.ndarray, k: int, config: VmfConfig | None = None, seed: int = 0
) -> VmfMixture:
    """Fit K symmetric vMF components to unit axes x (N, 3); best of `config.n_init` seeded restarts."""
    config = config or VmfConfig()
    x = np.asarray(x, dtype=np.float64)
    rng = np.random.default_rng(seed)
    best = None
    for _ in range(config.n_init):
        mu0 = _init_axes(x, k, rng)
        kappa0 = np.full(k, 5.0)
        logr = log_density(x, mu0, kappa0)
        resp = np.exp(logr - logsumexp_rows(logr))
        mu, kappa, weights, _, ll, it = em(
            x, resp, None, config.max_iter, config.tol, config.kappa_max, mu0, kappa0
        )
        if best is None or ll > best.log_likelihood:
            best = VmfMixture(mu, kappa, weights, ll, it)
    return best

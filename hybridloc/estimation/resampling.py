"""Resampling schemes of the particle filters, one signature: ``idx = scheme(w, rng, m=None)`` with
``w`` the normalised weights (N,) and ``idx`` (M,) the indices of the particles drawn (M = ``m``, N when
None), each particle i drawn E[N_i] = M w_i times on average (as nchopin/particles' ``resampling``,
``A = rs.scheme(W, M=None)``). Schemes differ in the variance of N_i (Douc, Cappe & Moulines 2005):
multinomial > stratified >= systematic; residual sits below multinomial. And log-weight helpers: a
filter keeps log w and normalises with logsumexp, so a product of many small likelihoods never
underflows to an all-zero cloud.

KLD-sampling (Fox 2003, "Adapting the sample size in particle filters through KLD-sampling"): how
many particles M the cloud needs so that, with probability 1 - delta, the Kullback-Leibler divergence
between the sample-based estimate and the true posterior (both taken over a grid of bins) stays below
epsilon. With k the number of bins the sample occupies (Fox eq. 7, the Wilson-Hilferty approximation
of the chi-square quantile with k - 1 degrees of freedom)::

    M = (k - 1) / (2 epsilon) * {1 - 2 / (9 (k - 1)) + sqrt(2 / (9 (k - 1))) z_{1-delta}}^3

Samples are drawn one at a time from the weighted cloud and the count k grows as they fall into new
bins; drawing stops at the first M with M >= the bound of its own k (:func:`kld_size`). A concentrated
cloud occupies few bins and gets few particles; a spread one (a cold start) many.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.special import logsumexp
from scipy.stats import norm

Resampler = Callable[..., np.ndarray]  # (w, rng, m=None) -> indices


def log_normalise(logw: np.ndarray) -> tuple[np.ndarray, float]:
    """(log w - logsumexp(log w), logsumexp(log w)); the total is -inf when every weight is zero."""
    total = float(logsumexp(logw))
    if not np.isfinite(total):
        return logw, total
    return logw - total, total


def _inverse_cdf(w: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Particle indices at cumulative-weight positions ``u`` in [0, 1) (the last sum is forced to 1)."""
    c = np.cumsum(w)
    c[-1] = 1.0
    return np.searchsorted(c, u)


def systematic(w: np.ndarray, rng: np.random.Generator, m: int | None = None) -> np.ndarray:
    """One uniform offset for M evenly spaced positions (u_k = (U + k) / M)."""
    m = len(w) if m is None else int(m)
    return _inverse_cdf(w, (rng.random() + np.arange(m)) / m)


def stratified(w: np.ndarray, rng: np.random.Generator, m: int | None = None) -> np.ndarray:
    """One uniform per stratum [k / M, (k + 1) / M)."""
    m = len(w) if m is None else int(m)
    return _inverse_cdf(w, (rng.random(m) + np.arange(m)) / m)


def multinomial(w: np.ndarray, rng: np.random.Generator, m: int | None = None) -> np.ndarray:
    """M independent draws (sorted positions, so the result is ordered like the others)."""
    m = len(w) if m is None else int(m)
    return _inverse_cdf(w, np.sort(rng.random(m)))


def residual(w: np.ndarray, rng: np.random.Generator, m: int | None = None) -> np.ndarray:
    """floor(M w_i) copies of each particle, the remaining R = M - sum floor(M w_i) drawn multinomially
    from the leftovers M w_i - floor(M w_i) (Liu & Chen 1998). M may differ from N = len(w) (KLD-sampling
    changes the count): the copies are of the N particles."""
    m = len(w) if m is None else int(m)
    mw = m * np.asarray(w, dtype=float)
    copies = np.floor(mw).astype(int)
    idx = np.repeat(np.arange(len(w)), copies)
    rest = m - len(idx)
    if rest > 0:
        left = mw - copies
        left = left / left.sum()
        idx = np.concatenate([idx, _inverse_cdf(left, np.sort(rng.random(rest)))])
    return idx


def kld_bound(k, epsilon: float, delta: float) -> np.ndarray:
    """Fox 2003 eq. 7: the particles needed for k occupied bins (module docstring); 0 for k <= 1."""
    if not (epsilon > 0 and 0 < delta < 1):
        raise ValueError(f"KLD-sampling needs epsilon > 0 and delta in (0, 1), got {epsilon}, {delta}")
    k = np.asarray(k, float)
    km1 = np.maximum(k - 1.0, 1.0)
    a = 2.0 / (9.0 * km1)
    z = float(norm.ppf(1.0 - delta))
    return np.where(k > 1, km1 / (2.0 * epsilon) * (1.0 - a + np.sqrt(a) * z) ** 3, 0.0)


def kld_size(keys: np.ndarray, epsilon: float, delta: float, n_min: int = 1) -> int:
    """The sample size KLD-sampling stops at, given the bins ``keys`` (L,) of samples in the order they
    were drawn (independent draws): the first M >= ``n_min`` with M >= :func:`kld_bound` of k(M), the
    bins occupied by the first M samples; L when no prefix satisfies it (draw more, or stop at the cap)."""
    keys = np.asarray(keys)
    n = len(keys)
    if n == 0:
        return 0
    _, first = np.unique(keys, return_index=True)
    new = np.zeros(n)
    new[first] = 1.0
    k = np.cumsum(new)  # bins occupied after 1, 2, ..., L samples
    m = np.arange(1, n + 1)
    ok = (m >= kld_bound(k, epsilon, delta)) & (m >= n_min)
    hit = np.flatnonzero(ok)
    return int(hit[0]) + 1 if hit.size else n


def kld_grow(draw: Callable[[int], np.ndarray], m0: int, epsilon: float, delta: float, n_min: int, n_max: int) -> int:
    """KLD-sampling's sample size, drawn in doubling batches: ``draw(k)`` draws k more samples (the
    caller keeps them) and returns their bins; from ``m0`` samples on, the count doubles until
    :func:`kld_size` stops inside what was drawn, or ``n_max`` is reached. Returns the size, <= n_max
    (the caller keeps that many of its samples, in draw order)."""
    m = m0
    keys = np.zeros(0, np.int64)
    while True:
        keys = np.concatenate([keys, draw(m - len(keys))])
        n = kld_size(keys, epsilon, delta, n_min)
        if n < m or m >= n_max:
            return min(n, n_max)
        m = min(2 * m, n_max)


def bin_keys(xy: np.ndarray, heading: np.ndarray, bin_xy: float, bin_heading: float) -> np.ndarray:
    """One integer per (x, y, heading) bin of a grid of ``bin_xy`` m squares and ``bin_heading`` rad
    sectors (KLD-sampling's bins): (N,) int64, equal for points in the same bin."""
    ix = np.floor(np.asarray(xy[:, 0]) / bin_xy).astype(np.int64) + (1 << 20)
    iy = np.floor(np.asarray(xy[:, 1]) / bin_xy).astype(np.int64) + (1 << 20)
    h = np.mod(np.asarray(heading, float), 2.0 * np.pi)
    ih = np.floor(h / bin_heading).astype(np.int64)
    if np.any((ix < 0) | (ix >= 1 << 21) | (iy < 0) | (iy >= 1 << 21)) or bin_heading < 2.0 * np.pi / 1000:
        raise ValueError("KLD bins: positions beyond +-2^20 bins of the origin or heading bins finer than 0.36 deg")
    return (ix << 31) | (iy << 10) | ih


RESAMPLERS: dict[str, Resampler] = {"systematic": systematic, "stratified": stratified, "multinomial": multinomial, "residual": residual}


def resampler(scheme: str | Resampler) -> Resampler:
    """A resampler by name (``RESAMPLERS``) or the callable itself."""
    if callable(scheme):
        return scheme
    try:
        return RESAMPLERS[scheme]
    except KeyError:
        raise ValueError(f"unknown resampler {scheme!r}; choose one of {sorted(RESAMPLERS)}") from None

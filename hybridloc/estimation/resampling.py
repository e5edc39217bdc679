"""Resampling schemes of the particle filters, one signature: ``idx = scheme(w, rng)`` with ``w`` the
normalised weights (N,) and ``idx`` (N,) the indices of the particles drawn, each particle i drawn
E[N_i] = N w_i times on average (as nchopin/particles' ``resampling``). Schemes differ in the variance
of N_i (Douc, Cappe & Moulines 2005): multinomial > stratified >= systematic; residual sits below
multinomial. And log-weight helpers: a filter keeps log w and normalises with logsumexp, so a product
of many small likelihoods never underflows to an all-zero cloud.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.special import logsumexp

Resampler = Callable[[np.ndarray, np.random.Generator], np.ndarray]


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


def systematic(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One uniform offset for N evenly spaced positions (u_k = (U + k) / N)."""
    n = len(w)
    return _inverse_cdf(w, (rng.random() + np.arange(n)) / n)


def stratified(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One uniform per stratum [k / N, (k + 1) / N)."""
    n = len(w)
    return _inverse_cdf(w, (rng.random(n) + np.arange(n)) / n)


def multinomial(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """N independent draws (sorted positions, so the result is ordered like the others)."""
    n = len(w)
    return _inverse_cdf(w, np.sort(rng.random(n)))


def residual(w: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """floor(N w_i) copies of each particle, the remaining R = N - sum floor(N w_i) drawn multinomially
    from the leftovers N w_i - floor(N w_i) (Liu & Chen 1998)."""
    n = len(w)
    nw = n * np.asarray(w, dtype=float)
    copies = np.floor(nw).astype(int)
    idx = np.repeat(np.arange(n), copies)
    rest = n - len(idx)
    if rest > 0:
        left = nw - copies
        left = left / left.sum()
        idx = np.concatenate([idx, _inverse_cdf(left, np.sort(rng.random(rest)))])
    return idx


RESAMPLERS: dict[str, Resampler] = {"systematic": systematic, "stratified": stratified, "multinomial": multinomial, "residual": residual}


def resampler(scheme: str | Resampler) -> Resampler:
    """A resampler by name (``RESAMPLERS``) or the callable itself."""
    if callable(scheme):
        return scheme
    try:
        return RESAMPLERS[scheme]
    except KeyError:
        raise ValueError(f"unknown resampler {scheme!r}; choose one of {sorted(RESAMPLERS)}") from None

"""Kourogi's GPS differential mode (eqs 17-18) as a pairing rule over the GPS fixes a filter accepts.

Two accepted GPS fixes (inside the 95 % region of the dead-reckoned estimate, i.e. free of
multipath) taken ``min_dt``-``max_dt`` seconds apart are differenced: their biased error e_b,
locally constant for one satellite set (eq 8), cancels, and the difference measures the walker's
displacement with the random errors only, cov = sigma_r(a)^2 I + sigma_r(b)^2 I (eq 18, with the
time uncertainty c folded in: fix times are the receiver's own). Pairs far apart in time are not
used: the bias drifts and the walker may not have gone straight, as Kourogi notes.
"""

from __future__ import annotations

import numpy as np

from ..types import AbsoluteFix, DisplacementFix, FixSource


class GpsDifferencer:
    def __init__(self, min_dt: float = 1.0, max_dt: float = 10.0):
        self.min_dt, self.max_dt = min_dt, max_dt
        self._last: tuple[AbsoluteFix, float] | None = None

    def push(self, fix: AbsoluteFix, sigma_random: float | None, accepted: bool) -> DisplacementFix | None:
        """Offer the next GPS fix (and whether the filter accepted it); the displacement since the
        previous accepted one when the pair qualifies, else None."""
        if fix.source is not FixSource.GPS or not accepted or sigma_random is None:
            return None
        prev, self._last = self._last, (fix, sigma_random)
        if prev is None:
            return None
        a, sa = prev
        dt = fix.t - a.t
        if not self.min_dt <= dt <= self.max_dt:
            return None
        delta = np.asarray(fix.pos_enu, float)[:2] - np.asarray(a.pos_enu, float)[:2]
        return DisplacementFix(a.t, fix.t, delta, np.eye(2) * (sa**2 + sigma_random**2), FixSource.GPS)

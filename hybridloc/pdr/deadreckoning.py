"""Dead reckoning, written once: steps in, positions and their covariance out, position at any time.

A step of length l_i and heading psi_i moves the walker from p_{i-1} to

    p_i = p_{i-1} + l_i (cos psi_i, sin psi_i)                                (Kourogi et al. 2006, eq 12)

and, the steps' errors being independent, the position covariance grows by each step's
displacement covariance (:meth:`~hybridloc.types.StepEvent.displacement_covariance`, eqs 11-14):

    C_i = C_{i-1} + A_i diag(sigma_l^2, (l tan sigma_psi)^2) A_i^T,  A_i = [d_i d_i_perp]    (eq 13)

For n equal steps along one heading the along-track variance is n sigma_l^2 and the cross-track one
n (l tan sigma_psi)^2. This is the PDR's own track: the filters in :mod:`hybridloc.fusion` add heading
bias and step scale on top (and the Kalman filter takes the heading-change sigma, since it carries
the bias as a state); here the absolute heading's sigma is the direction error, as in Kourogi.

Arithmetic: the positions are a running sum in step order, ``x_i = x_{i-1} + l_i cos psi_i`` with
``math.cos`` (the same bits as ``numpy.cumsum`` of ``StepEvent.displacement_enu`` from a zero start,
and as a running sum from any start), so every tool that dead-reckons gets the same last digits.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from ..types import StepEvent, Trajectory

#: Default start of a batch track: this long before the first step (the walker stood at the start
#: position until then; the batch tools of hybridloc have always started their tracks so).
START_BEFORE_FIRST_STEP = 1.0  # s


class DeadReckoning:
    """The positions after each step of a walk, with their covariance growth (module docstring).

    Rows: an optional start row ``(t0, pos0, cov0)`` and one row per step (its time, the position
    after it and the covariance then). Step times must be strictly increasing (and after ``t0``).

    ``position_at(t)`` interpolates linearly in time between rows (``numpy.interp``: the walker moves
    at constant velocity over each step), and **holds** outside them: before the first row the
    walker is at the first row's position (the start), after the last row at the last position (it
    stopped after its last step). :meth:`covers` says whether a time lies within the rows.

    Streaming use (a live client): ``DeadReckoning(t0=None)`` has no start row (its start time is
    unknown): the track begins at the first step, ``pos0`` plus that step's displacement; ``max_rows``
    bounds the history (when it is exceeded the oldest half is dropped, amortised O(1) per step).

    Parameters
    ----------
    t0 : float or None
        Time of the start position, s; None when unknown (no start row).
    pos0 : (2,) array_like
        Start position in the site frame, m.
    cov0 : (2, 2) array_like or None
        Start covariance, m^2 (default zero: the track is relative to the start).
    covariance : bool
        Whether to accumulate the covariance (eq 13); a caller that needs positions only saves the work.
    max_rows : int or None
        Bound of the kept history, rows (None: keep all).
    """

    def __init__(self, t0: float | None = None, pos0: Sequence[float] = (0.0, 0.0), cov0=None, covariance: bool = True, max_rows: int | None = None):
        if t0 is not None and not math.isfinite(t0):
            raise ValueError(f"DeadReckoning: start time t0 must be finite, got {t0!r}")
        x0, y0 = (float(v) for v in np.asarray(pos0, dtype=float).reshape(2))
        if not (math.isfinite(x0) and math.isfinite(y0)):
            raise ValueError(f"DeadReckoning: start position must be finite, got {(x0, y0)!r}")
        C0 = np.zeros((2, 2)) if cov0 is None else np.array(cov0, dtype=float).reshape(2, 2)
        if max_rows is not None and max_rows < 2:
            raise ValueError("DeadReckoning: max_rows must be at least 2")
        self._xy = (x0, y0)  # position after the last step (or the start)
        self._C: np.ndarray | None = C0 if covariance else None
        self.max_rows = max_rows
        self.n_steps = 0
        self._t: list[float] = []
        self._pos: list[tuple[float, float]] = []
        self._cov: list[np.ndarray] = []
        self._arrays: tuple | None = None
        if t0 is not None:
            self._append_row(float(t0))

    # ------------------------------------------------------------------ building
    @classmethod
    def from_steps(
        cls, steps: Iterable[StepEvent], pos0: Sequence[float] = (0.0, 0.0), t0: float | None = None, cov0=None, covariance: bool = True
    ) -> DeadReckoning:
        """The track of a whole walk, from ``pos0`` at ``t0`` (default :data:`START_BEFORE_FIRST_STEP` s
        before the first step; with no steps and no ``t0``, a track with no rows, which holds ``pos0``)."""
        steps = list(steps)
        if t0 is None and steps:
            t0 = steps[0].t - START_BEFORE_FIRST_STEP
        dr = cls(t0, pos0, cov0, covariance)
        dr.extend(steps)
        return dr

    @classmethod
    def from_lengths_headings(
        cls, t: Sequence[float], lengths: Sequence[float], headings: Sequence[float], pos0: Sequence[float] = (0.0, 0.0), t0: float | None = None
    ) -> DeadReckoning:
        """The track of steps given as arrays (s, m, rad): the same steps with other lengths (a length
        model) or headings (another attitude estimator). Positions only: without the steps' sigmas
        there is no covariance. ``t0`` as in :meth:`from_steps`."""
        t, L, h = (np.asarray(a, dtype=float).reshape(-1) for a in (t, lengths, headings))
        if not (len(t) == len(L) == len(h)):
            raise ValueError(f"DeadReckoning: {len(t)} step times, {len(L)} lengths and {len(h)} headings")
        for name, a in (("step times", t), ("lengths", L), ("headings", h)):
            if not np.all(np.isfinite(a)):
                raise ValueError(f"DeadReckoning: non-finite {name} (index {int(np.argmin(np.isfinite(a)))})")
        if t0 is None and len(t):
            t0 = float(t[0]) - START_BEFORE_FIRST_STEP
        dr = cls(t0, pos0, covariance=False)
        for ti, li, hi in zip(t.tolist(), L.tolist(), h.tolist()):
            dr._advance(ti, li, hi, None)
        return dr

    def add(self, step: StepEvent) -> None:
        """Dead-reckon one step (eqs 12-13)."""
        self._advance(step.t, step.length, step.heading, step if self._C is not None else None)

    def extend(self, steps: Iterable[StepEvent]) -> None:
        for s in steps:
            self.add(s)

    def _advance(self, t: float, length: float, heading: float, step: StepEvent | None) -> None:
        if not math.isfinite(t):
            raise ValueError(f"DeadReckoning: step time must be finite, got {t!r}")
        if self._t and t <= self._t[-1]:
            what = "the start time" if self.n_steps == 0 else "the previous step's time"
            raise ValueError(
                f"DeadReckoning: steps must come in strictly increasing time: step {self.n_steps} at t={t!r} is not after {what} {self._t[-1]!r}"
            )
        x, y = self._xy
        self._xy = (x + length * math.cos(heading), y + length * math.sin(heading))  # eq 12
        if step is not None:
            self._C = step.propagate_position_covariance(self._C)  # eq 13
        self.n_steps += 1
        self._append_row(float(t))

    def _append_row(self, t: float) -> None:
        self._t.append(t)
        self._pos.append(self._xy)
        if self._C is not None:
            self._cov.append(self._C)
        if self.max_rows is not None and len(self._t) > self.max_rows:
            k = self.max_rows // 2
            del self._t[:k], self._pos[:k], self._cov[:k]
        self._arrays = None

    # ------------------------------------------------------------------ reading
    def __len__(self) -> int:
        """Number of rows (start row, if any, plus kept steps)."""
        return len(self._t)

    def _as_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        if self._arrays is None:
            t = np.array(self._t, dtype=float)
            p = np.array(self._pos, dtype=float).reshape(-1, 2)
            c = np.array(self._cov, dtype=float).reshape(-1, 2, 2) if self._C is not None else None
            for a in (t, p) + ((c,) if c is not None else ()):
                a.flags.writeable = False
            self._arrays = (t, p, c)
        return self._arrays

    @property
    def t(self) -> np.ndarray:
        """Row times, shape (N,), s."""
        return self._as_arrays()[0]

    @property
    def pos_enu(self) -> np.ndarray:
        """Positions, shape (N, 2), m (site frame)."""
        return self._as_arrays()[1]

    @property
    def cov_enu(self) -> np.ndarray | None:
        """Position covariances, shape (N, 2, 2), m^2; None when not accumulated."""
        return self._as_arrays()[2]

    @property
    def position(self) -> np.ndarray:
        """The current position (after the last step), shape (2,), m."""
        return np.array(self._xy)

    @property
    def t_last(self) -> float | None:
        """Time of the last row, s; None without rows."""
        return self._t[-1] if self._t else None

    def covers(self, t: float) -> bool:
        """Whether time ``t`` lies within the rows (first row's time <= t <= last row's time)."""
        return bool(self._t) and self._t[0] <= t <= self._t[-1]

    def position_at(self, t) -> np.ndarray:
        """Position at time(s) ``t``: shape (2,) for a scalar, (M, 2) for an array of M times, m.

        Linear in time between rows, held before the first and after the last (class docstring); a
        track with no rows holds ``pos0``. Non-finite times raise ValueError."""
        tq = np.asarray(t, dtype=float)
        if not np.all(np.isfinite(tq)):
            raise ValueError("DeadReckoning.position_at: times must be finite")
        tr, p, _ = self._as_arrays()
        if len(tr) == 0:
            return np.broadcast_to(np.array(self._xy), tq.shape + (2,)).copy()
        return np.stack([np.interp(tq, tr, p[:, 0]), np.interp(tq, tr, p[:, 1])], axis=-1)

    def covariance_at(self, t) -> np.ndarray:
        """Position covariance at time(s) ``t``, shape (2, 2) or (M, 2, 2), m^2: that of the last row at
        or before t (a step's uncertainty comes with the step), the first row's before it."""
        tq = np.asarray(t, dtype=float)
        if not np.all(np.isfinite(tq)):
            raise ValueError("DeadReckoning.covariance_at: times must be finite")
        tr, _, c = self._as_arrays()
        if c is None:
            raise ValueError("DeadReckoning.covariance_at: this track does not accumulate covariance")
        if len(tr) == 0:
            return np.broadcast_to(self._C, tq.shape + (2, 2)).copy()
        k = np.clip(np.searchsorted(tr, tq, side="right") - 1, 0, len(tr) - 1)
        return c[k]

    def to_trajectory(self) -> Trajectory:
        """The rows as a :class:`~hybridloc.types.Trajectory` (z = 0; ``sigma_enu`` the square roots
        of the covariance's diagonal, z sigma 0, when accumulated)."""
        tr, p, c = self._as_arrays()
        if len(tr) == 0:
            raise ValueError("DeadReckoning.to_trajectory: the track has no rows (no start time and no steps)")
        pos = np.zeros((len(tr), 3))
        pos[:, :2] = p
        sig = None
        if c is not None:
            sig = np.zeros((len(tr), 3))
            sig[:, :2] = np.sqrt(np.diagonal(c, axis1=1, axis2=2))
        return Trajectory(tr.copy(), pos, sigma_enu=sig)

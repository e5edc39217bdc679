"""Kourogi et al. (2006)'s own Kalman filter: state (x, y, v_x, v_y), steps as observations.

The paper's framework, as written, beside :class:`~.kalman.LocalFusion` (which keeps the position
but replaces the velocity by a heading bias and a step scale). ``hybridloc eval fusion`` runs both on
the same steps and fixes.

* **Projection** (eqs 5-7): s <- F(dt) s, P <- F P F^T + Q, F the constant-velocity model; Q is a
  white-acceleration noise of density ``accel_sigma``^2 (the paper leaves Q open).
* **Step observation** (eq 9): after a step of stride l, azimuth theta and duration T,
  O = (x_prev + l cos theta, y_prev + l sin theta, l cos theta / T, l sin theta / T). Eq 15 gives it
  the covariance of the dead-reckoned position C_i (eqs 11-14) and (sigma_v cos theta)^2,
  (sigma_v sin theta)^2 for the velocity. C_i contains the previous position's own covariance, and O
  is built from that previous position: applied to the state as an independent observation it would
  count the previous position's uncertainty twice and shrink P at every step. So the position part is
  applied as what it is, an observation of the displacement since the previous step, p - p_prev = l d,
  on a stochastic clone of p_prev (the state augmented by the previous position for one update), with
  the step's own covariance A_i diag(sigma_l^2, (l tan sigma_theta)^2) A_i^T (eqs 11-14 without C_i).
  The velocity part is eq 15's, with a small floor where cos or sin theta vanishes.
* **No movement** (eq 10): no step for ``still_after`` s is an observation of zero velocity.
* **Position fix** (eqs 16, 19-20): O = (x_f, y_f, ., .) with infinite variance on the velocity, i.e.
  an observation of the position alone, through the shared gated ``correct`` of
  :class:`~.kalman.LocalFusion` (95 % gate, late fixes against the history, re-initialisation,
  floor tracking).
* **GPS differential mode** (eqs 17-18): two GPS positions t0 < t1 give the velocity
  v_G = (p1 - p0) / (t1 - t0), observed with covariance c (R_1 + R_0 random parts) / (t1 - t0)^2,
  ``c`` for the timing uncertainty (eq 18); used only while t1 is recent (the velocity is now's).

There is no heading-bias state: the filter trusts the PDR's azimuth, as the paper does (its PDR is
magnetometer-aided). A known start heading enters as a fixed rotation of every step's azimuth, and so
does the heading bias of a corrected track (:meth:`~.kalman.LocalFusion.reanchor`, position and
heading only: this state has no step scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..estimation import Measurement
from ..estimation import correct as gated_update
from ..types import DisplacementFix, StepEvent
from .kalman import Estimate, FusionConfig, LocalFusion
from .measurements import CloneStep, Velocity


@dataclass
class KourogiConfig(FusionConfig):
    sigma_v: float = 0.3  # m/s, eq 15: the velocity a step implies (stride and period errors)
    sigma_v_floor: float = 0.05  # m/s, added to each velocity axis so neither is exact
    accel_sigma: float = 1.0  # m/s^2/sqrt(Hz), white acceleration of the projection (Q)
    still_after: float = 2.0  # s without a step: observe zero velocity (eq 10)
    sigma_still: float = 0.05  # m/s, that observation's noise
    step_period: float = 0.55  # s, duration T assumed for a first step (no previous step)
    time_c: float = 2.0  # eq 18's c: timing uncertainty of a GPS difference
    max_diff_age: float = 2.0  # s; a GPS difference older than this is no longer the present velocity
    sigma_v0: float = 1.0  # m/s, initial velocity uncertainty


class KourogiFusion(LocalFusion):
    """State (x, y, v_x, v_y); ``predict(step)`` / ``correct(fix)`` like the other filters."""

    def __init__(
        self,
        config: KourogiConfig | None = None,
        init: tuple[float, float, float] | None = None,
        floor: str | None = None,
        heading_bias: tuple[float, float] | None = None,
    ):
        cfg = config or KourogiConfig()
        super().__init__(cfg, init, floor)
        self.cfg: KourogiConfig = cfg
        pos_var = init[2] ** 2 if init is not None else 1e6
        self.x = np.array([init[0], init[1], 0.0, 0.0]) if init is not None else np.zeros(4)
        self.P = np.diag([pos_var, pos_var, cfg.sigma_v0**2, cfg.sigma_v0**2])
        self.heading_offset = heading_bias[0] if heading_bias is not None else 0.0
        self._last_step_t: float | None = None
        self._tp = -math.inf  # time the velocity was last integrated to (set by the first step)

    def _constrain(self) -> None:  # no scale state to keep physical
        pass

    def _project(self, t: float) -> None:
        """Eqs 5-7: constant-velocity projection from the last projection time ``_tp`` to t.

        The projection clock is the steps' (and pauses'), not ``self.t``: a fix moves the present
        position but not the time the velocity was last integrated to.
        """
        dt = t - self._tp
        if dt <= 0:
            return
        F = np.eye(4)
        F[0, 2] = F[1, 3] = dt
        q = self.cfg.accel_sigma**2
        # white acceleration: Q = q [[dt^3/3, dt^2/2], [dt^2/2, dt]] per axis
        Q = np.zeros((4, 4))
        for i in (0, 1):
            Q[i, i] = q * dt**3 / 3.0
            Q[i, i + 2] = Q[i + 2, i] = q * dt**2 / 2.0
            Q[i + 2, i + 2] = q * dt
        self.x = F @ self.x
        self.P = F @ self.P @ F.T + Q
        self.P = 0.5 * (self.P + self.P.T)
        self._tp = t

    def _observe_velocity(self, v: np.ndarray, R: np.ndarray, kind: str, gate: bool | None = None) -> bool:
        """An observation of the velocity through the filter's one update; ``gate`` True: its 95 % gate."""
        return self.update(Measurement(np.asarray(v, float), Velocity(R, kind)), gate).accepted

    def predict(self, step: StepEvent) -> Estimate:
        self._memory.add(step)
        self._motion(step)
        return self._stepped(step)

    def _motion(self, step: StepEvent) -> None:
        """Eqs 5-15 for one step (eq 10 first after a pause); what :meth:`reanchor` re-applies."""
        cfg = self.cfg
        if self._last_step_t is not None and step.t - self._last_step_t > cfg.still_after:
            self._project(self._last_step_t + cfg.still_after)  # eq 10: no movement observed
            self._observe_velocity(np.zeros(2), np.eye(2) * cfg.sigma_still**2, "still")
        # the step's duration: since the previous step, or - for a first step and the first after a
        # pause, whose start is unknown - a typical step period
        gap = step.t - self._last_step_t if self._last_step_t is not None else math.inf
        T = max(gap, 0.2) if gap <= cfg.still_after else cfg.step_period
        self._last_step_t = step.t
        if not math.isfinite(self._tp) or self._tp >= step.t:
            self._tp = step.t - T  # first step (or a clock that went back): it took T
        # Clone the position before the step, then project the state to the step's time; the clone's
        # cross-covariance moves with the projected state (x' = F x + w, w independent of the clone).
        n = 4
        xa = np.concatenate([self.x, self.x[:2]])
        Pa = np.zeros((n + 2, n + 2))
        F = np.eye(n)
        F[0, 2] = F[1, 3] = step.t - self._tp
        Pa[n:, n:] = self.P[:2, :2]
        Pa[:n, n:] = F @ self.P[:, :2]
        Pa[n:, :n] = Pa[:n, n:].T
        self._project(step.t)
        self.t = step.t  # the estimate is the one at this step (as LocalFusion.predict)
        xa[:n] = self.x
        Pa[:n, :n] = self.P
        # Eq 9 as a displacement and a velocity: z = (l d, l d / T), h = (p - p_prev, v).
        theta = step.heading + self.heading_offset
        d = np.array([math.cos(theta), math.sin(theta)])
        z = np.concatenate([step.length * d, step.length * d / T])
        moved = StepEvent(step.t, step.length, theta, step.sigma_length, step.sigma_heading)
        R = np.zeros((4, 4))
        R[:2, :2] = moved.displacement_covariance()  # eqs 11-14 without C_i (the clone carries it)
        R[2:, 2:] = np.diag((cfg.sigma_v * d) ** 2 + cfg.sigma_v_floor**2)  # eq 15
        # the same one update, on the augmented state (never gated: a step is what the filter runs on)
        dx, Pa, _ = gated_update(xa, Pa, z, CloneStep(R), None, self.stats)
        xa = xa + dx
        self.x, self.P = xa[:n].copy(), Pa[:n, :n].copy()

    def _anchor(self, t: float, pos: np.ndarray, cov: np.ndarray, heading_bias: float | None, scale: float | None) -> None:
        """:meth:`LocalFusion.reanchor`'s state at t for this filter: the smoothed position with its
        covariance (the velocity keeps its present value, uncorrelated with it), the heading bias as the
        fixed rotation of the steps' azimuths; there is no scale state. The projection clock restarts at t."""
        self.x[:2] = pos
        if np.isfinite(cov).all():
            self.P[:2, :2] = cov
        self.P[:2, 2:] = 0.0
        self.P[2:, :2] = 0.0
        if heading_bias is not None:
            self.heading_offset = heading_bias
        last = self._memory.last_at_or_before(t)
        self._last_step_t = last.t if last is not None else None
        self._tp = t

    def _correct_displacement(self, fix: DisplacementFix) -> tuple[bool, Estimate]:
        """Eqs 17-18: the velocity of two GPS positions, while it is still the present one."""
        dt = fix.t1 - fix.t0
        if dt <= 0 or (math.isfinite(self.t) and self.t - fix.t1 > self.cfg.max_diff_age):
            self.n_rejected += 1
            return False, self.estimate("displacement-rejected")
        v = np.asarray(fix.delta_enu, float)[:2] / dt
        R = self.cfg.time_c * np.asarray(fix.cov, float)[:2, :2] / dt**2
        if not self._observe_velocity(v, R, "gps-velocity", True):  # the filter's own 95 % gate
            self.n_rejected += 1
            return False, self.estimate("displacement-rejected")
        return True, self.estimate("displacement")

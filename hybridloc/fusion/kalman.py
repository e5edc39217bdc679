"""Local fusion on the client: steps from any PDR + absolute fixes, in a small Kalman filter.

State (Kourogi et al. 2006 position-domain filter, extended): x = (p_x, p_y, b_psi, s) with p the
position in the site frame (m), b_psi a heading bias (rad) and s a step-length scale (-).

* **Predict with a step** (Kourogi eqs 9-12): p <- p + s L (cos(psi + b_psi), sin(psi + b_psi)), with
  the step's own stride and direction variances entering as process noise (eqs 13-14) and slow random
  walks on b_psi and s. Steps from the phone PDR and from the foot INS (strides) are treated alike.
* **Correct with a fix** (eq 16 family): z = p + noise(R_fix). Every update (fix, displacement,
  corridor heading) goes through :meth:`LocalFusion.update`, i.e. the one gated update of
  :func:`hybridloc.estimation.correct` (Joseph form, NIS, rejections counted per kind in ``stats``),
  with a chi-square gate: a fix outside the 95 % region of the dead-reckoned estimate is rejected
  (Kourogi sec. 3.3), which keeps multipath GPS and wrong-floor WiFi out. Because the bias and scale
  states are correlated with the position through the steps, consistent fixes teach the filter the
  walker's heading bias (a consistent turn) and step-length scale.
* **Correct with a displacement** (eq 17, GPS differential mode): two GPS positions seconds apart,
  differenced so their common bias cancels (:class:`~hybridloc.types.DisplacementFix`), against
  s R(b_psi) times the PDR's own displacement over the window (:class:`.measurements.StepDisplacement`):
  heading bias and step scale without any absolute position. Same gate, same Joseph update.
* **Floor**: the floor of the most recent accepted fixes, switching when a fix names another floor with
  probability above ``floor_switch``, or when a step reports a floor change.
* **Start**: until the first accepted fix the position is unknown; the first fix initialises it with
  its covariance (a client that knows its start passes ``init``).
* **Re-anchor from the smoother** (:meth:`LocalFusion.reanchor`): the crowd SLAM's corrected track of
  the walk replaces the filter's estimate at the track's latest time, and the steps taken since are
  propagated again (a re-linearisation from the smoothed estimate, not a measurement update).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from ..estimation import ChiSquareGate, Measurement, UpdateInfo, UpdateStats
from ..estimation import correct as gated_update
from ..pdr.deadreckoning import DeadReckoning
from ..types import AbsoluteFix, DisplacementFix, StepEvent
from ..units import wrap_angle
from .measurements import CorridorHeading, PositionFix, StepDisplacement


@dataclass
class FusionConfig:
    gate_probability: float = 0.95  # Kourogi: reject fixes outside the 95 % region
    sigma_bias0: float = math.radians(30.0)  # initial heading-bias uncertainty
    sigma_scale0: float = 0.15  # initial step-length scale uncertainty
    bias_rw: float = math.radians(0.5)  # heading-bias random walk per step
    scale_rw: float = 0.002  # scale random walk per step
    #: another floor is taken from a fix naming it with at least this probability (its kNN vote: 3 of 5
    #: neighbours). Simulated site with stairs (eval fusion, 15 clients): floor hit 84.3 % at 0.8, 90.4 % at
    #: 0.6, the raw fixes' floors 93.6 %; ILC site1 (one floor per walk) stays at 100 %.
    floor_switch: float = 0.6
    reinit_after: int = 5  # consecutive rejected fixes that re-initialise the position (lost track)
    #: correlation of the errors of successive fixes per source. WiFi fixes a scan apart err alike
    #: (the same look-alike place; lag-1 autocorrelation 0.5 on ILC site1), so each carries less than
    #: its covariance says: R is inflated by (1 + rho) / (1 - rho), the variance factor of an AR(1)
    #: mean (ILC site1, eval fusion replays: live Kalman 5.08 -> 4.99 m at waypoints). Held out by floor
    #: (eval fusion prints it), cold replays pick 0.25 on every floor (cold 4.36 -> 4.28 m), but a known
    #: start then loses more (2.89 -> 3.01 m): kept at 0.5.
    fix_correlation: dict = field(default_factory=lambda: {"wifi": 0.5, "ble": 0.5})
    #: gate probability per source where Kourogi's 95 % does not fit: an RFID detection is a proximity
    #: event (no multipath), so it is rejected only when wildly off
    gate_by_source: dict = field(default_factory=lambda: {"rfid": 0.9999})
    #: Heuristic drift elimination (:class:`.measurements.CorridorHeading`, with ``corridor_axes``):
    #: after ``straight_steps`` steps whose headings span less than ``straight_tol``, a corrected
    #: heading within ``corridor_capture`` of the floor's grid (mod 90 deg) is taken as that grid
    #: direction, +- ``corridor_sigma``. The capture stays below 22.5 deg, half-way to a diagonal
    #: corridor. ILC site1 (eval fusion replays, axes from the floor plan's walls): start known
    #: 3.30 -> 2.94 m, cold 4.43 -> 4.30 m; capture 15 / 25 deg: 3.02 / 3.24 m start known.
    corridor_sigma: float = math.radians(10.0)
    corridor_capture: float = math.radians(20.0)
    straight_steps: int = 6
    straight_tol: float = math.radians(10.0)


@dataclass
class Estimate:
    t: float
    pos: np.ndarray
    cov: np.ndarray
    floor: str | None
    kind: str  # "step" | "fix" | "init" | "reanchor" | ...


#: Steps a filter keeps for :meth:`LocalFusion.reanchor` (re-applied after the smoothed estimate's time):
#: 2,000 steps are about 17 minutes of walking at 2 steps/s, far more than the crowd SLAM lags a live walk.
REANCHOR_STEPS = 2000


class StepMemory:
    """The steps a filter took (the newest ``limit``) and when it started: what re-anchoring re-applies."""

    def __init__(self, limit: int = REANCHOR_STEPS):
        self.steps: deque[StepEvent] = deque(maxlen=limit)
        self.t_start = math.inf  # the first step or position fix the filter took
        self._forgotten = -math.inf  # time of the newest step no longer kept

    def started(self, t: float) -> None:
        self.t_start = min(self.t_start, t)

    def add(self, step: StepEvent) -> None:
        self.started(step.t)
        if len(self.steps) == self.steps.maxlen:
            self._forgotten = self.steps[0].t
        self.steps.append(step)

    @property
    def horizon(self) -> float:
        """The earliest time a re-anchoring can start from: every step after it is kept, and the filter
        had started (inf before the first step or fix)."""
        return max(self.t_start, self._forgotten)

    def since(self, t: float) -> list[StepEvent]:
        """The steps after time t, oldest first."""
        return [s for s in self.steps if s.t > t]

    def last_at_or_before(self, t: float) -> StepEvent | None:
        for s in reversed(self.steps):
            if s.t <= t:
                return s
        return None


def check_reanchor(memory: StepMemory, t: float, pos, cov) -> tuple[np.ndarray, np.ndarray]:
    """The position (2,) and covariance (2, 2) of a re-anchoring at time t; ValueError when t is before the
    filter started or older than the steps it keeps, or the position is not finite."""
    if not t >= memory.horizon:  # also NaN
        raise ValueError(f"cannot re-anchor at t={t}: the filter keeps its steps from t={memory.horizon} on")
    p, c = np.asarray(pos, float).reshape(2), np.asarray(cov, float).reshape(2, 2)
    if not np.isfinite(p).all():
        raise ValueError("a re-anchoring needs a finite position")
    return p, 0.5 * (c + c.T)


class LocalFusion:
    def __init__(
        self,
        config: FusionConfig | None = None,
        init: tuple[float, float, float] | None = None,
        floor: str | None = None,
        heading_bias: tuple[float, float] | None = None,
        corridor_axes: dict[str, float] | None = None,
    ):
        """``init`` = (x, y, sigma) of a known start; ``heading_bias`` = (mean, sigma) rad of the PDR's
        heading bias when known (e.g. aligned on a known first leg), else 0 +- ``sigma_bias0``;
        ``corridor_axes``: floor name -> its dominant grid direction, rad mod pi/2
        (:func:`hybridloc.geo.dominant_axis` of its walls), for heuristic drift elimination."""
        self.cfg = config or FusionConfig()
        self.corridor_axes = dict(corridor_axes or {})
        self._recent_headings: list[float] = []
        self.n_corridor = 0
        self.x = np.zeros(4)
        self.x[3] = 1.0
        self.P = np.diag([1e6, 1e6, self.cfg.sigma_bias0**2, self.cfg.sigma_scale0**2])
        if heading_bias is not None:
            self.x[2], self.P[2, 2] = heading_bias[0], heading_bias[1] ** 2
        self.initialised = False
        self.floor = floor
        self.t = -math.inf
        self.n_rejected = 0
        self._rejected_run = 0
        self.stats = UpdateStats()  # every update's outcome, per measurement kind
        self._gate = ChiSquareGate(self.cfg.gate_probability)
        self._gate_by_source = {src: ChiSquareGate(p) for src, p in self.cfg.gate_by_source.items()}
        self._hist: list[tuple[float, float, float]] = []  # (t, x, y) after each step, for delayed fixes
        self._raw = DeadReckoning(covariance=False, max_rows=200)  # the PDR's own track (sum of L (cos psi, sin psi)) since its first step
        self._memory = StepMemory()  # the steps taken, for reanchor
        self.n_reanchored = 0
        if init is not None:
            self.x[:2] = init[:2]
            self.P[0, 0] = self.P[1, 1] = init[2] ** 2
            self.initialised = True

    def estimate(self, kind: str) -> Estimate:
        return Estimate(self.t, self.x[:2].copy(), self.P[:2, :2].copy(), self.floor, kind)

    def predict(self, step: StepEvent) -> Estimate:
        """Dead-reckon one step (Kourogi eqs 9-14)."""
        self._memory.add(step)
        self._motion(step)
        if self._raw.t_last is not None and step.t <= self._raw.t_last:  # a clock that went back: the PDR's track starts over
            self._raw = DeadReckoning(pos0=self._raw.position, covariance=False, max_rows=200)
        self._raw.add(step)
        self._corridor(step)
        return self._stepped(step)

    def _motion(self, step: StepEvent) -> None:
        """The state and covariance moved by one step (Kourogi eqs 9-14); what :meth:`reanchor` re-applies."""
        b, s = self.x[2], self.x[3]
        psi = step.heading + b
        c, sn = math.cos(psi), math.sin(psi)
        L = step.length
        self.x[0] += s * L * c
        self.x[1] += s * L * sn
        # Jacobian of the new state w.r.t. (p, b, s)
        F = np.eye(4)
        F[0, 2], F[1, 2] = -s * L * sn, s * L * c
        F[0, 3], F[1, 3] = L * c, L * sn
        # step noise: stride and direction errors (eq 14), through the scaled geometry
        G = np.array([[s * c, -s * L * sn], [s * sn, s * L * c]])
        Q = np.zeros((4, 4))
        Q[:2, :2] = G @ np.diag([step.sigma_length**2, step.sigma_heading_change**2 if step.sigma_heading_change else step.sigma_heading**2]) @ G.T
        Q[2, 2] = self.cfg.bias_rw**2
        Q[3, 3] = self.cfg.scale_rw**2
        self.P = F @ self.P @ F.T + Q
        self.P = 0.5 * (self.P + self.P.T)
        self.t = step.t

    def _corridor(self, step: StepEvent) -> None:
        """Heuristic drift elimination after a step (see ``FusionConfig.corridor_*``)."""
        axis = self.corridor_axes.get(self.floor) if self.floor is not None else None
        if not straight_along(self._recent_headings, step.heading, axis, self.cfg.straight_steps, self.cfg.straight_tol):
            return
        psi = step.heading + self.x[2]
        target = nearest_grid_direction(psi, axis)
        y = wrap_angle(target - psi)
        if abs(y) >= self.cfg.corridor_capture:
            return
        # The gate of this 1-D update has always been the 2-D one (chi2.ppf(0.95, 2) = 5.99, i.e. 98.6 %
        # in 1-D); kept so the figures stay. The capture above bounds the innovation anyway.
        meas = Measurement(np.array([target]), CorridorHeading(step.heading, self.cfg.corridor_sigma), step.t)
        if self.update(meas, ChiSquareGate(self.cfg.gate_probability, dim=2)).accepted:
            self.n_corridor += 1

    def _stepped(self, step: StepEvent) -> Estimate:
        """After a step's prediction: record where it left us (for late fixes) and any floor change."""
        _keep(self._hist, (step.t, float(self.x[0]), float(self.x[1])))
        if step.floor_change and self.floor is not None:
            self.floor = _shift_floor(self.floor, step.floor_change, self.corridor_axes)
        return self.estimate("step")

    # ------------------------------------------------------------------ re-anchoring from the smoother
    @property
    def reanchor_horizon(self) -> float:
        """The earliest time :meth:`reanchor` takes (the filter's start, or its oldest kept step)."""
        return self._memory.horizon

    def reanchor(self, t: float, pos, cov, floor: str | None, heading_bias: float | None = None, scale: float | None = None) -> Estimate:
        """Re-anchor on the smoother's estimate at time ``t``: position ``pos`` (2,) with covariance ``cov``
        (2, 2; not finite: the filter keeps its own), ``floor``, and the walk's ``heading_bias`` and step
        ``scale`` where known. Returns the new estimate (kind ``"reanchor"``).

        This is an explicit re-linearisation, not a measurement update (predict/correct stay the step
        API): the crowd SLAM's smoothed estimate at t, which has seen the whole walk so far, replaces
        the filter's own estimate at t, and the state since then is propagated again with the same
        steps (:meth:`_motion`, Kourogi eqs 9-14):

            x(t) = (p_s, b', s'),   P(t) = blockdiag(C_s, P_bs)
            x_k = f(x_(k-1), step_k),   P_k = F_k P_(k-1) F_k^T + Q_k   for every step k after t

        with (p_s, C_s) the smoothed position and covariance, b' = ``heading_bias`` and s' = ``scale``
        (the filter's own when None) and P_bs the filter's present covariance of (b, s): the smoother
        gives no uncertainty for them, and its position is independent of the filter's (cross terms
        0). The live pose is then p_s + sum_k s' L_k (cos(psi_k + b'), sin(psi_k + b')): it moves by the
        correction at t and goes on with the steps, instead of jumping to where the walker was at t.
        Fixes fused after t are dropped (the smoother had not seen them; the next ones correct again).

        Conventions (checked against :class:`hybridloc.types.CorrectedTrack` and
        :mod:`hybridloc.slam.factors`, where a segment's odometry is T(n) D = s R(beta) D): the track's
        heading bias beta is the CCW angle that rotates the PDR's headings onto the corrected track,
        which is b_psi here (psi = heading + b_psi); its scale multiplies the PDR's step lengths, as s.

        Raises ValueError when t is before the filter started or older than the steps it keeps
        (:data:`REANCHOR_STEPS`, :attr:`reanchor_horizon`). A filter not yet initialised starts here.
        """
        p, c = check_reanchor(self._memory, t, pos, cov)
        since = self._memory.since(t)
        t_now = self.t
        self._anchor(t, p, c, heading_bias, scale)
        if floor:
            self.floor = floor
        self._hist.clear()
        _keep(self._hist, (t, float(self.x[0]), float(self.x[1])))
        for step in since:  # the same steps, from the smoothed state
            self._motion(step)
            _keep(self._hist, (step.t, float(self.x[0]), float(self.x[1])))
            if step.floor_change and self.floor is not None:
                self.floor = _shift_floor(self.floor, step.floor_change, self.corridor_axes)
        self.t = max(t_now, t)
        self.initialised = True
        self._rejected_run = 0
        self.n_reanchored += 1
        return self.estimate("reanchor")

    def _anchor(self, t: float, pos: np.ndarray, cov: np.ndarray, heading_bias: float | None, scale: float | None) -> None:
        """The state at the re-anchoring time: x(t) = (p_s, b', s'), P(t) = blockdiag(C_s, P_bs)."""
        self.x[:2] = pos
        if np.isfinite(cov).all():
            self.P[:2, :2] = cov
        self.P[:2, 2:] = 0.0
        self.P[2:, :2] = 0.0
        if heading_bias is not None:
            self.x[2] = heading_bias
        if scale is not None:
            self.x[3] = scale
        self._constrain()

    def _position_at(self, t: float) -> np.ndarray:
        if not self._hist or t >= self._hist[-1][0]:
            return self.x[:2].copy()
        if t <= self._hist[0][0]:
            return np.array(self._hist[0][1:])
        # where we were then = our track then, shifted by every correction made since (the history
        # stores the track as it was; corrections move the present only)
        return _track_at(self._hist, t) + (self.x[:2] - np.array(self._hist[-1][1:]))

    def _raw_at(self, t: float) -> np.ndarray | None:
        """The PDR's own track at time t; None outside the kept history."""
        return self._raw.position_at(t) if self._raw.covers(t) else None

    def correct(self, fix: AbsoluteFix | DisplacementFix) -> tuple[bool, Estimate]:
        """One gated update with a position fix or a displacement (GPS differential mode); returns
        (accepted, estimate). Both pass the same chi-square gate and Joseph-form update."""
        return getattr(self, fix_handler(self, fix))(fix)

    def _correct_position(self, fix: AbsoluteFix) -> tuple[bool, Estimate]:
        z = np.asarray(fix.pos_enu, float)[:2]
        R = np.asarray(fix.cov, float)[:2, :2]
        self._memory.started(fix.t)
        if not self.initialised:
            self.x[:2] = z
            self._hist.clear()
            self.P[:2, :2] = R
            self.P[:2, 2:] = 0.0
            self.P[2:, :2] = 0.0
            self.initialised = True
            self.t = max(self.t, fix.t)
            self.floor = fix.floor or self.floor
            return True, self.estimate("init")
        # A fix arrives after the scan it comes from (network, server batching): compare it with where
        # we were at the scan's time, and shift the present by the same correction (the steps since
        # then are kept as they are).
        p_then = self._position_at(fix.t)
        model = PositionFix(correlated_fix_cov(R, fix, self.cfg.fix_correlation), p_then - self.x[:2] if self._lags(fix.t) else None)
        if not self.update(Measurement(z, model, fix.t, fix), self._gate_by_source.get(fix.source.value, True)).accepted:
            self.n_rejected += 1
            self._rejected_run += 1
            if self._rejected_run >= self.cfg.reinit_after:  # lost: the fixes agree with each other, not with us
                self.initialised = False
                self._rejected_run = 0
                return self.correct(fix)
            return False, self.estimate("fix-rejected")
        self._rejected_run = 0
        self.t = max(self.t, fix.t)
        self.floor = floor_after_fix(self.floor, fix, self.cfg.floor_switch)
        return True, self.estimate("fix")

    def _lags(self, t: float) -> bool:
        """Is time t behind the last recorded step (a late fix, compared with the track then)?"""
        return bool(self._hist) and t < self._hist[-1][0]

    def _correct_displacement(self, fix: DisplacementFix) -> tuple[bool, Estimate]:
        """Kourogi eq 17: the displacement between t0 and t1 against s R(b) (PDR displacement)."""
        a, b = self._raw_at(fix.t0), self._raw_at(fix.t1)
        if a is None or b is None:
            self.n_rejected += 1  # the steps of that window are not (or no longer) known
            return False, self.estimate("displacement-rejected")
        meas = Measurement(np.asarray(fix.delta_enu, float), StepDisplacement(b - a, fix.cov), fix.t1, fix)
        if not self.update(meas).accepted:
            self.n_rejected += 1
            return False, self.estimate("displacement-rejected")
        return True, self.estimate("displacement")

    def update(self, meas: Measurement, gate: ChiSquareGate | bool | None = True) -> UpdateInfo:
        """The one gated update of this filter: :func:`hybridloc.estimation.correct` with the
        measurement's own model; ``gate`` True is the filter's (Kourogi sec. 3.3: reject outside the
        95 % region), False or None none. An accepted correction is added to the state, then constrained."""
        g = self._gate if gate is True else (gate or None)
        dx, P, info = gated_update(self.x, self.P, meas.value, meas.model, g, self.stats)
        if info.accepted:
            self.x, self.P = self.x + dx, P
            self._constrain()
        return info

    def _constrain(self) -> None:
        """Keep the step scale physical after an update."""
        self.x[3] = min(max(self.x[3], 0.5), 1.5)


#: Which handler of a filter takes which fix of the wire (a filter overrides the handler, not ``correct``).
FIX_HANDLERS = {AbsoluteFix: "_correct_position", DisplacementFix: "_correct_displacement"}


def fix_handler(filt, fix) -> str:
    """Name of the method of ``filt`` that takes ``fix`` (:data:`FIX_HANDLERS`, by the fix's class)."""
    for cls in type(fix).__mro__:
        if cls in FIX_HANDLERS:
            return FIX_HANDLERS[cls]
    raise TypeError(f"{type(filt).__name__} takes {' or '.join(c.__name__ for c in FIX_HANDLERS)}, not {type(fix).__name__}")


def straight_along(recent: list[float], heading: float, axis: float | None, steps: int, tol: float) -> bool:
    """Heuristic drift elimination's trigger: keep the last ``steps`` step headings in ``recent``
    (cleared where the floor has no grid ``axis``) and say whether they span less than ``tol``."""
    if axis is None:
        recent.clear()
        return False
    recent.append(heading)
    del recent[:-steps]
    if len(recent) < steps:
        return False
    u = np.unwrap(recent)
    return bool(u.max() - u.min() < tol)


def nearest_grid_direction(psi: float, axis: float) -> float:
    """The direction of a grid (``axis`` mod pi/2) nearest to heading ``psi``, rad."""
    quarter = math.pi / 2
    return axis + round((psi - axis) / quarter) * quarter


def correlated_fix_cov(R: np.ndarray, fix: AbsoluteFix, correlation: dict) -> np.ndarray:
    """A fix's covariance inflated by (1 + rho) / (1 - rho), rho the lag-1 correlation of its source's
    errors (the variance factor of an AR(1) mean: successive fixes carry less than each says)."""
    rho = correlation.get(fix.source.value, 0.0)
    return R * (1.0 + rho) / (1.0 - rho)


def floor_after_fix(floor: str | None, fix: AbsoluteFix, switch: float) -> str | None:
    """The floor after an accepted fix: the fix's when none is known yet, or when it names another
    floor with probability at least ``switch``."""
    if fix.floor is not None and (floor is None or (fix.floor != floor and fix.floor_prob >= switch)):
        return fix.floor
    return floor


def _keep(track: list, row: tuple, limit: int = 200) -> None:
    """Append to a bounded history (halved when it passes ``limit``)."""
    track.append(row)
    if len(track) > limit:
        del track[: limit // 2]


def _track_at(track: list[tuple[float, float, float]], t: float) -> np.ndarray:
    """Position of a (t, x, y) track at time t within its span, linear between rows."""
    k = min(int(np.searchsorted([r[0] for r in track], t, side="right")) - 1, len(track) - 1)
    if k == len(track) - 1:
        return np.array(track[-1][1:])
    (t0, x0, y0), (t1, x1, y1) = track[k], track[k + 1]
    a = (t - t0) / (t1 - t0) if t1 > t0 else 0.0
    return np.array([x0 + a * (x1 - x0), y0 + a * (y1 - y0)])


def _shift_floor(name: str, delta: int, known=()) -> str:
    """The floor ``delta`` levels from ``name``: the site's ``known`` floor at that level (the plan's
    names), else named in ``name``'s style (F2 -> F3, 2F -> 3F, F1 -> B1, 1F -> 1B)."""
    from ..io.msft import floor_level, floor_name

    try:
        return floor_name(floor_level(name) + delta, name, known)
    except ValueError:
        return name

"""15-state error-state EKF for a foot-mounted INS (Godha & Lachapelle's error model, Foxlin's ZUPT EKF).

Error state dx = (dp, dv, dtheta, db_a, db_g), nav-frame attitude error R_true = exp([dtheta]x) R.
Continuous error dynamics (Earth rate neglected, as in the strapdown):

    dp'     = dv
    dv'     = -[a_nav]x dtheta - R db_a - R n_a          a_nav = R (f - b_a)
    dtheta' = -R db_g - R n_g
    db_a'   = w_a,   db_g' = w_g                         (bias random walks)

discretised as Phi = I + F dt and Q_d = G Q_c G^T dt. Corrections (:meth:`ErrorStateEkf.correct`)
go through the one gated update of :func:`hybridloc.estimation.correct` (Joseph form, chi-square
gate on the normalised innovation squared, rejections counted per kind), which returns the error
state dx; the filter injects it into the nominal state (closed loop, ``x.plus(dx)``) and resets the
error to zero, with the reset Jacobian G_theta = I - [dtheta/2]x applied to the covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..estimation import ChiSquareGate, UpdateInfo, UpdateStats, correct
from ._compiled import strapdown_predict
from .measurements import DP, DTH, MeasurementModel
from .strapdown import NominalState

#: Default probability of the chi-square innovation gate.
GATE_PROBABILITY = 0.9999


@dataclass
class ImuNoise:
    """Noise of the IMU and of the model, as densities (SI).

    Defaults suit a foot-mounted MEMS unit (e.g. MicroStrain 3DM-GX3-25): the white-noise terms are
    inflated well above the datasheet (80 ug/rtHz, 0.03 deg/s/rtHz) to cover what the strapdown
    model leaves out on a foot (vibration, impacts, sculling); PyShoe uses 0.5 m/s^2 and 0.5 deg/s
    per 200 Hz sample, i.e. the same densities.
    """

    accel_density: float = 0.5 / math.sqrt(200.0)  # m/s^2/sqrt(Hz)
    gyro_density: float = 0.5 * math.pi / 180 / math.sqrt(200.0)  # rad/s/sqrt(Hz)
    accel_bias_rw: float = 1e-4  # m/s^3/sqrt(Hz)
    gyro_bias_rw: float = 1e-5  # rad/s^2/sqrt(Hz)
    # Turn-on bias uncertainty. Kept small: over a walk of minutes, foot impacts at stance leak into
    # loosely constrained bias states and cost more than the biases do (PyShoe VICON trials, default
    # detector: mean ARMSE 0.070 m with these, 0.082 m with 0.05 m/s^2 / 0.2 deg/s, 0.073 m with the
    # biases frozen - which would leave nothing to learn the gyro bias over a long walk).
    accel_bias_sigma0: float = 0.01  # m/s^2
    gyro_bias_sigma0: float = 0.02 * math.pi / 180  # rad/s


#: What :meth:`ErrorStateEkf.correct` returns (``accepted``, ``innovation``, ``S``, ``nis``, ``dx``).
Correction = UpdateInfo


class ErrorStateEkf:
    """Predict/correct step API; the nominal state ``x`` and covariance ``P`` (15 x 15) are attributes."""

    def __init__(self, x0: NominalState, P0: np.ndarray, noise: ImuNoise, g: float, gate_probability: float = GATE_PROBABILITY):
        self.x = x0
        self.P = np.array(P0, dtype=float)
        self.noise = noise
        self.g = g
        self.gate = ChiSquareGate(gate_probability)
        self.stats = UpdateStats()
        self._Phi = np.eye(15)  # predict() rewrites its time-varying blocks in place
        n = noise  # diag(Q_c), the continuous noise densities per error state: Q_d = diag(Q_c) dt
        self._qd_rate = np.array([0.0] * 3 + [n.accel_density**2] * 3 + [n.gyro_density**2] * 3 + [n.accel_bias_rw**2] * 3 + [n.gyro_bias_rw**2] * 3)

    @property
    def gate_probability(self) -> float:
        return self.gate.probability

    @property
    def n_rejected(self) -> int:
        """Corrections the chi-square gate turned away (per kind: ``stats.rejected``)."""
        return self.stats.n_rejected

    def predict(self, f_body: np.ndarray, w_body: np.ndarray, dt: float) -> None:
        """Strapdown step of the nominal state (same equations as :func:`.strapdown.mechanise`, done
        in place) and covariance propagation P <- Phi P Phi^T + Q_d (:func:`._compiled.strapdown_predict`).

        The samples are at the end of the step (t_k): the attitude there is q_{k-1} exp(w_k dt), and
        it is with that attitude that f_k is resolved. Resolving f_k with q_{k-1} misaligns the two
        by one sample, i.e. by w dt - 0.025-0.05 rad in a foot's swing: PyShoe VICON trials on the
        authors' stance labels, 0.0645 -> 0.0551 m mean ARMSE (theirs: 0.0557)."""
        x = self.x
        x.q, x.p, x.v, self.P = strapdown_predict(x.q, x.p, x.v, x.b_a, x.b_g, f_body, w_body, dt, self.g, self.P, self._Phi, self._qd_rate)

    @property
    def transition(self) -> np.ndarray:
        """A copy of the error-state transition matrix Phi of the last :meth:`predict`."""
        return self._Phi.copy()

    def correct(self, model: MeasurementModel, z, gate: bool = True) -> Correction:
        """ZUPT, ZARU, heading and position fixes: the one gated update, then injection and reset."""
        dx, P, info = correct(self.x, self.P, z, model, self.gate if gate else None, self.stats, compiled=True)
        if not info.accepted:
            return info
        self.x = self.x.plus(dx)
        # Reset: the attitude error's covariance seen through the injected rotation.
        hx, hy, hz = 0.5 * dx[DTH]
        Gt = np.array([[1.0, hz, -hy], [-hz, 1.0, hx], [hy, -hx, 1.0]])  # I - [dtheta/2]x
        P[DTH, :] = Gt @ P[DTH, :]
        P[:, DTH] = P[:, DTH] @ Gt.T
        self.P = 0.5 * (P + P.T)
        return info

    def position_sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.P)[DP], 0.0, None))

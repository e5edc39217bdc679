"""15-state error-state EKF for a foot-mounted INS (Godha & Lachapelle's error model, Foxlin's ZUPT EKF).

Error state dx = (dp, dv, dtheta, db_a, db_g), nav-frame attitude error R_true = exp([dtheta]x) R.
Continuous error dynamics (Earth rate neglected, as in the strapdown):

    dp'     = dv
    dv'     = -[a_nav]x dtheta - R db_a - R n_a          a_nav = R (f - b_a)
    dtheta' = -R db_g - R n_g
    db_a'   = w_a,   db_g' = w_g                         (bias random walks)

discretised as Phi = I + F dt and Q_d = G Q_c G^T dt. Corrections (:meth:`ErrorStateEkf.correct`)
use the Joseph form, gate the innovation with a chi-square test on its normalised square, inject the
estimated error into the nominal state (closed loop) and reset the error to zero, with the reset
Jacobian G_theta = I - [dtheta/2]x applied to the covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from .measurements import DP, DTH, MeasurementModel
from .strapdown import NominalState, quat_to_dcm


def _qmul_exp(q: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """q (x) exp(phi / 2), normalised; plain floats (4-vectors are cheaper outside numpy)."""
    px, py, pz = float(phi[0]), float(phi[1]), float(phi[2])
    a = math.sqrt(px * px + py * py + pz * pz)
    if a < 1e-12:
        bw, bx, by, bz = 1.0, 0.5 * px, 0.5 * py, 0.5 * pz
    else:
        s = math.sin(0.5 * a) / a
        bw, bx, by, bz = math.cos(0.5 * a), px * s, py * s, pz * s
    aw, ax, ay, az = float(q[0]), float(q[1]), float(q[2]), float(q[3])
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return np.array([w / n, x / n, y / n, z / n])


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


@dataclass
class Correction:
    accepted: bool
    innovation: np.ndarray
    S: np.ndarray
    nis: float  # normalised innovation squared
    dx: np.ndarray | None = None  # the error state injected (accepted corrections only)


def _inv_spd_small(S: np.ndarray) -> np.ndarray:
    """Inverse of a small symmetric innovation covariance: closed form for 1-3 dimensions (the ZUPT,
    ZARU and heading updates run at every stance sample, where numpy's general inverse is most of
    the cost), numpy's for larger ones."""
    m = S.shape[0]
    if m == 1:
        return np.array([[1.0 / S[0, 0]]])
    if m == 3:
        a, b, c = S[0]
        _, e, f = S[1]
        i = S[2, 2]
        A, B, C = e * i - f * f, c * f - b * i, b * f - c * e
        det = a * A + b * B + c * C
        if det > 0.0:
            E, F, I_ = a * i - c * c, b * c - a * f, a * e - b * b
            return np.array([[A, B, C], [B, E, F], [C, F, I_]]) / det
    return np.linalg.inv(S)


class ErrorStateEkf:
    """Predict/correct step API; the nominal state ``x`` and covariance ``P`` (15 x 15) are attributes."""

    def __init__(self, x0: NominalState, P0: np.ndarray, noise: ImuNoise, g: float, gate_probability: float = GATE_PROBABILITY):
        self.x = x0
        self.P = np.array(P0, dtype=float)
        self.noise = noise
        self.g = g
        self.gate_probability = gate_probability
        self._gates: dict[int, float] = {}
        self._I = np.eye(15)
        self._Phi = np.eye(15)
        self._dt = -1.0
        self._qd = np.zeros(15)
        self._qd_rate: np.ndarray | None = None
        self.n_rejected = 0

    def predict(self, f_body: np.ndarray, w_body: np.ndarray, dt: float) -> None:
        """Strapdown step of the nominal state (same equations as :func:`.strapdown.mechanise`, done
        in place) and covariance propagation P <- Phi P Phi^T + Q_d."""
        x = self.x
        # The samples are at the end of the step (t_k): the attitude there is q_{k-1} exp(w_k dt), and
        # it is with that attitude that f_k is resolved. Resolving f_k with q_{k-1} misaligns the two
        # by one sample, i.e. by w dt - 0.025-0.05 rad in a foot's swing: PyShoe VICON trials on the
        # authors' stance labels, 0.0645 -> 0.0551 m mean ARMSE (theirs: 0.0557).
        q_new = _qmul_exp(x.q, (w_body - x.b_g) * dt)
        R = quat_to_dcm(q_new)
        fb = f_body - x.b_a
        a_nav = R @ fb
        Phi = self._Phi
        if dt != self._dt:
            self._set_dt(dt)
        ax, ay, az = a_nav
        # Phi[DV, DTH] = -[a_nav]x dt
        Phi[3, 7], Phi[3, 8] = az * dt, -ay * dt
        Phi[4, 6], Phi[4, 8] = -az * dt, ax * dt
        Phi[5, 6], Phi[5, 7] = ay * dt, -ax * dt
        mRdt = R * (-dt)
        Phi[3:6, 9:12] = mRdt
        Phi[6:9, 12:15] = mRdt
        P = Phi @ self.P @ Phi.T
        P.ravel()[::16] += self._qd  # Q_d is diagonal: R diag(s) R^T = s I for isotropic noise
        self.P = P
        a_nav[2] -= self.g
        x.p = x.p + x.v * dt + (0.5 * dt * dt) * a_nav
        x.v = x.v + a_nav * dt
        x.q = q_new

    @property
    def transition(self) -> np.ndarray:
        """A copy of the error-state transition matrix Phi of the last :meth:`predict`."""
        return self._Phi.copy()

    def _set_dt(self, dt: float) -> None:
        # Timestamps jitter, so this runs at almost every sample: no allocation here.
        if self._qd_rate is None:
            n = self.noise
            self._qd_rate = np.concatenate([np.zeros(3), np.full(3, n.accel_density**2), np.full(3, n.gyro_density**2),
                                            np.full(3, n.accel_bias_rw**2), np.full(3, n.gyro_bias_rw**2)])
        self._dt = dt
        self._Phi[0, 3] = self._Phi[1, 4] = self._Phi[2, 5] = dt
        np.multiply(self._qd_rate, dt, out=self._qd)

    def _gate(self, m: int) -> float:
        if m not in self._gates:
            self._gates[m] = float(chi2.ppf(self.gate_probability, m))
        return self._gates[m]

    def correct(self, model: MeasurementModel, z, gate: bool = True) -> Correction:
        """The one correction path: ZUPT, ZARU, heading and position fixes all come through here."""
        z_pred = model.evaluate(self.x)
        H = model.jacobian(self.x)
        R = model.covariance()
        y = model.residual(z, z_pred)
        PHt = self.P @ H.T
        S = H @ PHt + R
        S = 0.5 * (S + S.T)
        Sinv = _inv_spd_small(S)
        nis = float(y @ Sinv @ y)
        if gate and nis > self._gate(len(y)):
            self.n_rejected += 1
            return Correction(False, y, S, nis)
        K = PHt @ Sinv
        IKH = self._I - K @ H
        P = IKH @ self.P @ IKH.T + K @ R @ K.T  # Joseph form: stays symmetric positive definite
        dx = K @ y
        self.x = self.x.plus(dx)
        # Reset: the attitude error's covariance seen through the injected rotation.
        hx, hy, hz = 0.5 * dx[DTH]
        Gt = np.array([[1.0, hz, -hy], [-hz, 1.0, hx], [hy, -hx, 1.0]])  # I - [dtheta/2]x
        P[DTH, :] = Gt @ P[DTH, :]
        P[:, DTH] = P[:, DTH] @ Gt.T
        self.P = 0.5 * (P + P.T)
        return Correction(True, y, S, nis, dx)

    def position_sigma(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.P)[DP], 0.0, None))

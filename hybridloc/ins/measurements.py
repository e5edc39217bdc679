"""Measurement models of the foot-mounted error-state EKF: small classes with evaluate/jacobian/covariance.

Every model answers for a :class:`~.strapdown.NominalState` x:

* ``evaluate(x)`` -> predicted measurement h(x), shape (m,);
* ``jacobian(x)`` -> H = dh/d(dx), shape (m, 15), w.r.t. the error state injected by ``x.plus(dx)``
  (order dp, dv, dtheta, db_a, db_g); tested against finite differences;
* ``covariance(x=None)`` -> R, shape (m, m);
* ``residual(z, z_pred)`` -> z - z_pred (angles wrapped).

They follow the protocol of :class:`hybridloc.estimation.MeasurementModel` and all go through the one
gated update, :func:`hybridloc.estimation.correct`, via :meth:`~.eskf.ErrorStateEkf.correct`.
"""

from __future__ import annotations

import math

import numpy as np

from ..estimation import jacobian_check
from ..estimation.models import MeasurementModel as _CoreModel
from .strapdown import NominalState, skew

DP, DV, DTH, DBA, DBG = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12), slice(12, 15)


class MeasurementModel(_CoreModel):
    """A model of the foot INS: its Jacobians are with respect to the 15-dimensional error state."""

    dim = 0
    state_dof = 15


class ZeroVelocity(MeasurementModel):
    """ZUPT: the foot's velocity is zero during stance, z = 0, h = v (Foxlin; Godha sec. 3)."""

    dim = 3
    kind = "zupt"
    selects = DV

    def __init__(self, sigma: float = 0.01):
        self.R = np.eye(3) * sigma**2
        self.H = np.zeros((3, 15))
        self.H[:, DV] = np.eye(3)

    def evaluate(self, x):
        return x.v.copy()

    def jacobian(self, x):
        return self.H

    def covariance(self, x=None):
        return self.R


class ZeroAngularRate(MeasurementModel):
    """ZARU: during stance the true rate is ~0, so the gyro reading is its bias: h = omega_m - b_g."""

    dim = 3
    kind = "zaru"

    def __init__(self, omega_body: np.ndarray, sigma: float = 0.5 * math.pi / 180):
        self.omega = np.asarray(omega_body, dtype=float)
        self.R = np.eye(3) * sigma**2
        self.H = np.zeros((3, 15))
        self.H[:, DBG] = -np.eye(3)

    def evaluate(self, x):
        return self.omega - x.b_g

    def jacobian(self, x):
        return self.H

    def covariance(self, x=None):
        return self.R


class ZeroYawRate(MeasurementModel):
    """Vertical ZARU: during stance the foot does not turn about the vertical, so the gyro's reading
    about the body axis that points up is its bias along that axis: h = u . (omega_m - b_g), with u the
    body's up axis (``up_body``, the last row of R_body_to_nav, supplied with the reading).

    On a foot whose stance is never still (the gait-driven walks' 3DM-GX5-25: 7-33 deg/s at the
    stance's quietest sample) the 3-D ZARU's gate turns most stance samples away, because the foot
    rolls heel to toe about a horizontal axis. That roll has no vertical component, so this one
    component still holds, and it is the bias component that integrates into heading drift (the one
    a ZUPT cannot see: hde.py's docstring). u is data, like the reading: the update moves the bias
    only (H = -u^T on db_g). Letting it also tilt the attitude (u from the state) did no better on the
    gait-driven walks (a scratch run: return median / max 1.55 / 2.69 % against 1.56 / 2.73 % at 5 deg/s,
    1.87 / 3.06 % against 1.74 / 3.33 % at 0.5 deg/s)."""

    dim = 1
    kind = "zaru_up"

    def __init__(self, omega_body: np.ndarray, up_body: np.ndarray, sigma: float = 5 * math.pi / 180):
        self.omega = np.asarray(omega_body, dtype=float)
        self.up_body = np.asarray(up_body, dtype=float)
        self.R = np.array([[sigma**2]])

    def evaluate(self, x):
        return np.array([float(self.up_body @ (self.omega - x.b_g))])

    def jacobian(self, x):
        H = np.zeros((1, 15))
        H[0, DBG] = -self.up_body
        return H

    def covariance(self, x=None):
        return self.R


class Heading(MeasurementModel):
    """Heading of a body axis projected on the horizontal: h = atan2(f_y, f_x), f = R a_body.

    Serves the magnetometer heading taken once per stance (Harle sec. IV) and an external heading
    (Li et al.'s EKF heading-correction mode, e.g. from a building's corridor directions).
    With R_true = exp([dtheta]x) R, df = -[f]x dtheta, so H_theta = dpsi/df_xy (-[f]x)_xy.
    """

    dim = 1
    kind = "heading"
    angles = (0,)

    def __init__(self, axis_body=(1.0, 0.0, 0.0), sigma: float = 5 * math.pi / 180):
        self.axis = np.asarray(axis_body, dtype=float)
        self.R = np.array([[sigma**2]])

    def evaluate(self, x):
        f = x.R @ self.axis
        return np.array([math.atan2(f[1], f[0])])

    def jacobian(self, x):
        f = x.R @ self.axis
        r2 = f[0] ** 2 + f[1] ** 2
        dpsi_df = np.array([-f[1] / r2, f[0] / r2, 0.0])
        H = np.zeros((1, 15))
        H[0, DTH] = dpsi_df @ (-skew(f))
        return H

    def covariance(self, x=None):
        return self.R


class StrideHeading(Heading):
    """The heading of a stride, predicted as the foot's heading plus the stride's offset from it:
    h = atan2(f_y, f_x) + offset, f = R a_body (the Jacobian is :class:`Heading`'s).

    Heuristic drift elimination (Borenstein, Ojeda & Kwanmuang 2009, HDR; Jimenez et al. 2012, iHDE:
    "Improved heuristic drift elimination with magnetically-aided dominant directions"): when a walker
    goes straight along one of a building's dominant directions, the stride heading the INS computed
    (``offset`` = that heading minus the foot's own, fixed over the stride) is measured as the nearest
    dominant direction z. Its innovation is the drift since the last such stride; through the filter's
    covariance it also reaches the gyro biases (dtheta' = -R db_g).
    """

    kind = "hde"

    def __init__(self, axis_body=(1.0, 0.0, 0.0), sigma: float = 2 * math.pi / 180, offset: float = 0.0):
        super().__init__(axis_body, sigma)
        self.offset = float(offset)

    def evaluate(self, x):
        return super().evaluate(x) + self.offset


class PositionFix(MeasurementModel):
    """An absolute position (2-D or 3-D) with its covariance, h = p[:dim]."""

    kind = "position"

    def __init__(self, cov: np.ndarray):
        self.R = np.atleast_2d(np.asarray(cov, dtype=float))
        self.dim = self.R.shape[0]
        self.H = np.zeros((self.dim, 15))
        self.H[:, : self.dim] = np.eye(self.dim)
        self.selects = slice(0, self.dim)

    def evaluate(self, x):
        return x.p[: self.dim].copy()

    def jacobian(self, x):
        return self.H

    def covariance(self, x=None):
        return self.R


def jacobian_fd(model: MeasurementModel, x: NominalState, eps: float = 1e-6) -> np.ndarray:
    """dh/d(dx) by central differences through ``x.plus`` (the test oracle for analytic Jacobians);
    :func:`hybridloc.estimation.jacobian_fd`, kept here under its old name."""
    return jacobian_check.jacobian_fd(model, x, eps)

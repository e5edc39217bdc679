"""Measurement models of the client fusion filters (see :mod:`.kalman` and :mod:`.kourogi`).

State of :class:`~.kalman.LocalFusion`: x = (p_x, p_y, b_psi, s); of :class:`~.kourogi.KourogiFusion`:
x = (p_x, p_y, v_x, v_y). Each model is a small class after :class:`hybridloc.estimation.MeasurementModel`:
``evaluate(x)`` the predicted measurement, ``jacobian(x)`` its derivative with respect to the state
(tested against finite differences), ``covariance()`` the measurement noise, ``kind`` its name in the
rejection counts. Every one of them reaches its filter through the one gated update,
:func:`hybridloc.estimation.correct`.
"""

from __future__ import annotations

import math

import numpy as np

from ..estimation import MeasurementModel


class PositionFix(MeasurementModel):
    """z = p + v, v ~ N(0, R): a WiFi / RFID / GPS position (Kourogi eqs 16 and 19-20).

    ``offset`` serves a fix that arrives late: it is compared with where the walker was at the scan's
    time, p_then = p + offset (offset = the track's displacement since then, taken as known), so
    h(x) = p + offset and the Jacobian is the same.
    """

    kind = "position"

    def __init__(self, R: np.ndarray, offset: np.ndarray | None = None):
        self.R = np.asarray(R, float)
        self.offset = None if offset is None else np.asarray(offset, float)

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        p = np.asarray(x[:2], float)
        return p if self.offset is None else p + self.offset

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        H = np.zeros((2, len(x)))
        H[0, 0] = H[1, 1] = 1.0
        return H

    def covariance(self, x=None) -> np.ndarray:
        return self.R


class StepDisplacement(MeasurementModel):
    """z = s R(b) d + v: the displacement over a time window (Kourogi eq 17, GPS differential mode).

    ``d`` is the PDR's own displacement over the window, sum of L_i (cos psi_i, sin psi_i) as the steps
    reported it; the walker truly moved by that rotated by the heading bias b and scaled by the step
    scale s (the bias and scale are taken constant over a window of a few seconds). The measurement
    says nothing of the position: H has zeros there, so it teaches b and s only.
    """

    kind = "displacement"

    def __init__(self, d_pdr: np.ndarray, R: np.ndarray):
        self.d = np.asarray(d_pdr, float)
        self.R = np.asarray(R, float)

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        b, s = x[2], x[3]
        c, sn = math.cos(b), math.sin(b)
        return s * np.array([c * self.d[0] - sn * self.d[1], sn * self.d[0] + c * self.d[1]])

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        b, s = x[2], x[3]
        c, sn = math.cos(b), math.sin(b)
        rd = np.array([c * self.d[0] - sn * self.d[1], sn * self.d[0] + c * self.d[1]])  # R(b) d
        drd = np.array([-sn * self.d[0] - c * self.d[1], c * self.d[0] - sn * self.d[1]])  # dR/db d
        H = np.zeros((2, len(x)))
        H[:, 2] = s * drd
        H[:, 3] = rd
        return H

    def covariance(self, x=None) -> np.ndarray:
        return self.R


class CorridorHeading(MeasurementModel):
    """z = psi_pdr + b + v: the walking direction along a corridor of the floor's dominant grid.

    Heuristic drift elimination (Borenstein et al.): while a walker goes straight, the true direction
    is most likely one of the building's grid directions, so the one nearest to the corrected heading
    psi_pdr + b is taken as a measurement of it. ``psi_pdr`` is the step's own heading; the
    measurement teaches the heading bias b only (the residual is wrapped to (-pi, pi]).
    """

    kind = "corridor"
    angles = (0,)

    def __init__(self, psi_pdr: float, sigma: float):
        self.psi = float(psi_pdr)
        self.R = np.array([[sigma**2]])

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        return np.array([self.psi + x[2]])

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        H = np.zeros((1, len(x)))
        H[0, 2] = 1.0
        return H

    def covariance(self, x=None) -> np.ndarray:
        return self.R


class Velocity(MeasurementModel):
    """z = v + n: the walker's velocity (Kourogi's state (p, v)): eq 10's zero velocity when no step
    came for a while (kind ``"still"``), eqs 17-18's velocity of two GPS positions (``"gps-velocity"``)."""

    def __init__(self, R: np.ndarray, kind: str = "velocity"):
        self.R = np.asarray(R, float)
        self.kind = kind

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x[2:4], float)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        H = np.zeros((2, len(x)))
        H[0, 2] = H[1, 3] = 1.0
        return H

    def covariance(self, x=None) -> np.ndarray:
        return self.R


class CloneStep(MeasurementModel):
    """Kourogi eq 9 on a stochastic clone: z = (l d, l d / T), h = (p - p_prev, v).

    State (p_x, p_y, v_x, v_y, p_prev_x, p_prev_y): the filter's state augmented by the position
    before the step, so the step is an observation of the displacement since then (see
    :mod:`.kourogi`), and of the velocity it implies.
    """

    kind = "step"

    def __init__(self, R: np.ndarray):
        self.R = np.asarray(R, float)
        H = np.zeros((4, 6))
        H[0, 0] = H[1, 1] = 1.0
        H[0, 4] = H[1, 5] = -1.0
        H[2, 2] = H[3, 3] = 1.0
        self.H = H

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        return self.H @ np.asarray(x, float)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        return self.H

    def covariance(self, x=None) -> np.ndarray:
        return self.R

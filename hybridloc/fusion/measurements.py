"""Measurement models of the client fusion filter, state x = (p_x, p_y, b_psi, s) (see :mod:`.kalman`).

Each is a small class: ``evaluate(x)`` the predicted measurement, ``jacobian(x)`` its derivative
with respect to the state (tested against finite differences), ``covariance()`` the measurement noise.
Every one of them reaches the filter through the same gated ``correct`` path.
"""

from __future__ import annotations

import math

import numpy as np


class PositionFix:
    """z = p + v, v ~ N(0, R): a WiFi / RFID / GPS position (Kourogi eqs 16 and 19-20)."""

    def __init__(self, R: np.ndarray):
        self.R = np.asarray(R, float)

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        return np.asarray(x[:2], float)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        H = np.zeros((2, len(x)))
        H[0, 0] = H[1, 1] = 1.0
        return H

    def covariance(self) -> np.ndarray:
        return self.R


class StepDisplacement:
    """z = s R(b) d + v: the displacement over a time window (Kourogi eq 17, GPS differential mode).

    ``d`` is the PDR's own displacement over the window, sum of L_i (cos psi_i, sin psi_i) as the steps
    reported it; the walker truly moved by that rotated by the heading bias b and scaled by the step
    scale s (the bias and scale are taken constant over a window of a few seconds). The measurement
    says nothing of the position: H has zeros there, so it teaches b and s only.
    """

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

    def covariance(self) -> np.ndarray:
        return self.R


class CorridorHeading:
    """z = psi_pdr + b + v: the walking direction along a corridor of the floor's dominant grid.

    Heuristic drift elimination (Borenstein et al.): while a walker goes straight, the true direction
    is most likely one of the building's grid directions, so the one nearest to the corrected heading
    psi_pdr + b is taken as a measurement of it. ``psi_pdr`` is the step's own heading; the
    measurement teaches the heading bias b only (the residual must be wrapped to (-pi, pi]).
    """

    def __init__(self, psi_pdr: float, sigma: float):
        self.psi = float(psi_pdr)
        self.R = np.array([[sigma**2]])

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        return np.array([self.psi + x[2]])

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        H = np.zeros((1, len(x)))
        H[0, 2] = 1.0
        return H

    def covariance(self) -> np.ndarray:
        return self.R

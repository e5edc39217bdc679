"""The measurement-model protocol of every filter in hybridloc, and robust kernels.

A measurement model is a small class (navlie's ``MeasurementModel``):

* ``evaluate(x)`` -> the predicted measurement h(x), shape (m,);
* ``jacobian(x)`` -> H = dh/d(dx), shape (m, dof), with respect to the error state injected by the
  state's ``plus`` (for a plain vector state, x + dx). The default is finite differences
  (:func:`.jacobian_check.jacobian_fd`); models give the analytic one, and tests check it;
* ``covariance(x=None)`` -> R, shape (m, m);
* ``residual(z, z_pred)`` -> the innovation z - h, with the components listed in ``angles`` wrapped
  to (-pi, pi] (a heading innovation never jumps by 2 pi);
* ``kind`` names the measurement in the per-kind counts of :class:`.update.UpdateStats`;
* ``kernel`` (optional): a robust kernel that down-weights a large innovation (see below).

A :class:`Measurement` carries its value and its model, so the one update
(:func:`.update.correct`) needs to know nothing else about it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from ..units import wrap_angle
from .jacobian_check import jacobian_fd


@runtime_checkable
class RobustKernel(Protocol):
    """Weight w(r) in (0, 1] of a measurement whose normalised residual is r = sqrt(NIS).

    The update uses it as one step of iteratively reweighted least squares: R is inflated to R / w,
    i.e. the measurement counts as if its noise were 1 / sqrt(w) times larger (Zhang 1997, M-estimators).
    """

    def weight(self, r: float) -> float: ...


@dataclass(frozen=True)
class Huber:
    """Huber's kernel: quadratic within ``k`` sigmas, linear beyond, w = min(1, k / r)."""

    k: float = 1.345  # 95 % efficiency on Gaussian data

    def weight(self, r: float) -> float:
        return 1.0 if r <= self.k else self.k / r


@dataclass(frozen=True)
class Cauchy:
    """Cauchy (Lorentzian) kernel, rho = c^2 / 2 log(1 + (r / c)^2), w = 1 / (1 + (r / c)^2)."""

    c: float = 2.3849  # 95 % efficiency on Gaussian data

    def weight(self, r: float) -> float:
        return 1.0 / (1.0 + (r / self.c) ** 2)


class MeasurementModel:
    """Base of the measurement models; subclasses give ``evaluate`` and ``covariance`` (and, better,
    an analytic ``jacobian``)."""

    kind: str = "measurement"
    #: indices of the measurement's components that are angles (residual wrapped to (-pi, pi])
    angles: tuple[int, ...] = ()
    kernel: RobustKernel | None = None
    #: degrees of freedom of the error state, when the state cannot tell (e.g. a nominal INS state)
    state_dof: int | None = None
    #: when H = [0 I 0] picks this block of the state (ZUPT, position fix), the update takes the
    #: block's rows and columns instead of multiplying by H: the same numbers, a few matrix products fewer
    selects: slice | None = None

    def evaluate(self, x) -> np.ndarray:
        raise NotImplementedError

    def jacobian(self, x) -> np.ndarray:
        return jacobian_fd(self, x)

    def covariance(self, x=None) -> np.ndarray:
        raise NotImplementedError

    def residual(self, z, z_pred: np.ndarray) -> np.ndarray:
        y = np.asarray(z, dtype=float) - z_pred
        if self.angles:
            y = np.array(y, dtype=float)
            for i in self.angles:
                y[i] = wrap_angle(float(y[i]))
        return y


class LinearModel(MeasurementModel):
    """z = H x + v, v ~ N(0, R): a linear observation of a plain vector state."""

    def __init__(self, H: np.ndarray, R: np.ndarray, kind: str = "linear", angles: tuple[int, ...] = ()):
        self.H = np.atleast_2d(np.asarray(H, dtype=float))
        self.R = np.atleast_2d(np.asarray(R, dtype=float))
        self.kind = kind
        self.angles = tuple(angles)

    def evaluate(self, x) -> np.ndarray:
        return self.H @ np.asarray(x, dtype=float)

    def jacobian(self, x) -> np.ndarray:
        return self.H

    def covariance(self, x=None) -> np.ndarray:
        return self.R


@dataclass(frozen=True)
class Measurement:
    """A measured value with its model (navlie's ``Measurement``): the update reads everything from it.

    ``t`` is the time of validity, s (None when it does not matter); ``meta`` is whatever the source
    wants to keep with it (e.g. the wire fix it came from).
    """

    value: np.ndarray
    model: MeasurementModel
    t: float | None = None
    meta: Any = None


def normalised_residual(nis: float) -> float:
    """r = sqrt(NIS), the argument of a robust kernel."""
    return math.sqrt(max(nis, 0.0))

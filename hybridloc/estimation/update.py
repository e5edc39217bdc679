"""The one gated Kalman update of hybridloc: every fix, zero-velocity update and pseudo-measurement
of the foot error-state filter and of the phone filters comes through :func:`correct`.

For a state x with covariance P and a measurement z with model h (Jacobian H, noise R):

    y = z (-) h(x)                         innovation (angle components wrapped)
    S = H P H^T + R                        innovation covariance
    NIS = y^T S^-1 y                       normalised innovation squared, ~ chi2(m) when consistent
    reject when NIS > chi2.ppf(p, m)       the gate (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4.2)
    K = P H^T S^-1                         gain
    dx = K y                               the correction, in the error state
    P+ = (I - K H) P (I - K H)^T + K R K^T Joseph form: symmetric positive definite whatever the rounding

``correct`` returns dx rather than x + dx: a plain-vector filter adds it, an error-state filter
injects it into its nominal state with its own ``plus`` and resets (:mod:`hybridloc.ins.eskf`).
It never mutates its inputs.

A robust kernel on the model (:class:`.models.Huber`, :class:`.models.Cauchy`) is applied after
the gate as one reweighting step: R -> R / w(sqrt(NIS)).
"""

from __future__ import annotations

import functools
from collections import Counter
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from .models import MeasurementModel, normalised_residual


@functools.lru_cache(maxsize=256)
def chi2_threshold(probability: float, dim: int) -> float:
    """The chi-square gate: NIS beyond ``chi2.ppf(probability, dim)`` is rejected."""
    return float(chi2.ppf(probability, dim))


@dataclass(frozen=True)
class ChiSquareGate:
    """Accept an innovation whose NIS lies inside the ``probability`` region of chi2(m).

    ``dim`` fixes the degrees of freedom of the threshold instead of the measurement's own m (a gate
    tuned on another dimension is kept this way where its figures depend on it).
    """

    probability: float
    dim: int | None = None

    def threshold(self, m: int) -> float:
        return chi2_threshold(self.probability, self.dim or m)


@dataclass(slots=True)
class UpdateInfo:
    """What one update did. ``innovation`` y, ``S`` its covariance, ``nis`` y^T S^-1 y, ``threshold`` the
    gate (inf when ungated), ``dx`` the correction (None when rejected), ``weight`` the robust kernel's."""

    kind: str
    accepted: bool
    innovation: np.ndarray
    S: np.ndarray
    nis: float
    threshold: float
    dx: np.ndarray | None = None
    weight: float = 1.0


class UpdateStats:
    """Accepted and rejected updates, counted per measurement kind."""

    def __init__(self) -> None:
        self.accepted: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()

    def record(self, info: UpdateInfo) -> None:
        (self.accepted if info.accepted else self.rejected)[info.kind] += 1

    @property
    def n_rejected(self) -> int:
        return sum(self.rejected.values())

    def as_dict(self) -> dict[str, dict[str, int]]:
        return {"accepted": dict(self.accepted), "rejected": dict(self.rejected)}


def inv_spd_small(S: np.ndarray) -> np.ndarray:
    """Inverse of a small symmetric positive definite matrix: closed form (adjugate over determinant)
    for 1-3 dimensions, where numpy's general inverse costs more than the rest of an update (the
    foot filter's ZUPT and ZARU run at every stance sample); numpy's for larger ones."""
    m = S.shape[0]
    if m > 3:
        return np.linalg.inv(S)
    s = S.tolist()  # Python floats: the same IEEE arithmetic as numpy's scalars, without their overhead
    if m == 1:
        return np.array([[1.0 / s[0][0]]])
    if m == 2:
        a, b, d = s[0][0], s[0][1], s[1][1]
        det = a * d - b * b
        if det > 0.0:
            return np.array([[d, -b], [-b, a]]) / det
    if m == 3:
        a, b, c = s[0]
        _, e, f = s[1]
        i = s[2][2]
        A, B, C = e * i - f * f, c * f - b * i, b * f - c * e
        det = a * A + b * B + c * C
        if det > 0.0:
            E, F, I_ = a * i - c * c, b * c - a * f, a * e - b * b
            return np.array([[A, B, C], [B, E, F], [C, F, I_]]) / det
    return np.linalg.inv(S)


@functools.lru_cache(maxsize=32)
def _identity(n: int) -> np.ndarray:
    eye = np.eye(n)
    eye.flags.writeable = False
    return eye


def _as_gate(gate: ChiSquareGate | float | None) -> ChiSquareGate | None:
    if gate is None or isinstance(gate, ChiSquareGate):
        return gate
    return ChiSquareGate(float(gate))


def correct(
    x,
    P: np.ndarray,
    z,
    model: MeasurementModel,
    gate: ChiSquareGate | float | None = None,
    stats: UpdateStats | None = None,
    compiled: bool = False,
) -> tuple[np.ndarray, np.ndarray, UpdateInfo]:
    """One gated Kalman update (module docstring); returns (dx, P+, info).

    ``gate``: a :class:`ChiSquareGate`, a probability (shorthand for ``ChiSquareGate(p)``), or None
    for no gate. A rejected measurement returns dx = 0 and P unchanged. ``stats`` counts the outcome
    under ``model.kind``.

    ``compiled``: the arithmetic of measurements of up to 3 components without a robust kernel runs
    compiled (:func:`._compiled.gated_joseph`: the same operations, several times faster on small
    matrices; its first use on a machine compiles it, about 7 s, then it is cached on disk). The foot
    filter asks for it (an update or two at every 200 Hz stance sample); filters updated a few times a
    second are better off without the compile.
    """
    z_pred = model.evaluate(x)
    H = model.jacobian(x)
    R = model.covariance(x)
    y = model.residual(z, z_pred)
    g = _as_gate(gate)
    threshold = g.threshold(len(y)) if g is not None else float("inf")
    kind = getattr(model, "kind", "measurement")
    sel = model.selects
    a, b, step = sel.indices(P.shape[0]) if sel is not None else (-1, -1, 1)
    if compiled and len(y) <= 3 and getattr(model, "kernel", None) is None and step == 1:
        kernels = _kernels()
        status, S, nis, dx, P_new = kernels.gated_joseph(_f64(P), _f64(H), _f64(R), _f64(y), a, b, threshold)
        if status != kernels.SINGULAR:
            accepted = status == kernels.ACCEPTED
            info = UpdateInfo(kind, accepted, y, S, nis, threshold, dx if accepted else None)
            if stats is not None:
                stats.record(info)
            return (dx, P_new, info) if accepted else (np.zeros(P.shape[0]), P, info)
    return _update_numpy(P, H, R, y, model, threshold, kind, stats)


@functools.cache
def _kernels():
    """The compiled arithmetic, imported on its first use: Numba's import (0.15-0.5 s) is not paid by
    the commands and processes that never ask for it."""
    from . import _compiled

    return _compiled


def _f64(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def _update_numpy(
    P: np.ndarray, H: np.ndarray, R: np.ndarray, y: np.ndarray, model: MeasurementModel, threshold: float, kind: str, stats: UpdateStats | None
) -> tuple[np.ndarray, np.ndarray, UpdateInfo]:
    """The update's arithmetic in numpy (module docstring): the reference of the compiled one, and the
    path of robust kernels and of measurements of more than 3 components."""
    sel = model.selects
    # H = [0 I 0] (``selects``): P H^T is P's block columns and H P H^T its block, exactly (the products
    # with H add zeros); otherwise the products themselves
    PHt = P[:, sel] if sel is not None else P @ H.T
    HPHt = PHt[sel] if sel is not None else H @ PHt
    S = HPHt + R
    S = 0.5 * (S + S.T)
    Sinv = inv_spd_small(S)
    nis = float(y @ Sinv @ y)
    if nis > threshold:
        info = UpdateInfo(kind, False, y, S, nis, threshold)
        if stats is not None:
            stats.record(info)
        return np.zeros(P.shape[0]), P, info
    weight = 1.0
    kernel = getattr(model, "kernel", None)
    if kernel is not None:
        weight = float(kernel.weight(normalised_residual(nis)))
        if weight < 1.0:
            R = R / weight
            S = HPHt + R
            S = 0.5 * (S + S.T)
            Sinv = inv_spd_small(S)
    K = PHt @ Sinv
    if sel is not None:  # I - K H, K H being K in the selected columns and zeros elsewhere
        IKH = np.array(_identity(P.shape[0]))
        IKH[:, sel] -= K
    else:
        IKH = _identity(P.shape[0]) - K @ H
    P_new = IKH @ P @ IKH.T + K @ R @ K.T  # Joseph form
    dx = K @ y
    info = UpdateInfo(kind, True, y, S, nis, threshold, dx, weight)
    if stats is not None:
        stats.record(info)
    return dx, 0.5 * (P_new + P_new.T), info

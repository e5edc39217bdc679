"""Step length models and their per-device calibration (Harle's survey, sec. V-A).

* :class:`ConstantLength`: L = c. Pedestrians keep a surprisingly constant natural step.
* :class:`WeinbergLength`: L = K (a_max - a_min)^(1/4), with a the vertical acceleration over the step
  (Weinberg 2002: within ~8 %).
* :class:`FrequencyLength`: L = a + b f, f the step frequency (a linear fit reaches ~5.6 % RMS).
* :class:`KimLength`: L = K (mean |a_v|)^(1/3), the mean absolute vertical acceleration over the step
  (Kim, Jang, Hwang and Park 2004, cited in Harle's survey as Kim et al.): an average over the whole
  step rather than its two extremes, so one jolt moves it less than Weinberg's bounce.
* :class:`BounceHeightLength`: L = K (mean |a_v| T^2)^(1/3), T the step's duration. The vertical
  acceleration of a bounce of height h repeated every T is ~ h (2 pi / T)^2, so mean |a_v| T^2 is
  proportional to h: this is Kim's model on the bounce height instead of its acceleration, which
  grows with cadence for the same step (``hybridloc eval pdr-phone`` on ILC site1, 2-fold cross-fit:
  segment length error median 9.0 %, p90 24.3 % against Kim's 9.7 / 26.2, Weinberg's 10.3 / 26.8,
  the step-frequency line's 11.2 / 30.3 and a constant length's 10.6 / 27.9; when the model was
  chosen, exponents 1/2 and 1/4 on h did worse: 9.9 / 28.4 and 9.8 / 26.3 against 9.5 / 26.1).

Calibration (:class:`LengthCalibrator`): every model is linear in its coefficients,
L_i = theta . phi_i, so a walked segment of known length D (between two absolute fixes or marks)
gives one linear equation D = theta . sum_i phi_i. A recursive least-squares estimator with a forgetting
factor updates theta online, segment by segment, and saves itself per device as JSON.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class StepFeatures:
    """What a length model may use about one step."""

    duration: float  # s since the previous step
    bounce: float  # max - min of vertical acceleration over the step, m/s^2
    mean_abs: float = 0.0  # mean |vertical acceleration - g| over the step, m/s^2

    @property
    def frequency(self) -> float:
        return 1.0 / self.duration


class LengthModel:
    """Base: a model linear in ``coef``; ``relative_sigma`` is its typical 1-sigma relative error."""

    name = "base"
    relative_sigma = 0.15
    coef: np.ndarray

    def regressors(self, f: StepFeatures) -> np.ndarray:
        raise NotImplementedError

    def length(self, f: StepFeatures) -> float:
        return max(0.0, float(self.regressors(f) @ self.coef))

    def to_dict(self) -> dict:
        return {"model": self.name, "coef": [float(c) for c in self.coef], "relative_sigma": self.relative_sigma}


class ConstantLength(LengthModel):
    name = "constant"
    relative_sigma = 0.15  # Weinberg: up to 40 % between people at one speed; ~15 % for one person

    def __init__(self, length: float = 0.7):
        self.coef = np.array([length])

    def regressors(self, f: StepFeatures) -> np.ndarray:
        return np.array([1.0])


class WeinbergLength(LengthModel):
    name = "weinberg"
    relative_sigma = 0.08  # Weinberg 2002, as reported in Harle's survey

    # Default K fitted on hand-held phones (Indoor Location Competition site1, 2-fold cross-fit);
    # calibrate per device for anything else.
    def __init__(self, K: float = 0.37):
        self.coef = np.array([K])

    def regressors(self, f: StepFeatures) -> np.ndarray:
        return np.array([max(f.bounce, 0.0) ** 0.25])


class FrequencyLength(LengthModel):
    name = "frequency"
    relative_sigma = 0.056  # linear step-frequency fit, RMS (Harle's survey, ref. 52)

    def __init__(self, a: float = 0.3, b: float = 0.2):
        self.coef = np.array([a, b])

    def regressors(self, f: StepFeatures) -> np.ndarray:
        return np.array([1.0, min(f.frequency, 4.0)])


class KimLength(LengthModel):
    name = "kim"
    relative_sigma = 0.08  # of Weinberg's order (Kim et al. report errors of a few %, on their walks)

    # Default K fitted like Weinberg's (ILC site1, 2-fold cross-fit); calibrate per device.
    def __init__(self, K: float = 0.46):
        self.coef = np.array([K])

    def regressors(self, f: StepFeatures) -> np.ndarray:
        return np.array([max(f.mean_abs, 0.0) ** (1.0 / 3.0)])


class BounceHeightLength(LengthModel):
    name = "height"
    relative_sigma = 0.08

    # Default K fitted on ILC site1 (2-fold cross-fit: 0.697 | 0.704); calibrate per device.
    def __init__(self, K: float = 0.70):
        self.coef = np.array([K])

    def regressors(self, f: StepFeatures) -> np.ndarray:
        # (mean |a_v| T^2)^(1/3): proportional to the cube root of the bounce height
        return np.array([(max(f.mean_abs, 0.0) * f.duration * f.duration) ** (1.0 / 3.0)])


MODELS = {"constant": ConstantLength, "weinberg": WeinbergLength, "frequency": FrequencyLength, "kim": KimLength, "height": BounceHeightLength}


def make_model(name: str, coef: list[float] | None = None) -> LengthModel:
    if name not in MODELS:
        raise ValueError(f"unknown step length model {name!r}; choose one of {sorted(MODELS)}")
    m = MODELS[name]()
    if coef is not None:
        if len(coef) != len(m.coef):
            raise ValueError(f"model {name} takes {len(m.coef)} coefficients, got {len(coef)}")
        m.coef = np.asarray(coef, dtype=float)
    return m


#: Relative residual beyond which a calibration segment is down-weighted (Huber). About 1.5 sigma of
#: a segment's relative error on ILC site1 (PDR scale +-9.4 % and the marks' +-0.67 m on 7 m): there,
#: cross-fitted with the marks' 0.5 m alone as a segment's noise, median segment error 9.4 -> 8.7 %,
#: p90 24.5 -> 24.1 % (least squares was pulled down by first segments 50-70 % long), waypoint error
#: mean 4.04 -> 4.09 m; 0.30: 9.0 %, 0.08: 8.6 %. With the segment scatter of calibrate_from_marks
#: added: 9.0 %, 24.3 %, 4.05 m.
HUBER_REL = 0.15

#: A calibration's prior on each coefficient, relative: about twice the spread of Weinberg's constant
#: between people, so one walk's few segments (one of them perhaps mis-marked) cannot swing a
#: device's calibration far.
PRIOR_REL_SIGMA = 0.1


class LengthCalibrator:
    """Recursive least squares for a length model's coefficients from segments of known length.

    Each segment gives D = theta . Phi with Phi = sum of the steps' regressors. With forgetting factor
    lambda (older segments weigh lambda^k), the information form is P^-1 <- lambda P^-1 + Phi Phi^T / s^2
    and theta follows the standard RLS gain. ``sigma_D`` (m) is the known distance's own uncertainty,
    so short segments and poor fixes count less. Robust (Huber) in the relative residual: a segment
    off by more than ``huber_rel`` of its length (a mis-marked waypoint, a fix from a look-alike place)
    weighs huber_rel D / |r| instead of fully, so a few bad distances cannot drag the coefficients.
    """

    def __init__(self, model: LengthModel, prior_rel_sigma: float = PRIOR_REL_SIGMA, forgetting: float = 0.98, huber_rel: float | None = HUBER_REL):
        self.model = model
        n = len(model.coef)
        # Prior: the model's default coefficients, each uncertain by prior_rel_sigma of itself.
        self.P = np.diag((prior_rel_sigma * np.maximum(np.abs(model.coef), 0.1)) ** 2)
        self.forgetting = forgetting
        self.huber_rel = huber_rel
        self.n_segments = 0
        self.sum_sq_rel = 0.0
        self._n = n

    def update(self, steps: list[StepFeatures], distance: float, sigma_distance: float = 0.5) -> None:
        if not steps or not (distance > 0 and math.isfinite(distance)):
            raise ValueError("a calibration segment needs steps and a positive distance")
        phi = np.sum([self.model.regressors(f) for f in steps], axis=0)
        pred = float(phi @ self.model.coef)
        r = distance - pred
        P = self.P / self.forgetting
        var_d = sigma_distance**2
        if self.huber_rel is not None and abs(r) > self.huber_rel * distance:
            # Huber: beyond huber_rel of the distance the residual counts linearly, not squared, i.e.
            # the segment weighs huber_rel D / |r| (its variance divided by that)
            var_d /= self.huber_rel * distance / abs(r)
        s = float(phi @ P @ phi) + var_d
        k = P @ phi / s
        self.model.coef = self.model.coef + k * r
        self.P = P - np.outer(k, phi @ P)
        self.P = 0.5 * (self.P + self.P.T)
        self.n_segments += 1
        self.sum_sq_rel += (r / distance) ** 2

    @property
    def rms_relative_residual(self) -> float:
        return math.sqrt(self.sum_sq_rel / self.n_segments) if self.n_segments else float("nan")

    def to_dict(self) -> dict:
        return {
            **self.model.to_dict(),
            "P": self.P.tolist(),
            "n_segments": self.n_segments,
            "forgetting": self.forgetting,
            "sum_sq_rel": self.sum_sq_rel,
            "huber_rel": self.huber_rel,
        }

    def save(self, path: str | os.PathLike) -> None:
        """Write the calibration (model, coefficients, covariance) as JSON, atomically."""
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_dict(), indent=1), encoding="utf-8")
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> LengthCalibrator:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
        c = cls(make_model(d["model"], d["coef"]), forgetting=float(d.get("forgetting", 0.98)), huber_rel=d.get("huber_rel", HUBER_REL))
        c.P = np.asarray(d["P"], dtype=float)
        c.n_segments = int(d.get("n_segments", 0))
        c.sum_sq_rel = float(d.get("sum_sq_rel", 0.0))
        return c


#: Shortest waypoint segment used to calibrate, m: on shorter ones the marks' own error (+-0.7 m on
#: ILC site1) is more than the PDR's scale error to be learned.
MIN_CALIBRATION_SEGMENT_M = 3.0


def calibrate_from_marks(
    cal: LengthCalibrator,
    step_t: np.ndarray,
    features: list[StepFeatures],
    mark_t: np.ndarray,
    mark_xy: np.ndarray,
    sigma_distance: float = 0.5,
    rel_scatter: float = 0.08,
    min_segment_m: float = MIN_CALIBRATION_SEGMENT_M,
) -> int:
    """Update ``cal`` from a walk with marked points (survey waypoints): each pair of consecutive marks
    at least ``min_segment_m`` apart is a known distance (straight line) for the steps between their
    times. Its error against the model is the marks' ``sigma_distance`` (m; two marks of ~0.35 m
    each) and the PDR's own scale scatter from one segment to the next, ``rel_scatter`` of D (ILC
    site1: +-7.7 %, a random part no coefficient can learn), so one segment cannot swing the
    calibration. Returns the number of segments used."""
    step_t = np.asarray(step_t, float)
    mark_t, mark_xy = np.asarray(mark_t, float), np.asarray(mark_xy, float)
    used = 0
    for k in range(len(mark_t) - 1):
        D = float(np.hypot(*(mark_xy[k + 1] - mark_xy[k])))
        idx = np.flatnonzero((step_t > mark_t[k]) & (step_t <= mark_t[k + 1]))
        if D >= min_segment_m and len(idx) >= 2:
            cal.update([features[i] for i in idx], D, sigma_distance=math.hypot(sigma_distance, rel_scatter * D))
            used += 1
    return used


def calibrate_from_scale(cal: LengthCalibrator, features: list[StepFeatures], scale: float, sigma_scale: float) -> bool:
    """Update ``cal`` from a step-length scale learned by fusion with absolute fixes (the Kalman
    filter's ``s``: true length = s x the model's): the walk's steps are one known distance,
    s times what the model gave them, uncertain by ``sigma_scale`` of it. Returns False (nothing
    learned) without steps or with a scale the fixes did not pin (sigma_scale not below a
    calibration's own prior, ``PRIOR_REL_SIGMA``)."""
    if not features or not (math.isfinite(scale) and math.isfinite(sigma_scale)) or scale <= 0 or sigma_scale >= PRIOR_REL_SIGMA:
        return False
    pred = float(sum(cal.model.length(f) for f in features))
    if pred <= 0:
        return False
    cal.update(features, scale * pred, sigma_distance=max(sigma_scale * pred, 1e-3))
    return True

"""One estimation core for every filter of hybridloc.

* :mod:`.models`: the measurement-model protocol (``evaluate``, ``jacobian``, ``covariance``,
  ``residual``, optional robust kernel) and :class:`~.models.Measurement`, which carries its model;
* :mod:`.update`: the one gated update, :func:`~.update.correct` (Joseph form, NIS, chi-square gate,
  rejections counted per kind), used by the foot error-state filter and the phone Kalman filters;
* :mod:`.jacobian_check`: finite-difference Jacobians, the default and the test oracle;
* :mod:`.resampling`: the particle filters' resamplers and log-weight helpers.
"""

from .jacobian_check import assert_jacobian, jacobian_fd
from .models import Cauchy, Huber, LinearModel, Measurement, MeasurementModel, RobustKernel
from .resampling import RESAMPLERS, bin_keys, kld_bound, kld_size, log_normalise, multinomial, resampler, residual, stratified, systematic
from .update import ChiSquareGate, UpdateInfo, UpdateStats, chi2_threshold, correct

__all__ = [
    "assert_jacobian",
    "jacobian_fd",
    "Cauchy",
    "Huber",
    "LinearModel",
    "Measurement",
    "MeasurementModel",
    "RobustKernel",
    "RESAMPLERS",
    "bin_keys",
    "kld_bound",
    "kld_size",
    "log_normalise",
    "multinomial",
    "resampler",
    "residual",
    "stratified",
    "systematic",
    "ChiSquareGate",
    "UpdateInfo",
    "UpdateStats",
    "chi2_threshold",
    "correct",
]

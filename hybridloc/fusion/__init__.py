"""Client-side fusion of PDR steps with absolute fixes.

* :class:`LocalFusion` (:mod:`.kalman`): Kourogi et al.'s position-domain Kalman filter (position,
  heading bias, step scale); needs nothing but steps and fixes.
* :class:`ParticleFusion` (:mod:`.particle`): the same inputs plus the site's map - walls the walker
  cannot cross and a walk prior (where people are, learnt from the crowd's labelled scans carried in
  the radio map, :mod:`.walkprior`) - as a particle filter.

Both have ``predict(step)`` / ``correct(fix)`` step APIs, a chi-square gate on every fix and the same
:class:`Estimate` output, so agents use either; :func:`run_fusion` (:mod:`.runner`) runs one over
recorded steps and fixes.
"""

from .gps import GpsDifferencer
from .kalman import Estimate, FusionConfig, LocalFusion
from .particle import ParticleConfig, ParticleFusion
from .runner import run_fusion
from .walkprior import WalkPrior

__all__ = ["GpsDifferencer", "Estimate", "FusionConfig", "LocalFusion", "ParticleConfig", "ParticleFusion", "WalkPrior", "run_fusion"]

"""Client-side fusion of PDR steps with absolute fixes.

* :class:`LocalFusion` (:mod:`.kalman`): Kourogi et al.'s position-domain Kalman filter (position,
  heading bias, step scale); needs nothing but steps and fixes.
* :class:`KourogiFusion` (:mod:`.kourogi`): the paper's own filter, state (x, y, v_x, v_y) with steps
  as observations (eqs 5-20), kept as the reference the others are measured against.
* :class:`ParticleFusion` (:mod:`.particle`): the same inputs plus the site's map - walls the walker
  cannot cross and a walk prior (where people are, learnt from the crowd's labelled scans carried in
  the radio map, :mod:`.walkprior`) - as a particle filter.

Both have ``predict(step)`` / ``correct(fix)`` step APIs, a chi-square gate on every fix and the same
:class:`Estimate` output, so agents use either; :func:`run_fusion` (:mod:`.runner`) runs one over
recorded steps and fixes.
"""

from .gps import GpsDifferencer
from .kalman import Estimate, FusionConfig, LocalFusion
from .kourogi import KourogiConfig, KourogiFusion
from .particle import ParticleConfig, ParticleFusion
from .runner import run_fusion, run_fusion_smoothed
from .walkprior import WalkPrior

__all__ = [
    "GpsDifferencer",
    "Estimate",
    "FusionConfig",
    "KourogiConfig",
    "KourogiFusion",
    "LocalFusion",
    "ParticleConfig",
    "ParticleFusion",
    "WalkPrior",
    "run_fusion",
    "run_fusion_smoothed",
]

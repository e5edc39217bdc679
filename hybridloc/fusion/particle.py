"""Particle filter fusion of PDR steps, absolute fixes and the site's map.

Each particle is a hypothesis (p_x, p_y, b_psi, s): position in the site frame (m), heading bias of
the PDR (rad) and step-length scale (-), the same state as :class:`~.kalman.LocalFusion`, so the two
filters answer alike; what the particles add is the map, which no Gaussian can carry.

* **Predict with a step** (Kourogi eqs 9-14, sampled): every particle moves by
  s (L + n_L) (cos(psi + b + n_psi), sin(psi + b + n_psi)), n_L ~ N(0, sigma_L^2) the stride error and
  n_psi ~ N(0, sigma_dpsi^2) the direction error of this step; b and s random-walk slowly. A particle
  whose move crosses a wall dies; the others are weighted by the walk prior at their new place
  (:mod:`.walkprior`): the motion model is the PDR's Gaussian times "where people walk", which pulls
  the cloud into corridors and through doors the way walkers go. The map enters through a
  constraint hook (:class:`MapConstraint`, default :class:`WalkPriorConstraint`): a log-likelihood per
  particle, -inf for a move through a wall or a place off the walkable area.
* **Correct with a fix**: one gated ``correct``. The gate is Kourogi sec. 3.3's, on the cloud's mean and
  covariance (a fix outside the 95 % region of the dead-reckoned estimate is rejected); accepted fixes
  weight particles by a heavy-tailed likelihood - (1 - eps) N(z; p, R) + eps N(z; p, k^2 R) - because
  WiFi fixes now and then land on a look-alike place. A fix that arrives after later steps (network and
  server latency) is compared with each particle's position at the scan's time, kept in a short
  per-particle history.
* **Weights** are kept as log-weights, normalised with logsumexp (a product of many small likelihoods
  never underflows to an all-zero cloud); ``w`` gives the normalised weights.
* **Resampling**: when the effective sample size 1 / sum w^2 falls below ``resample_ess`` N, with a
  pluggable scheme (``resampler``: systematic by default, or stratified, residual, multinomial, or any
  callable of :mod:`hybridloc.estimation.resampling`'s signature). Every per-particle array (position,
  bias, scale, prior at the particle, ancestry) is reordered together.
* **KLD-sampling** (Fox 2003; Woodman & Harle's filter, Harle's survey sec. VI): with
  ``kld_epsilon`` set, the count adapts. At every resampling, draws from the weighted cloud are binned
  over (x, y, heading) (``kld_bin_xy`` m, ``kld_bin_heading`` rad) and the count is the first M with
  M >= Fox's bound for the k bins they occupy (:func:`hybridloc.estimation.resampling.kld_size`),
  between ``n_min`` and ``n_max``; the M particles are then drawn by the resampler. After a step,
  when even all the present particles' bins would need fewer than half of them, the cloud is
  resampled to shrink. A start draws its own count the same way from the start distribution.
* **Start**: from the first fix (or ``init``), bias and scale from their priors. ``start="gaussian"``:
  positions drawn from the fix's Gaussian where the map allows. ``start="containment"`` (Beauregard's
  and Woodman & Harle's start, Harle sec. VI): positions uniform inside the first fix's 95 % region
  restricted to the walkable area - the :class:`~hybridloc.types.ContainmentRegion` the server sends
  with the fix when :meth:`ParticleFusion.correct` is given the whole :class:`~hybridloc.types.Fix`,
  else the fix covariance's 95 % ellipse. After ``reinit_after`` consecutive rejected fixes the track
  is considered lost and restarts from the fix (as LocalFusion does), the same way.
* **Ancestry** (Beauregard's backtracking, Klepal & Beauregard 2008): each step records the
  particles' positions and, for each, the index of its parent in the step before; a resampling only
  re-indexes the parents. Late fixes read a particle's position at the scan's time from its own
  lineage, and :meth:`ParticleFusion.smoothed` / :meth:`ParticleFusion.backtrack` give the fixed-lag
  smoothed track: the positions ``lag`` steps ago of the particles alive now, weighted by their present
  weights (Kitagawa's smoother by genealogy) - a particle that died at a wall or by a fix takes its
  whole past with it, so the surviving history is the smoothed track (:func:`~.runner.run_fusion` with
  ``smooth_lag``).
* **Re-anchor from the smoother** (:meth:`ParticleFusion.reanchor`, as
  :meth:`~.kalman.LocalFusion.reanchor`): the cloud is redrawn at the corrected track's latest time
  around its position and covariance (where the map allows), each particle's bias and scale shifted
  so that the cloud's means are the walk's, and the steps since are sampled again on top.

Random numbers come from an explicit ``numpy.random.Generator`` (default: seeded from ``config.seed``),
so a replay is reproducible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import shapely

from ..estimation import UpdateStats, chi2_threshold, log_normalise
from ..estimation import resampler as make_resampler
from ..estimation.resampling import Resampler, bin_keys, kld_bound, kld_grow
from ..types import AbsoluteFix, ContainmentRegion, DisplacementFix, Fix, StepEvent
from ..units import wrap_angle
from .kalman import (
    Estimate,
    StepMemory,
    _shift_floor,
    check_reanchor,
    correlated_fix_cov,
    fix_handler,
    floor_after_fix,
    nearest_grid_direction,
    straight_along,
)
from .walkprior import WalkPrior

#: log of the smallest prior a particle's old place counts with (the step's likelihood divides by it)
LOG_PRIOR_FLOOR = math.log(1e-12)


class MapConstraint(Protocol):
    """The constraint hook of :class:`ParticleFusion`: what the site's map says, as log-likelihoods.

    ``log_density(floor, p)`` (N,): log of how likely a walker is at each place p (N, 2), -inf where
    no one can be (off the walkable area); ``log_transition(floor, p, q)`` (N,): 0 for a move p -> q
    the map allows, -inf for one through a wall.
    """

    def log_density(self, floor: str | None, p: np.ndarray) -> np.ndarray: ...

    def log_transition(self, floor: str | None, p: np.ndarray, q: np.ndarray) -> np.ndarray: ...


class WalkPriorConstraint:
    """:class:`MapConstraint` of a :class:`~.walkprior.WalkPrior`: log pi(p), and -inf across walls."""

    def __init__(self, prior: WalkPrior):
        self.prior = prior

    def log_density(self, floor: str | None, p: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return np.log(self.prior.at(floor, p))

    def log_transition(self, floor: str | None, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        return np.where(self.prior.crosses_wall(floor, p, q), -np.inf, 0.0)


@dataclass
class ParticleConfig:
    n_particles: int = 1000
    gate_probability: float = 0.95  # Kourogi sec. 3.3
    # initial heading-bias spread (magnetometer heading indoors), rad. ILC site1 eval fusion replays
    # with the map, cold start: 20 deg 4.51 m, 30 deg 4.58, 45 deg 4.59, 60 deg 4.70. (A wider prior
    # "with a map" once looked better, an artefact of the resampling bug fixed alongside.)
    sigma_bias0: float = math.radians(20.0)
    sigma_scale0: float = 0.15  # initial step-length scale spread
    bias_rw: float = math.radians(0.5)  # per step
    scale_rw: float = 0.003  # per step
    min_sigma_turn: float = math.radians(2.0)  # per-step direction noise floor (the PDR's own is optimistic)
    min_sigma_length: float = 0.05  # m, per-step stride noise floor
    outlier_prob: float = 0.1  # share of fixes from a look-alike place
    outlier_scale: float = 3.0  # their spread, in fix sigmas
    resample_ess: float = 0.5
    reinit_after: int = 5
    #: another floor is taken from a fix naming it with at least this probability (its kNN vote: 3 of 5
    #: neighbours). Simulated site with stairs (eval fusion, 15 clients): floor hit 84.3 % at 0.8, 90.4 % at
    #: 0.6, the raw fixes' floors 93.6 %; ILC site1 (one floor per walk) stays at 100 %.
    floor_switch: float = 0.6
    #: A cloud born on the wrong side of a wall cannot walk through it to where the fixes are. When a
    #: fix lies beyond a wall from the cloud's mean and outside its 50 % region, this share of the
    #: particles is redrawn around the fix (sensor resetting, Lenser & Veloso 2000), where the map
    #: allows; a fix off on open floor, however far, redraws nothing.
    reset_share: float = 0.3
    history: int = 64  # steps of per-particle history (ancestry) for late fixes and the smoothed track
    #: "gaussian": the start cloud drawn from the first fix's Gaussian; "containment": uniform in its
    #: 95 % region (the server's containment region, else the covariance ellipse) on the walkable area
    start: str = "gaussian"
    #: KLD-sampling (module docstring): None keeps n_particles fixed; else Fox's epsilon (the bound on
    #: the KL divergence), delta (its 1 - confidence), the bins and the count's limits
    kld_epsilon: float | None = None
    kld_delta: float = 0.01
    kld_bin_xy: float = 0.5  # m
    kld_bin_heading: float = math.radians(10.0)
    n_min: int = 200
    n_max: int = 50_000
    seed: int = 0
    fix_correlation: dict = field(default_factory=lambda: {"wifi": 0.5, "ble": 0.5})  # as FusionConfig.fix_correlation
    # heuristic drift elimination along the floor's grid, as FusionConfig.corridor_* (with corridor_axes).
    # ILC site1 replays with the map, cold / start known: none 4.45 / 3.09 m; 10 deg 4.33 / 2.88;
    # 20 deg 4.32 / 2.94; 30 deg 4.32 / 3.02. (Deciding per particle instead of on the cloud's mean
    # heading favoured particles that a large bias aligned with the grid on a diagonal: 4.89 cold.)
    corridor_sigma: float = math.radians(10.0)
    corridor_capture: float = math.radians(20.0)
    straight_steps: int = 6
    straight_tol: float = math.radians(10.0)


class ParticleFusion:
    """Particle filter with the :class:`~.kalman.LocalFusion` interface (``predict``, ``correct``, ``estimate``)."""

    def __init__(
        self,
        prior: WalkPrior | None = None,
        config: ParticleConfig | None = None,
        init: tuple[float, float, float] | None = None,
        floor: str | None = None,
        rng: np.random.Generator | None = None,
        heading_bias: tuple[float, float] | None = None,
        corridor_axes: dict[str, float] | None = None,
        constraint: MapConstraint | None = None,
        resampler: str | Resampler = "systematic",
    ):
        """``init`` = (x, y, sigma) of a known start; ``heading_bias`` = (mean, sigma) rad of the PDR's
        heading bias when known, else 0 +- ``config.sigma_bias0``; ``corridor_axes`` as for
        :class:`~.kalman.LocalFusion` (heuristic drift elimination); ``constraint`` the map's hook
        (default: the walk prior's walls and walkable area); ``resampler`` a scheme's name or callable."""
        self.cfg = config or ParticleConfig()
        if self.cfg.n_particles < 10:
            raise ValueError("a particle filter needs at least 10 particles")
        if self.cfg.start not in ("gaussian", "containment"):
            raise ValueError(f"ParticleConfig.start must be 'gaussian' or 'containment', got {self.cfg.start!r}")
        if self.cfg.kld_epsilon is not None:
            kld_bound(2, self.cfg.kld_epsilon, self.cfg.kld_delta)  # checks epsilon and delta
            if not 10 <= self.cfg.n_min <= self.cfg.n_max:
                raise ValueError(f"KLD-sampling needs 10 <= n_min <= n_max, got {self.cfg.n_min}, {self.cfg.n_max}")
            if not (self.cfg.kld_bin_xy > 0 and self.cfg.kld_bin_heading > 0):
                raise ValueError("KLD-sampling bins must be positive")
        if self.cfg.history < 2:
            raise ValueError("ParticleConfig.history must keep at least 2 steps")
        self.prior = prior or WalkPrior({})
        self.constraint: MapConstraint = constraint if constraint is not None else WalkPriorConstraint(self.prior)
        self.resampler = make_resampler(resampler)
        self.rng = rng if rng is not None else np.random.default_rng(self.cfg.seed)
        n = self.cfg.n_particles
        self.p = np.zeros((n, 2))
        self.b = np.zeros(n)
        self.s = np.ones(n)
        self.logw = np.full(n, -math.log(n))  # normalised log-weights
        self._logpi = np.zeros(n)  # log of the walk prior at each particle's place
        self.floor = floor
        self._bias0 = heading_bias if heading_bias is not None else (0.0, self.cfg.sigma_bias0)
        self.t = -math.inf
        self.initialised = False
        self.n_rejected = 0
        self.stats = UpdateStats()  # fixes and displacements accepted / rejected, per kind
        self.n_map_conflicts = 0  # steps after which no particle was left where the map allows
        self.corridor_axes = dict(corridor_axes or {})
        self._recent_headings: list[float] = []
        self.n_corridor = 0
        self._rejected_run = 0
        self.n_reset = 0  # particles redrawn around fixes beyond a wall
        self._gate = chi2_threshold(self.cfg.gate_probability, 2)
        self._half = chi2_threshold(0.5, 2)
        H = self.cfg.history
        # the ancestry ring (module docstring): per recorded step k (ring index k % H) the particles'
        # positions, each one's parent index in step k - 1's arrays, and the shift a reset particle's
        # lineage carries before it (None when none was reset)
        self._hist_p: list[np.ndarray | None] = [None] * H
        self._hist_a: list[np.ndarray | None] = [None] * H
        self._hist_o: list[np.ndarray | None] = [None] * H
        self._hist_t = np.full(H, -math.inf)
        self._hist_k = 0  # number of steps recorded (ring index = k % H)
        self._anc = np.arange(n)  # each particle's index in the newest recorded step
        self._off: np.ndarray | None = None  # (N, 2) shift of each particle's lineage since then (resets)
        self._region: ContainmentRegion | None = None  # the region of the fix being handled
        self.steps_seen = 0  # steps predicted once initialised, and their particle counts
        self.particle_steps = 0
        self.particle_max = 0
        self._memory = StepMemory()  # the steps taken, for reanchor
        self.n_reanchored = 0
        if init is not None:
            self._start(np.asarray(init[:2], float), np.eye(2) * init[2] ** 2, None)

    # ------------------------------------------------------------------ state summaries
    #: :meth:`correct` takes the server's whole answer (:class:`~hybridloc.types.Fix`, its region starts the cloud)
    takes_regions = True

    @property
    def n_particles(self) -> int:
        """The present number of particles (changes under KLD-sampling)."""
        return len(self.logw)

    @property
    def w(self) -> np.ndarray:
        """The normalised weights, exp(log w) (read-only view of the log-weights)."""
        return np.exp(self.logw)

    def _mean_cov(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = self.w
        m = w @ p
        d = p - m
        cov = (d * w[:, None]).T @ d
        return m, 0.5 * (cov + cov.T) + np.eye(2) * 1e-9

    def estimate(self, kind: str) -> Estimate:
        m, c = self._mean_cov(self.p)
        return Estimate(self.t, m, c, self.floor, kind)

    # ------------------------------------------------------------------ start
    def _start(self, z: np.ndarray, R: np.ndarray, floor: str | None, region: ContainmentRegion | None = None) -> None:
        """A new cloud at a fix z, R (and the server's 95 % region, for ``start="containment"``)."""
        if floor is not None:
            self.floor = floor
        cfg = self.cfg
        if cfg.kld_epsilon is None:
            n = cfg.n_particles
            p = self._draw_start(z, R, region, n)
            b = self.rng.normal(self._bias0[0], self._bias0[1], n)
            s = 1.0 + self.rng.normal(0.0, cfg.sigma_scale0, n)
        else:  # KLD-sampling from the start distribution: draw until the bound of the bins occupied is met
            drawn: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

            def draw(k: int) -> np.ndarray:
                pk = self._draw_start(z, R, region, k)
                bk = self.rng.normal(self._bias0[0], self._bias0[1], k)
                drawn.append((pk, bk, 1.0 + self.rng.normal(0.0, cfg.sigma_scale0, k)))
                return bin_keys(pk, bk, cfg.kld_bin_xy, cfg.kld_bin_heading)

            m0 = max(cfg.n_min, min(cfg.n_particles, cfg.n_max))
            n = kld_grow(draw, m0, cfg.kld_epsilon, cfg.kld_delta, cfg.n_min, cfg.n_max)
            p, b, s = (np.concatenate(part)[:n] for part in zip(*drawn))
        self._place(p, b, s)

    def _draw_start(self, z: np.ndarray, R: np.ndarray, region: ContainmentRegion | None, n: int) -> np.ndarray:
        """n start positions: from N(z, R) (``start="gaussian"``) or uniform in the 95 % region on the
        walkable area (``start="containment"``; the Gaussian draw when none of it is walkable)."""
        if self.cfg.start == "containment":
            p = self._draw_uniform(z, R, region, n)
            if p is not None:
                return p
        return self._draw(z, R, n)

    def _draw_uniform(self, z: np.ndarray, R: np.ndarray, region: ContainmentRegion | None, n: int) -> np.ndarray | None:
        """n positions uniform in ``region`` (its floor the cloud's, or unknown) or, without one, in the
        95 % ellipse of N(z, R), where the map allows (rejection); None when a few thousand tries find
        no allowed place in it."""
        use_region = region is not None and region.area_m2 > 0 and (region.floor is None or self.floor is None or region.floor == self.floor)
        chi = math.sqrt(self._gate)  # the 95 % ellipse: (p - z)' R^-1 (p - z) <= chi2_2(0.95)
        L = np.linalg.cholesky(R + np.eye(2) * 1e-9)
        if use_region:
            assert region is not None
            area = region.area
            shapely.prepare(area)
            x0, y0, x1, y1 = area.bounds
            share = max(area.area / max((x1 - x0) * (y1 - y0), 1e-9), 1e-3)
        else:
            share = 1.0
        got: list[np.ndarray] = []
        have = tried = 0
        acc = share  # the share of candidates kept (the region's share of its box, then as measured)
        while have < n:
            k = int(min(max(1.2 * (n - have) / acc, 256), 2_000_000))
            if use_region:
                q = np.column_stack([self.rng.uniform(x0, x1, k), self.rng.uniform(y0, y1, k)])
                q = q[shapely.contains_xy(area, q[:, 0], q[:, 1])]
            else:  # uniform in the unit disc, mapped onto the ellipse
                r = np.sqrt(self.rng.random(k))
                a = self.rng.uniform(0.0, 2.0 * math.pi, k)
                q = z + (chi * np.column_stack([r * np.cos(a), r * np.sin(a)])) @ L.T
            q = q[self.constraint.log_density(self.floor, q) > -np.inf]
            tried += k
            have += len(q)
            got.append(q)
            if have == 0 and tried >= 20_000:
                return None
            acc = max(have / tried, 1e-4) if have else acc * 0.1
        return np.concatenate(got)[:n]

    def _draw(self, z: np.ndarray, R: np.ndarray, n: int | None = None) -> np.ndarray:
        """n positions (default ``n_particles``) from N(z, R) where the map allows (a few rounds of
        rejection; what is left stays where it fell)."""
        n = self.cfg.n_particles if n is None else n
        L = np.linalg.cholesky(R + np.eye(2) * 1e-9)
        p = z + self.rng.standard_normal((n, 2)) @ L.T
        for _ in range(10):
            bad = self.constraint.log_density(self.floor, p) == -np.inf
            if not bad.any():
                break
            p[bad] = z + self.rng.standard_normal((int(bad.sum()), 2)) @ L.T
        return p

    def _place(self, p: np.ndarray, b: np.ndarray, s: np.ndarray) -> None:
        """A new cloud (positions, biases, scales): equal weights times the map's prior at each place, no history."""
        n = len(p)
        self.p, self.b, self.s = p, b, s
        self.logw = np.full(n, -math.log(n))
        self._hist_t[:] = -math.inf
        self._hist_p = [None] * self.cfg.history
        self._hist_a = [None] * self.cfg.history
        self._hist_o = [None] * self.cfg.history
        self._hist_k = 0
        self._anc, self._off = np.arange(n), None
        self._logpi = self.constraint.log_density(self.floor, self.p)
        self._weigh(self._logpi.copy())
        self.initialised = True

    def set_prior(self, prior: WalkPrior) -> None:
        """Use a new walk prior (a new radio map version of the site): the map's constraint hook becomes
        the prior's, and each particle's prior at its place is the new one's (the next step weighs by it)."""
        self.prior = prior
        self.constraint = WalkPriorConstraint(prior)
        if self.initialised:
            self._logpi = self.constraint.log_density(self.floor, self.p)

    # ------------------------------------------------------------------ weights
    def _weigh(self, loglike: np.ndarray) -> bool:
        """Add ``loglike`` to the log-weights and normalise (logsumexp); False (weights untouched) if
        that leaves nothing (every particle at -inf)."""
        logw, total = log_normalise(self.logw + loglike)
        if not np.isfinite(total):
            return False
        self.logw = logw
        w = np.exp(logw)
        if 1.0 / float(w @ w) < self.cfg.resample_ess * len(w):
            self._resample(w)
        return True

    def _pick(self, u: np.ndarray) -> np.ndarray:
        """Particle indices at cumulative-weight positions ``u`` in [0, 1): each index as often as its weight says."""
        c = np.cumsum(self.w)
        c[-1] = 1.0
        return np.searchsorted(c, u)

    def _resample(self, w: np.ndarray) -> None:
        if self.cfg.kld_epsilon is None:
            idx = self.resampler(w, self.rng)
        else:  # KLD-sampling: as many as the bins of independent draws from the cloud say, drawn by the resampler
            idx = self.resampler(w, self.rng, self._kld_count(w))
        n = len(idx)
        self.p, self.b, self.s, self._logpi = self.p[idx], self.b[idx], self.s[idx], self._logpi[idx]
        self._anc = self._anc[idx]  # the history stays; only who descends from whom changes
        if self._off is not None:
            self._off = self._off[idx]
        self.logw = np.full(n, -math.log(n))

    def _kld_count(self, w: np.ndarray) -> int:
        """Fox's KLD-sampling count for the weighted cloud: independent draws, binned over (x, y,
        heading bias: with the step heading every particle shares, its heading), until the draws
        satisfy the bound of the bins they occupy (:func:`~hybridloc.estimation.resampling.kld_size`),
        within [n_min, n_max]."""
        cfg = self.cfg
        assert cfg.kld_epsilon is not None
        c = np.cumsum(w)
        c[-1] = 1.0

        def draw(k: int) -> np.ndarray:
            idx = np.searchsorted(c, self.rng.random(k))
            return bin_keys(self.p[idx], self.b[idx], cfg.kld_bin_xy, cfg.kld_bin_heading)

        return kld_grow(draw, max(cfg.n_min, min(len(w), cfg.n_max)), cfg.kld_epsilon, cfg.kld_delta, cfg.n_min, cfg.n_max)

    def _kld_shrink(self) -> None:
        """KLD-sampling between resamplings: when the bins of all the present particles would need
        fewer than half of them, resample (to the count the bound gives)."""
        cfg = self.cfg
        n = len(self.logw)
        if cfg.kld_epsilon is None or n <= 2 * cfg.n_min:
            return
        k = len(np.unique(bin_keys(self.p, self.b, cfg.kld_bin_xy, cfg.kld_bin_heading)))
        if float(kld_bound(k, cfg.kld_epsilon, cfg.kld_delta)) < 0.5 * n:
            self._resample(self.w)

    # ------------------------------------------------------------------ predict
    def predict(self, step: StepEvent) -> Estimate:
        """Move every particle by one step (Kourogi eqs 9-14, sampled) and weigh it by the map."""
        self._memory.add(step)
        self.t = step.t
        if step.floor_change and self.floor is not None:
            self.floor = _shift_floor(self.floor, step.floor_change, {*self.prior.floors, *self.corridor_axes})
        if not self.initialised:
            return self.estimate("step")
        self._move(step)
        self._corridor(step)
        self._kld_shrink()
        self._record(step.t)
        self.steps_seen += 1
        self.particle_steps += self.n_particles
        self.particle_max = max(self.particle_max, self.n_particles)
        return self.estimate("step")

    def _move(self, step: StepEvent) -> None:
        """Every particle moved by one step, sampled, and weighed by the map; what :meth:`reanchor` re-applies."""
        n = len(self.w)
        cfg = self.cfg
        sig_l = max(step.sigma_length, cfg.min_sigma_length)
        sig_psi = max(step.sigma_heading_change or 0.0, cfg.min_sigma_turn)
        self.b = self.b + self.rng.normal(0.0, cfg.bias_rw, n)
        self.s = np.clip(self.s + self.rng.normal(0.0, cfg.scale_rw, n), 0.5, 1.5)
        L = self.s * np.maximum(step.length + self.rng.normal(0.0, sig_l, n), 0.0)
        psi = step.heading + self.b + self.rng.normal(0.0, sig_psi, n)
        q = self.p + np.column_stack([L * np.cos(psi), L * np.sin(psi)])
        # the map's constraint hook: log pi(new), -inf off the walkable area or through a wall
        logpi_new = self.constraint.log_density(self.floor, q) + self.constraint.log_transition(self.floor, self.p, q)
        # the prior enters once, at the particle's present place: weight by pi(new) / pi(old), so a
        # particle that stays in a sparsely walked spot is not penalised again at every step
        loglike = logpi_new - np.maximum(self._logpi, LOG_PRIOR_FLOOR)
        # the new places and their prior go in before weighing: a resampling inside _weigh reorders
        # both together (assigning pi_new after it once paired resampled particles with other
        # particles' prior, and a dead one's 0 then weighed its new owner by 1e12 at the next step)
        prev_logpi = self._logpi
        self.p, self._logpi = q, logpi_new
        if not self._weigh(loglike):
            # nobody is where the map allows: the map or the track is wrong here - keep dead reckoning
            self._logpi = prev_logpi
            self.n_map_conflicts += 1

    def _record(self, t: float) -> None:
        """Every particle's position at time t into the history ring (for late fixes)."""
        k = self._hist_k % self.cfg.history
        self._hist_p[k] = self.p.copy()
        self._hist_a[k] = self._anc
        self._hist_o[k] = self._off
        self._hist_t[k] = t
        self._hist_k += 1
        self._anc, self._off = np.arange(len(self.p)), None

    # ------------------------------------------------------------------ re-anchoring from the smoother
    @property
    def reanchor_horizon(self) -> float:
        """The earliest time :meth:`reanchor` takes (the filter's start, or its oldest kept step)."""
        return self._memory.horizon

    def reanchor(self, t: float, pos, cov, floor: str | None, heading_bias: float | None = None, scale: float | None = None) -> Estimate:
        """Re-anchor on the smoother's estimate at time ``t`` (as :meth:`.kalman.LocalFusion.reanchor`,
        whose docstring has the math and the bias/scale conventions), the cloud's way:

        * the positions at t are redrawn from N(p_s, C_s) where the map allows (C_s not finite: the
          cloud's own spread at t); the smoothed position is independent of the filter's, so every
          particle's place is drawn afresh;
        * each particle keeps a bias and scale of the present cloud (drawn by weight), shifted so that
          the cloud's circular mean bias is ``heading_bias`` and its mean scale ``scale`` (kept when
          None): the filter's spread of them stays, as P_bs does in the Kalman filter;
        * the steps since t are sampled again on top (:meth:`_move`, walls and walk prior included),
          so the cloud moves by the correction at t and goes on with the steps.

        Raises ValueError when t is before the filter started or older than the steps it keeps, and for
        a cloud not yet initialised given no finite covariance (a cloud not yet initialised starts here).
        """
        z, R = check_reanchor(self._memory, t, pos, cov)
        if not np.isfinite(R).all():
            if not self.initialised:
                raise ValueError("a particle filter not yet started needs the track's covariance to re-anchor")
            R = self._mean_cov(self._positions_at(t))[1]
        since = self._memory.since(t)
        t_now = self.t
        if floor:
            self.floor = floor
        n = self.cfg.n_particles
        if self.initialised:
            idx = self.resampler(self.w, self.rng)  # the cloud's (bias, scale) pairs, by weight
            b, sc = self.b[idx].copy(), self.s[idx].copy()
        else:
            b = self.rng.normal(self._bias0[0], self._bias0[1], n)
            sc = 1.0 + self.rng.normal(0.0, self.cfg.sigma_scale0, n)
        if heading_bias is not None:
            b = heading_bias + wrap_angle(b - math.atan2(float(np.sin(b).mean()), float(np.cos(b).mean())))
        if scale is not None:
            sc = np.clip(scale + (sc - sc.mean()), 0.5, 1.5)
        self._place(self._draw(z, R, len(b)), b, sc)  # as many as the cloud has (KLD-sampling changes the count)
        self._record(t)
        for step in since:  # the same steps, sampled again from the smoothed state
            if step.floor_change and self.floor is not None:
                self.floor = _shift_floor(self.floor, step.floor_change, {*self.prior.floors, *self.corridor_axes})
            self._move(step)
            self._record(step.t)
        self.t = max(t_now, t)
        self._rejected_run = 0
        self.n_reanchored += 1
        return self.estimate("reanchor")

    def _corridor(self, step: StepEvent) -> None:
        """Heuristic drift elimination (as :meth:`.kalman.LocalFusion._corridor`): after a straight
        stretch, when the cloud's corrected heading (step heading + weighted circular mean of the
        biases) lies within the capture of the floor's grid, every particle is weighed by the
        Gaussian of its own heading's offset from that grid direction. The decision is the cloud's,
        not each particle's: on a diagonal corridor, particles whose large bias happens to align
        them with the grid must not be favoured."""
        cfg = self.cfg
        axis = self.corridor_axes.get(self.floor) if self.floor is not None else None
        if not straight_along(self._recent_headings, step.heading, axis, cfg.straight_steps, cfg.straight_tol):
            return
        w = self.w
        b_mean = math.atan2(float(w @ np.sin(self.b)), float(w @ np.cos(self.b)))
        psi = step.heading + b_mean
        target = nearest_grid_direction(psi, axis)  # the grid direction nearest the cloud's heading
        if abs(wrap_angle(target - psi)) >= cfg.corridor_capture:
            return
        y = wrap_angle(target - (step.heading + self.b))  # each particle's offset
        if self._weigh(-0.5 * (y / cfg.corridor_sigma) ** 2):
            self.n_corridor += 1

    def _lineage(self, depths: list[int]) -> dict[int, np.ndarray]:
        """The present particles' positions ``d`` recorded steps back (0: the newest record), for each
        d of ``depths`` (each < the records kept), traced through the parents and reset shifts."""
        H = self.cfg.history
        out: dict[int, np.ndarray] = {}
        want = sorted(set(depths))
        wanted = set(want)
        if not want:
            return out
        idx = self._anc
        off = self._off.copy() if self._off is not None else None
        newest = self._hist_k - 1
        for d in range(want[-1] + 1):
            r = (newest - d) % H
            if d in wanted:
                pos = self._hist_p[r][idx]  # type: ignore[index]
                out[d] = pos + off if off is not None else pos
            if d == want[-1]:
                break
            o = self._hist_o[r]
            if o is not None:
                off = o[idx] if off is None else off + o[idx]
            idx = self._hist_a[r][idx]  # type: ignore[index]
        return out

    def _positions_at(self, t: float) -> np.ndarray:
        """Each particle's position at time t (linear between recorded steps; now if t is newer),
        from its own lineage."""
        H = self.cfg.history
        m = min(self._hist_k, H)
        if m == 0 or t >= self._hist_t[(self._hist_k - 1) % H]:
            return self.p
        ts = np.array([self._hist_t[(self._hist_k - m + i) % H] for i in range(m)])  # oldest .. newest
        j = int(np.searchsorted(ts, t, side="right"))  # ts[j-1] <= t < ts[j]
        if j == 0:
            return self._lineage([m - 1])[m - 1]
        da, db = m - j, m - 1 - j  # depths of the records before and after t
        got = self._lineage([da, db])
        u = (t - ts[j - 1]) / max(ts[j] - ts[j - 1], 1e-9)
        return (1.0 - u) * got[da] + u * got[db]

    # ------------------------------------------------------------------ smoothed track
    def smoothed(self, lag: int) -> Estimate | None:
        """The fixed-lag smoothed estimate ``lag`` steps back (0: the newest step): the positions then of
        the particles alive now, weighted by their present weights (module docstring); None when fewer
        steps are kept (``lag`` >= history, or the cloud is younger)."""
        if lag < 0:
            raise ValueError("the smoothing lag is a number of steps >= 0")
        m = min(self._hist_k, self.cfg.history)
        if not self.initialised or lag >= m:
            return None
        p = self._lineage([lag])[lag]
        mu, c = self._mean_cov(p)
        return Estimate(float(self._hist_t[(self._hist_k - 1 - lag) % self.cfg.history]), mu, c, self.floor, "smoothed")

    def backtrack(self) -> list[Estimate]:
        """Backtracking (Klepal & Beauregard): the smoothed estimates of every kept step, oldest first,
        from the lineages of the particles alive now (what :meth:`smoothed` gives for each lag at once)."""
        m = min(self._hist_k, self.cfg.history) if self.initialised else 0
        got = self._lineage(list(range(m)))
        out = []
        for d in range(m - 1, -1, -1):
            mu, c = self._mean_cov(got[d])
            out.append(Estimate(float(self._hist_t[(self._hist_k - 1 - d) % self.cfg.history]), mu, c, self.floor, "smoothed"))
        return out

    # ------------------------------------------------------------------ correct
    def correct(self, fix: AbsoluteFix | DisplacementFix | Fix) -> tuple[bool, Estimate]:
        """One gated update with a position fix or a displacement; returns (accepted, estimate). The
        server's whole answer (:class:`~hybridloc.types.Fix`) is taken too: its fix goes through the
        same gate, its containment region starts the cloud (``start="containment"``); a "no fix"
        answer changes nothing (not accepted)."""
        if isinstance(fix, Fix):
            if fix.fix is None:
                return False, self.estimate("no-fix")
            self._region = fix.region
            try:
                return self._correct_position(fix.fix)
            finally:
                self._region = None
        return getattr(self, fix_handler(self, fix))(fix)

    def _correct_position(self, fix: AbsoluteFix) -> tuple[bool, Estimate]:
        z = np.asarray(fix.pos_enu, float)[:2]
        R = correlated_fix_cov(np.asarray(fix.cov, float)[:2, :2], fix, self.cfg.fix_correlation)
        if not (np.isfinite(z).all() and np.isfinite(R).all()) or np.linalg.eigvalsh(0.5 * (R + R.T)).min() <= 0:
            raise ValueError("a fix needs a finite position and a positive-definite covariance")
        self._memory.started(fix.t)
        if not self.initialised:
            self._start(z, R, fix.floor, self._region)
            self.t = max(self.t, fix.t)
            return True, self.estimate("init")
        p_then = self._positions_at(fix.t)
        m, nis = self._nis(z, p_then, R)
        # outside the cloud's 50 % region and behind a wall from its mean: sensor resetting (reset_share)
        beyond_wall = (
            self.cfg.reset_share > 0.0 and nis > self._half and bool(self.constraint.log_transition(self.floor, m[None, :], z[None, :])[0] == -np.inf)
        )
        if nis > self._gate:
            self.n_rejected += 1
            self.stats.rejected["position"] += 1
            self._rejected_run += 1
            if self._rejected_run >= self.cfg.reinit_after:  # lost: the fixes agree with each other, not with us
                self._rejected_run = 0
                self._start(z, R, fix.floor, self._region)
                self.t = max(self.t, fix.t)
                return True, self.estimate("init")
            if beyond_wall:
                self._reset_around(z, R, p_then)
            return False, self.estimate("fix-rejected")
        self._rejected_run = 0
        self.stats.accepted["position"] += 1
        lineage = self._anc
        self._weigh(self._log_likelihood(z, p_then, R))
        if beyond_wall:  # the positions then of the particles now: a resampling in _weigh reorders (under KLD resizes) the cloud
            self._reset_around(z, R, p_then if self._anc is lineage else self._positions_at(fix.t))
        self.t = max(self.t, fix.t)
        self.floor = floor_after_fix(self.floor, fix, self.cfg.floor_switch)
        return True, self.estimate("fix")

    def _reset_around(self, z: np.ndarray, R: np.ndarray, p_then: np.ndarray) -> None:
        """Redraw ``reset_share`` of the particles around the fix z (drawn at the fix's time, moved to
        now as their donors moved since), where the map allows; each keeps its donor's bias, scale
        and, shifted, history, and the mean weight."""
        n = len(self.w)
        m = int(self.cfg.reset_share * n)
        if m == 0:
            return
        donors = self._pick(self.rng.random(m))
        L = np.linalg.cholesky(R + np.eye(2) * 1e-9)
        q_now = z + self.rng.standard_normal((m, 2)) @ L.T + (self.p[donors] - p_then[donors])
        logpi = self.constraint.log_density(self.floor, q_now)
        ok = logpi > -np.inf
        if not ok.any():
            return
        donors, q_now, logpi = donors[ok], q_now[ok], logpi[ok]
        slots = self.rng.choice(n, size=len(donors), replace=False)
        # each slot takes its donor's lineage, shifted by where it was redrawn (the shift rides along
        # the lineage: its history is the donor's moved by the same offset)
        off = self._off if self._off is not None else np.zeros((n, 2))
        off[slots] = off[donors] + (q_now - self.p[donors])
        self._off = off
        self._anc = self._anc.copy()
        self._anc[slots] = self._anc[donors]
        self.b[slots], self.s[slots] = self.b[donors], self.s[donors]
        self.p[slots], self._logpi[slots] = q_now, logpi
        logw = self.logw.copy()
        logw[slots] = -math.log(n)  # the mean weight
        self.logw = log_normalise(logw)[0]
        self.n_reset += len(slots)

    def _nis(self, z: np.ndarray, h: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, float]:
        """The cloud's predicted measurements h (N, 2): their mean, and z's normalised innovation
        squared against their spread plus R."""
        m, C = self._mean_cov(h)
        y = z - m
        return m, float(y @ np.linalg.solve(C + R, y))

    def _gated(self, z: np.ndarray, h: np.ndarray, R: np.ndarray) -> bool:
        """Chi-square gate on the cloud's predicted measurements h (N, 2): is z inside their 95 % region?"""
        return self._nis(z, h, R)[1] <= self._gate

    def _log_likelihood(self, z: np.ndarray, h: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Heavy-tailed log((1 - eps) N(z; h, R) + eps N(z; h, k^2 R)) per particle (up to a constant)."""
        d = z - h
        Ri = np.linalg.inv(R)
        e = np.einsum("ni,ij,nj->n", d, Ri, d)
        k2 = self.cfg.outlier_scale**2
        eps = self.cfg.outlier_prob
        with np.errstate(divide="ignore"):
            return np.logaddexp(
                math.log(1.0 - eps) - 0.5 * e if eps < 1.0 else -np.inf, (math.log(eps / k2) if eps > 0.0 else -np.inf) - 0.5 * e / k2
            )

    def _correct_displacement(self, fix: DisplacementFix) -> tuple[bool, Estimate]:
        """Kourogi eq 17 (GPS differential mode): each particle's own displacement between t0 and t1,
        from its history, against the measured one - no linearisation needed."""
        H = self.cfg.history
        m = min(self._hist_k, H)
        oldest = self._hist_t[(self._hist_k - m) % H] if m else math.inf
        newest = self._hist_t[(self._hist_k - 1) % H] if m else -math.inf
        if not self.initialised or fix.t0 < oldest or fix.t1 > newest:
            self.n_rejected += 1  # the window is older than the particles remember, or its steps are not in yet
            return False, self.estimate("displacement-rejected")
        d = self._positions_at(fix.t1) - self._positions_at(fix.t0)
        z, R = np.asarray(fix.delta_enu, float), np.asarray(fix.cov, float)
        if not self._gated(z, d, R):
            self.n_rejected += 1
            self.stats.rejected["displacement"] += 1
            return False, self.estimate("displacement-rejected")
        self.stats.accepted["displacement"] += 1
        self._weigh(self._log_likelihood(z, d, R))
        return True, self.estimate("displacement")

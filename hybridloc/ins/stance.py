"""Zero-velocity (stance) detectors for foot-mounted IMUs, each a function of an IMU block.

Every detector returns ``(statistic, mask)``: the per-sample test statistic and the boolean stance
mask (True = foot on the ground). Thresholds are in stated units. Windows are centred on the sample
(a causal streaming version lags by half a window, ~12 ms at 200 Hz for W = 5).

* :func:`amvd` (Godha & Lachapelle 2008, eq 1): moving variance of |a| over n samples (and |a| near
  g) below ``threshold`` (m/s^2)^2.
* :func:`gyro_minimum` (Ojeda & Borenstein 2007, eq 6): in each segment of n samples, the sample of
  least |omega| if it is below Omega (rad/s): one instant per stance (what DEDRIFT-I needs).
* :func:`ared`: angular-rate energy, mean |omega|^2 over W samples below ``threshold`` (rad/s)^2.
* :func:`shoe` (Skog et al. 2010, the SHOE / GLRT detector, PyShoe's form):
  T = 1/W sum ( |a - g a_bar/|a_bar||^2 / sigma_a^2 + |omega|^2 / sigma_w^2 ) below ``gamma``
  (dimensionless). ``sigma_a`` (m/s^2) and ``sigma_w`` (rad/s) are the detector's noise scales.
* :func:`adaptive_shoe`: the project default. SHOE with a threshold relative to the statistic's
  local minimum over each gait cycle, so one setting serves walking, running and stairs;
  :func:`weak_stance` the shallower dips it leaves out and :func:`swing_level` how hard the foot
  swings, which the foot INS uses to decide which ZUPTs its chi-square gate must vet.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import maximum_filter1d, median_filter, minimum_filter1d, uniform_filter1d

from ..units import DEG, G0


def _moving_mean(x: np.ndarray, w: int) -> np.ndarray:
    return uniform_filter1d(x, size=w, axis=0, mode="nearest")


def shoe(acc: np.ndarray, gyr: np.ndarray, gamma: float = 2e7, W: int = 5, sigma_a: float = 0.00098, sigma_w: float = 8.7266463e-5, g: float = G0):
    """SHOE/GLRT statistic and mask (defaults: PyShoe's detector noise scales, its median-ish gamma)."""
    a_bar = _moving_mean(acc, W)
    u = a_bar / np.linalg.norm(a_bar, axis=1, keepdims=True)
    ta = np.sum((acc - g * u) ** 2, axis=1) / sigma_a**2
    tw = np.sum(gyr**2, axis=1) / sigma_w**2
    T = _moving_mean(ta + tw, W)
    return T, T < gamma


def ared(gyr: np.ndarray, threshold: float = 0.1, W: int = 5):
    T = _moving_mean(np.sum(gyr**2, axis=1), W)
    return T, T < threshold


def amvd(acc: np.ndarray, threshold: float = 0.05, n: int = 5, g: float = G0, magnitude_tol: float = 0.5):
    """Godha eq 1: variance of |a| over n samples < threshold and | |a| - g | < magnitude_tol (m/s^2)."""
    m = np.linalg.norm(acc, axis=1)
    mean = _moving_mean(m, n)
    var = _moving_mean(m * m, n) - mean * mean
    return var, (var < threshold) & (np.abs(mean - g) < magnitude_tol)


def gyro_minimum(gyr: np.ndarray, omega: float = 60 * DEG, n: int = 100):
    """Ojeda eq 6: per segment of n samples, the least-|omega| sample if below omega (rad/s)."""
    w = np.linalg.norm(gyr, axis=1)
    mask = np.zeros(len(w), bool)
    for s in range(0, len(w), n):
        seg = w[s : s + n]
        k = int(np.argmin(seg))
        if seg[k] < omega:
            mask[s + k] = True
    return w, mask


def adaptive_shoe(
    acc: np.ndarray,
    gyr: np.ndarray,
    rate_hz: float,
    W: int = 5,
    sigma_a: float = 0.00098,
    sigma_w: float = 8.7266463e-5,
    g: float = G0,
    window: float = 1.2,
    decades: float = 0.5,
    gamma_still: float = 1e6,
    gamma_max: float = 1e9,
    context: float = 4.0,
    context_decades: float | None = 1.0,
):
    """SHOE with a threshold that follows the gait: stance where log10 T is within ``decades`` of its
    minimum over the surrounding ``window`` seconds (and T < ``gamma_max``), or where T < ``gamma_still``.

    Why: the SHOE statistic at mid-stance spans four decades across gaits (PyShoe's per-trial optimal
    gamma runs from 5e5 walking slowly to 1e9 running), so no fixed gamma serves walking, running
    and stairs. Every gait cycle still has a stance at which T is near its local minimum, and the
    swing is decades above it. A window of 1.2 s holds at least one full stride at any pace (a slow
    walk's stride is ~1.2 s), so every stance is compared with its own cycle. ``gamma_still`` keeps a
    long standing still (where the window has no swing to contrast) as stance; ``gamma_max`` keeps
    the detector from calling the quietest moment of a swing-only stretch (e.g. a foot in the air) a
    stance, and so does the context test: stance must also lie within ``context_decades`` of the
    median stance level of the surrounding ``context`` seconds (a slow lift onto a stair has a local
    minimum decades above the real stances around it).

    The defaults were chosen on the 28 PyShoe VICON trials in ../shared/data (mean 2-D ARMSE 0.081 m
    without the context test, 0.074 m with it; re-gridded after the strapdown alignment fix, still
    the best: 0.070 m; with the foot INS's vetting of doubtful ZUPTs 0.0594, and 0.0529 smoothed, see
    foot.py); they are one setting for all trials, not per trial.
    """
    T, _ = shoe(acc, gyr, np.inf, W, sigma_a, sigma_w, g)
    return T, adaptive_mask(T, rate_hz, window, decades, gamma_still, gamma_max, context, context_decades)


def adaptive_mask(
    T: np.ndarray,
    rate_hz: float,
    window: float = 1.2,
    decades: float = 0.5,
    gamma_still: float = 1e6,
    gamma_max: float = 1e9,
    context: float = 4.0,
    context_decades: float | None = 1.0,
) -> np.ndarray:
    """The stance mask of :func:`adaptive_shoe` from a SHOE statistic ``T`` already computed."""
    logT = np.log10(np.maximum(T, 1e-30))
    n = max(3, int(round(window * rate_hz)) | 1)
    local_min = minimum_filter1d(logT, size=n, mode="nearest")
    mask = (logT <= local_min + decades) & (T < gamma_max)
    if context and context_decades is not None:
        # The gait's own stance level: the median of the per-cycle minima over ``context`` s. A slow
        # stretch with no stance inside one window (a foot lifted slowly onto a stair) has a local
        # minimum far above it, and is not stance.
        step = max(1, n // 4)
        sub = local_min[::step]
        k = max(1, int(round(context * rate_hz / step)) | 1)
        base = np.repeat(median_filter(sub, size=k, mode="nearest"), step)[: len(T)]
        mask &= logT <= base + context_decades
    return mask | (T < gamma_still)


#: Window of the weak-stance test (:func:`weak_stance`), s: half a stride, so each dip of the SHOE
#: statistic is compared with itself rather than with the deeper stance of the stride before.
WEAK_WINDOW_S = 0.6


def weak_stance(
    T: np.ndarray, rate_hz: float, strong: np.ndarray, window: float = WEAK_WINDOW_S, decades: float = 0.5, gamma_max: float = 1e9
) -> np.ndarray:
    """Stance-like dips the adaptive test leaves out: within ``decades`` of the local minimum over a
    shorter ``window``, with no context test, and not already in ``strong``.

    These are the stances the context test drops as too shallow for the gait around them (a running
    foot's brief, rolling contact; a stance in a turn) mixed with what it is meant to drop (a foot
    lifted slowly onto a stair). They cannot be told apart by the statistic, so the foot INS applies
    their ZUPTs through the chi-square gate: the filter's own velocity decides. On the PyShoe VICON
    trials this takes the running trials' stance-starved strides (2017-11-27-11-18-11 0.210 -> 0.158 m).
    """
    loose = adaptive_mask(T, rate_hz, window, decades, 0.0, gamma_max, 0.0, None)
    return loose & ~np.asarray(strong, bool)


def swing_level(T: np.ndarray, rate_hz: float, window: float = 1.5, context: float = 4.0) -> np.ndarray:
    """log10 of the SHOE statistic at the gait's swing peaks, per sample: the running maximum of
    log10 T over ``window`` s (a stride at any pace), smoothed by the median over ``context`` s.

    It says how hard the foot swings: on the PyShoe VICON trials about 9.3-10.3 for walking and
    running, 8.1 crawling and 9.1-9.2 for slow, short steps (see :data:`GENTLE_SWING_LOG10`).
    """
    logT = np.log10(np.maximum(T, 1e-30))
    n = max(3, int(round(window * rate_hz)) | 1)
    peak = maximum_filter1d(logT, size=n, mode="nearest")
    step = max(1, int(round(rate_hz / 20)))  # the median on a 20 Hz subsample: same answer, 10x faster
    k = max(1, int(round(context * rate_hz / step)) | 1)
    return np.repeat(median_filter(peak[::step], size=k, mode="nearest"), step)[: len(T)]


#: Swing level (:func:`swing_level`) below which a gait is "gentle": the foot never swings hard
#: (crawling, shuffling, slow short steps). There the stance/swing contrast of the SHOE statistic is
#: low and the detector calls stance while the foot still creeps, but the INS barely accelerates, so
#: its own velocity covariance is right and the chi-square gate can veto those ZUPTs. In a hard swing
#: (walking, running) the INS's velocity error after a stride exceeds what its covariance says, so
#: the gate would veto true ZUPTs and the filter would diverge: no vetting there.
GENTLE_SWING_LOG10 = 9.5


#: Shortest swing of a foot, s: two stance runs closer than this are one stance of one step (a stance
#: broken by a heel-to-toe roll, or a mid-swing dip of the statistic beside a true stance). A foot's
#: swing lasts about 40 % of its stride at any pace (0.35-0.5 s walking, 0.3-0.4 s running; Perry's
#: gait phases): the default sits under the shortest. The value used by ``--detector robust`` is chosen
#: by cross-validation in ``hybridloc eval pdr-foot`` (:data:`MIN_SWING_CANDIDATES_S`).
MIN_SWING_S = 0.25
MIN_SWING_CANDIDATES_S = (0.15, 0.2, 0.25, 0.3, 0.35)

#: Shortest stance of a step, s: a run of the stance mask shorter than this is not where a step ends.
#: Mid-swing, where the foot's pitch rate reverses, the statistic of the 3DM-GX5-25 can dip for a
#: few samples to its stance level while the foot still moves at metres per second (walk 45: 2-3
#: samples, 8-12 ms, |a| - g 1-4 m/s^2 there against a few tenths at stance). Cut at such a dip, a
#: stride splits in two (walk 45: 0.14 + 0.51 m where 1.27 m was walked). The shortest stances the
#: robust detector keeps last 25 ms (walks 31, 33, 38, 39), and 30 ms already splits strides of walk
#: 31, so the bound sits one sample under them; longer dips (walk 34's 5 samples) stay for the
#: cluster rule and the gate on demoted runs. Chosen by cross-validation in ``hybridloc eval
#: pdr-foot`` on the stride counts (:data:`MIN_STANCE_CANDIDATES_S`): 20 ms in every fold leaving
#: one walk out, counts exact on 11 of 13 walks against 7 with no bound.
MIN_STANCE_S = 0.02
MIN_STANCE_CANDIDATES_S = (0.0, 0.01, 0.015, 0.02, 0.025, 0.03, 0.04)


def stance_runs(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) sample of each run of True in ``mask``."""
    e = np.diff(np.concatenate([[0], np.asarray(mask, np.int8), [0]]))
    return np.flatnonzero(e == 1), np.flatnonzero(e == -1)


def one_stance_per_step(
    mask: np.ndarray, T: np.ndarray, rate_hz: float, min_swing: float = MIN_SWING_S, min_stance: float = MIN_STANCE_S
) -> tuple[np.ndarray, np.ndarray]:
    """Split a stance mask into one stance per step and the rest: ``(strong, demoted)``.

    Runs shorter than ``min_stance`` s are demoted outright (a mid-swing dip, :data:`MIN_STANCE_S`).
    Of the others, runs separated by less than ``min_swing`` s are one cluster (no foot swings that
    fast); of each cluster the run whose SHOE statistic ``T`` dips deepest is the step's stance
    (``strong``), the others are ``demoted`` (not where a stride ends). Why: on a sensor whose
    statistic at stance sits near its swing level (the 3DM-GX5-25 of the gait-driven set: stance at
    log10 T 7.2-7.9 against 3.5-6 on PyShoe's GX3), the adaptive test also calls the brief mid-swing
    dips and the fragments of a rolling stance, a third more stances than steps walked.
    """
    s, e = stance_runs(mask)
    strong = np.zeros(len(mask), bool)
    demoted = np.zeros(len(mask), bool)
    brief = (e - s) < int(round(min_stance * rate_hz))  # whole samples, as the swing's gap below
    for a, b in zip(s[brief], e[brief]):
        demoted[a:b] = True
    s, e = s[~brief], e[~brief]
    if not len(s):
        return strong, demoted
    gap = max(1, int(round(min_swing * rate_hz)))
    depth = np.array([float(np.min(T[a:b])) for a, b in zip(s, e)])
    cluster = np.concatenate([[0], np.cumsum(s[1:] - e[:-1] >= gap)])
    for c in range(int(cluster[-1]) + 1):
        idx = np.flatnonzero(cluster == c)
        keep = idx[int(np.argmin(depth[idx]))]
        for j in idx:
            (strong if j == keep else demoted)[s[j] : e[j]] = True
    return strong, demoted


DETECTORS = ("adaptive", "robust", "shoe", "ared", "amvd", "mbgtd")

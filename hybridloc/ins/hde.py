"""Heuristic drift elimination for a foot INS: heading measured as a building's dominant direction.

A ZUPT-aided INS cannot see its own heading: during stance the specific force is gravity alone, so
the yaw error leaves no trace in the velocity (Godha & Lachapelle 2008, eq 2), and a gyro's vertical
bias integrates into a heading drift (on the gait-driven walks' 3DM-GX5-25, 0.2 deg/s: 20-25 deg over
a 100 s walk). Buildings have few directions: corridors run along two orthogonal axes, and people walk
along them. Borenstein, Ojeda & Kwanmuang (2009, "Heuristic reduction of gyro drift for personnel
tracking systems", HDR/HDE) and Jimenez et al. (2012, iHDE) use this: when the walker goes straight
and the stride's heading lies near one of the dominant directions, the heading is taken to be that
direction. Here it is a measurement of the filter (:class:`.measurements.StrideHeading`, through the
one gated ``correct()``), once per stride:

* a stride ends at the last sample of a stance, ``min_stride`` m or more from where the last one
  ended (a fragment of a rolling stance moves the foot a few cm: no stride);
* the walker goes straight when the last ``strides`` stride headings all lie within ``straight``
  of their circular mean;
* the dominant directions are ``grid + k pi/2``; ``grid`` is given (a floor plan's axes in the nav
  frame) or, when None, taken from the first straight stretch of the walk (the circular mean of its
  stride headings, modulo pi/2: Borenstein's "the first straight segment defines the grid");
* a straight stride within ``window`` of its nearest dominant direction is measured as that
  direction, with standard deviation ``sigma``. Strides farther off (diagonal walking, turns, a
  loop) are left alone, so a wrong snap needs a drift of ``window`` first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..units import DEG

QUARTER = 0.5 * math.pi


@dataclass(frozen=True)
class HdeConfig:
    """Settings of :class:`DriftEliminator` (angles in radians, lengths in metres). The defaults are
    the candidate of :data:`HDE_CANDIDATES` that ``hybridloc eval pdr-foot`` chooses on the gait-driven
    walks (held out by walk and by session there)."""

    grid: float | None = None  # a dominant direction in the nav frame (the others at + k pi/2); None: learned from the walk
    window: float = 15 * DEG  # |stride heading - nearest dominant direction| below this to be measured
    straight: float = 20 * DEG  # the last ``strides`` stride headings within this of their circular mean
    strides: int = 3
    sigma: float = 3 * DEG  # standard deviation of the measured heading
    min_stride: float = 0.3  # m; a shorter move between stance ends is not a stride
    # Prior standard deviation of the gyro bias's vertical component (rad/s; None: the filter's
    # ``gyro_bias_sigma0``, as for the other components). Stance observes the other two (ZARU, and
    # tilt through the ZUPT); only the heading measurements see this one, so its prior may be wider.
    bias_sigma0_up: float | None = 0.2 * DEG


def circular_mean(angles, period: float = 2 * math.pi) -> float:
    """Mean of angles modulo ``period`` (rad), in (-period/2, period/2]."""
    k = 2 * math.pi / period
    a = np.asarray(angles, float) * k
    return float(math.atan2(np.sin(a).mean(), np.cos(a).mean()) / k)


def wrap(a: float, period: float = 2 * math.pi) -> float:
    """``a`` wrapped to [-period/2, period/2)."""
    return (a + 0.5 * period) % period - 0.5 * period


class DriftEliminator:
    """Decides, at each stance end, whether the stride just walked is measured as a dominant direction.

    ``stride_end(p_xy)`` takes the foot's horizontal position (nav frame, m) at the last sample of a
    stance and returns ``(z, psi)``: the dominant direction to measure and the stride's own heading
    (rad), or None. ``grid`` holds the dominant direction in use (None until learned); ``n_straight``
    and ``n_measured`` count straight strides and those measured."""

    def __init__(self, cfg: HdeConfig):
        self.cfg = cfg
        self.grid = cfg.grid
        self._last: np.ndarray | None = None
        self._headings: list[float] = []
        self.n_strides = self.n_straight = self.n_measured = 0

    def stride_end(self, p_xy: np.ndarray) -> tuple[float, float] | None:
        c = self.cfg
        p = np.asarray(p_xy, float)[:2]
        if self._last is None:
            self._last = p.copy()
            return None
        d = p - self._last
        if math.hypot(d[0], d[1]) < c.min_stride:
            return None
        self._last = p.copy()
        self.n_strides += 1
        psi = math.atan2(d[1], d[0])
        self._headings = (self._headings + [psi])[-c.strides :]
        if len(self._headings) < c.strides:
            return None
        m = circular_mean(self._headings)
        if max(abs(wrap(h - m)) for h in self._headings) > c.straight:
            return None
        self.n_straight += 1
        if self.grid is None:
            self.grid = circular_mean(self._headings, QUARTER)
            return None
        z = self.grid + round((psi - self.grid) / QUARTER) * QUARTER
        if abs(wrap(psi - z)) > c.window:
            return None
        self.n_measured += 1
        return wrap(z), psi


#: Candidates chosen by cross-validation in ``hybridloc eval pdr-foot`` (leave one gait-driven walk
#: out, and one session out): how straight a stretch must be (``straight``) and whether the vertical
#: gyro bias gets a wider prior the heading measurements can teach (``bias_sigma0_up``, rad/s). The
#: window (15 deg) and sigma (3 deg) are iHDE's order of magnitude, not fitted.
HDE_CANDIDATES = tuple(
    HdeConfig(window=15 * DEG, straight=st * DEG, sigma=3 * DEG, bias_sigma0_up=bu) for st in (10.0, 20.0) for bu in (None, 0.2 * DEG)
)


def describe(c: HdeConfig) -> str:
    bu = "filter's" if c.bias_sigma0_up is None else f"{c.bias_sigma0_up / DEG:g} deg/s"
    return f"straight {c.straight / DEG:g} deg, vertical gyro bias prior {bu}"


#: What ``hybridloc pdr foot --hde`` uses (the grid learned unless given).
HDE_DEFAULT = HdeConfig()

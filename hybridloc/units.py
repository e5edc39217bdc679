"""Named unit conversions and angle helpers (see the conventions in :mod:`hybridloc`)."""

from __future__ import annotations

import math

import numpy as np

#: Radians per degree: ``x_rad = x_deg * DEG``.
DEG = math.pi / 180.0
#: Standard gravity, m/s^2 (CGPM 1901); used to convert accelerometers reporting in g.
G0 = 9.80665
#: Tesla per microtesla (Android reports the magnetic field in uT).
UT_TO_T = 1e-6
#: Tesla per gauss (MicroStrain magnetometers report gauss).
GAUSS_TO_T = 1e-4
#: Hertz per megahertz (Android reports WiFi frequency in MHz).
MHZ_TO_HZ = 1e6
#: Seconds per millisecond (Android / Indoor Location Competition timestamps are Unix ms).
MS_TO_S = 1e-3


def wrap_angle(a):
    """Wrap angle(s) in radians to the half-open interval (-pi, pi]."""
    if type(a) is float or type(a) is int:  # one angle: Python's float % is numpy's np.mod (fmod, then the divisor's sign), bit for bit
        s = (float(a) + math.pi) % (2.0 * math.pi) - math.pi
        return math.pi if s == -math.pi else s
    w = np.mod(np.asarray(a, dtype=float) + math.pi, 2.0 * math.pi) - math.pi
    w = np.where(w == -math.pi, math.pi, w)
    return float(w) if np.ndim(w) == 0 else w


def heading_to_bearing_deg(heading):
    """Heading (rad, counter-clockwise from East) -> compass bearing (deg, clockwise from North) in [0, 360)."""
    b = np.mod(90.0 - np.asarray(heading, dtype=float) / DEG, 360.0)
    return float(b) if np.ndim(b) == 0 else b


def bearing_deg_to_heading(bearing_deg):
    """Compass bearing (deg, clockwise from North) -> heading (rad, counter-clockwise from East)."""
    return wrap_angle((90.0 - np.asarray(bearing_deg, dtype=float)) * DEG)

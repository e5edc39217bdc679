"""Passive survey labelling: positions for every scan of a walk whose operator marked a few known points.

Between two consecutive marks (waypoints) A and B at times t_A, t_B the phone PDR gives a relative
track r(t). The track is stretched and rotated so that it starts at A and ends at B (the similarity
transform mapping r(t_A) -> A and r(t_B) -> B), and every scan in between is labelled with the
transformed position at its time (Harle's survey sec. VII: Woodman & Harle's maps from PDR traces; the
Indoor Location Competition traces are used this way as surveys).

Label uncertainty: the error of a bridged PDR segment is zero at both marks and largest mid-way.
With a relative error ``rel_sigma`` of PDR displacement, the standard deviation at arc fraction u is
``sigma0 + rel_sigma * D * 2 * min(u, 1 - u)`` plus ``sigma0`` for the mark itself (a person marks a
point to about half a metre). Scans outside the first/last mark are not labelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..pdr.deadreckoning import DeadReckoning
from ..types import RfScan, StepEvent, Waypoints


@dataclass(frozen=True)
class LabelledScan:
    """A scan with a surveyed position. ``pos_enu`` (2,) m in the floor-plan frame, ``sigma`` m."""

    scan: RfScan
    pos_enu: np.ndarray
    sigma: float
    floor: str | None
    source: str = ""


def label_scans(
    scans: list[RfScan], steps: list[StepEvent], waypoints: Waypoints, t_start: float, source: str = "", sigma0: float = 0.5, rel_sigma: float = 0.1
) -> list[LabelledScan]:
    """Label the scans lying between the first and last waypoint (module docstring)."""
    if len(waypoints) < 2:
        return []
    track_at = DeadReckoning.from_steps(steps, t0=min(t_start, steps[0].t - 1.0) if steps else t_start, covariance=False).position_at

    out: list[LabelledScan] = []
    wt, wp = waypoints.t, waypoints.pos_enu
    for scan in scans:
        k = int(np.searchsorted(wt, scan.t, side="right")) - 1
        if k == len(wt) - 1 and scan.t == wt[-1]:  # exactly at the last mark: end of the last segment
            k -= 1
        if k < 0 or k >= len(wt) - 1:
            continue
        tA, tB = wt[k], wt[k + 1]
        A, B = wp[k], wp[k + 1]
        floor = waypoints.floor_of(k)
        if tB <= tA or waypoints.floor_of(k + 1) != floor:  # between marks on two floors: on the stairs
            continue
        rA, rB = track_at(tA), track_at(tB)
        dr, dw = rB - rA, B - A
        nr, nw = float(np.hypot(*dr)), float(np.hypot(*dw))
        u = (scan.t - tA) / (tB - tA)
        if nr < 0.3 or nw < 0.3:
            # standing still or no PDR motion: interpolate linearly in time between the marks
            pos = A + u * dw
        else:
            s = nw / nr
            ang = math.atan2(dw[1], dw[0]) - math.atan2(dr[1], dr[0])
            c, sn = math.cos(ang), math.sin(ang)
            v = track_at(scan.t) - rA
            pos = A + s * np.array([c * v[0] - sn * v[1], sn * v[0] + c * v[1]])
        sigma = sigma0 + rel_sigma * nw * 2.0 * min(u, 1.0 - u)
        out.append(LabelledScan(scan, pos, float(sigma), floor, source))
    return out


def label_trace(trace, source: str = "") -> list[LabelledScan]:
    """A waypointed recording (an Indoor Location Competition trace) as a passive survey: its phone
    PDR bridged between consecutive waypoints labels its WiFi scans (:func:`label_scans`)."""
    from ..pdr.phone import PhonePdr
    from ..pdr.steplength import make_model

    if trace.imu is None or len(trace.waypoints) < 2:
        return []
    steps = PhonePdr(trace.imu.rate_hz, make_model("height"), heading0=0.0).process(trace.imu)
    return label_scans(list(trace.wifi_scans), steps, trace.waypoints, float(trace.imu.t[0]), source=source)

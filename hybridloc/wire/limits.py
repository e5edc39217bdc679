"""Physical limits on what a batch may carry: items beyond them are refused one by one, counted by reason.

A batch that decodes is stored whatever its items say (so the device's go-back-N stream moves on and
nothing good in it is lost), but an item no walker or radio can produce is left out and counted under
a stable reason (docs/protocol.md, "Physical limits"). The limits are set from physics with a margin
over what hybridloc's own clients send on every shared recording (``../shared/data``: 305 site1 phone
walks through the phone PDR, 28 PyShoe trials and the OpenShoe square through the foot INS), so a real
walker is never refused:

=====================  =================================  ============================  ===================
reason                 limit                              why                           largest seen
=====================  =================================  ============================  ===================
``step-too-long``      length <= 5 m                      a sprinter's stride (two      1.12 m phone step,
                                                          steps) is 4.5-5 m             1.99 m foot stride
``step-too-fast``      >= 0.05 s after the previous       20 steps/s: 4x a sprint        0.28 s phone,
                       step, length / interval <= 12.5    cadence (~5 Hz); 12.5 m/s:    0.15 s foot; 2.3 and
                       m/s                                the fastest human sprint      2.7 m/s
``turn-too-fast``      abs(heading_change) <= 2 pi        a whole turn within one step  2.98 rad phone,
                                                                                        3.14 rad foot
``climb-too-high``     abs(height_change) <= 2 m,         a storey per step; a lift     0.53 m (stairs)
                       abs(floor_change) <= 200           ride is floor_change, and no
                                                          building has 200 floors
``scan-too-large``     <= 1,500 readings per scan         channels x BSSIDs per radio   558 (mall WiFi)
``reading-too-old``    0 <= age <= 300 s per reading      Android's cached results are  139 s
                       (the reading is dropped)           minutes old at most
``wrong-units``        abs(t) < 1e11 s; abs(heading),     milliseconds since 1970 are   -
                       sigma_heading(_change) <= 2 pi;    1.7e12; degrees exceed 2 pi;
                       frequency in [1e5, 1e11] Hz;       a frequency in MHz is < 1e5;
                       mark abs(x), abs(y) <= 1e5 m       no site spans 100 km
``time-out-of-order``  times non-decreasing within the    each list is in time order    -
                       batch's steps, scans and marks     on every client
``batch-span``         all items within 300 s             a batch is a few seconds of   -
                                                          a walk
=====================  =================================  ============================  ===================

Order of the checks: per item (units, then the limits above), then the batch's time span (the largest
set of items within :data:`MAX_BATCH_SPAN_S`, the others refused), then the order of each list (an item
earlier than the one kept before it is refused), then the step rate against the previous kept step.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from ..types import RfScan, StepEvent, SurveyMark

MAX_STEP_LENGTH_M = 5.0
MIN_STEP_INTERVAL_S = 0.05
MAX_STEP_SPEED_M_S = 12.5
MAX_HEADING_CHANGE_RAD = 2.0 * math.pi
MAX_HEIGHT_CHANGE_M = 2.0
MAX_FLOOR_CHANGE = 200
MAX_SCAN_READINGS = 1500
MAX_READING_AGE_S = 300.0
MAX_BATCH_SPAN_S = 300.0
#: |t| at or beyond this is not seconds (milliseconds since 1970 are ~1.7e12)
MAX_ABS_TIME_S = 1e11
MAX_ANGLE_RAD = 2.0 * math.pi
MIN_FREQUENCY_HZ, MAX_FREQUENCY_HZ = 1e5, 1e11
MAX_ABS_COORD_M = 1e5

#: every reason :func:`screen` may give, in the order of the table above
REASONS = (
    "step-too-long",
    "step-too-fast",
    "turn-too-fast",
    "climb-too-high",
    "scan-too-large",
    "reading-too-old",
    "wrong-units",
    "time-out-of-order",
    "batch-span",
)


def _step_reason(s: StepEvent, sent: tuple[float, float | None]) -> str | None:
    """``sent``: the heading and heading change as sent (the record wraps both into (-pi, pi], which
    would hide degrees and a spin)."""
    heading, change = sent
    angles = [heading, s.sigma_heading] + [a for a in (s.sigma_heading_change,) if a is not None]
    if abs(s.t) >= MAX_ABS_TIME_S or any(abs(a) > MAX_ANGLE_RAD for a in angles):
        return "wrong-units"
    if s.length > MAX_STEP_LENGTH_M:
        return "step-too-long"
    if change is not None and abs(change) > MAX_HEADING_CHANGE_RAD:
        return "turn-too-fast"
    if abs(s.height_change) > MAX_HEIGHT_CHANGE_M or abs(s.floor_change) > MAX_FLOOR_CHANGE:
        return "climb-too-high"
    return None


def _scan_reason(s: RfScan) -> str | None:
    if abs(s.t) >= MAX_ABS_TIME_S or any(not (MIN_FREQUENCY_HZ <= f <= MAX_FREQUENCY_HZ) for f in s.frequency_hz.values()):
        return "wrong-units"
    if len(s.rssi_dbm) > MAX_SCAN_READINGS:
        return "scan-too-large"
    return None


def _mark_reason(m: SurveyMark) -> str | None:
    if abs(m.t) >= MAX_ABS_TIME_S or abs(m.x) > MAX_ABS_COORD_M or abs(m.y) > MAX_ABS_COORD_M:
        return "wrong-units"
    return None


def _fresh_readings(s: RfScan, refused: Counter) -> RfScan | None:
    """The scan without its readings older than MAX_READING_AGE_S (or of negative age), each counted;
    None when none is left."""
    if not s.age_s:
        return s
    stale = {k for k, a in s.age_s.items() if not (0.0 <= a <= MAX_READING_AGE_S)}
    if not stale:
        return s
    refused["reading-too-old"] += len(stale)
    rssi = {k: v for k, v in s.rssi_dbm.items() if k not in stale}
    if not rssi:
        return None
    keep = lambda d: {k: v for k, v in d.items() if k not in stale}  # noqa: E731
    return RfScan(s.t, s.technology, rssi, keep(s.frequency_hz), keep(s.age_s), s.device_model)


def screen_scan(s: RfScan) -> tuple[RfScan | None, Counter]:
    """One scan within the limits (stale readings dropped; None: refused or none left) and what was
    refused, by reason: what a locate query's scan goes through."""
    refused: Counter = Counter()
    r = _scan_reason(s)
    if r is not None:
        refused[r] += 1
        return None, refused
    return _fresh_readings(s, refused), refused


def _largest_window(times: np.ndarray, span: float) -> np.ndarray:
    """Mask of the largest set of ``times`` inside one window of length ``span`` (the earliest such window)."""
    if times.size == 0:
        return np.zeros(0, dtype=bool)
    srt = np.sort(times)
    # for each start i, the items in [srt[i], srt[i] + span]
    ends = np.searchsorted(srt, srt + span, side="right")
    i = int(np.argmax(ends - np.arange(srt.size)))
    return (times >= srt[i]) & (times <= srt[i] + span)


def _in_order(items: list, refused: Counter) -> list:
    """Items whose time does not go back from the previous kept one (the others counted)."""
    out: list = []
    for x in items:
        if out and x.t < out[-1].t:
            refused["time-out-of-order"] += 1
            continue
        out.append(x)
    return out


def screen(
    steps: Sequence[StepEvent],
    scans: Sequence[RfScan],
    marks: Sequence[SurveyMark],
    sent_angles: Sequence[tuple[float, float | None]] | None = None,
) -> tuple[tuple[StepEvent, ...], tuple[RfScan, ...], tuple[SurveyMark, ...], Counter]:
    """The items of a batch within the physical limits, and the refused ones counted by reason.
    ``sent_angles``: each step's (heading, heading_change) as sent, before the record wrapped them
    (default: the records' own)."""
    refused: Counter = Counter()

    def keep(items, why, extra):
        out = []
        for x, e in zip(items, extra):
            r = why(x, e) if e is not None else why(x)
            if r is None:
                out.append(x)
            else:
                refused[r] += 1
        return out

    angles = list(sent_angles) if sent_angles is not None else [(s.heading, s.heading_change) for s in steps]
    if len(angles) != len(steps):
        raise ValueError(f"{len(angles)} sent angles for {len(steps)} steps")
    st = keep(steps, _step_reason, angles)
    sc, mk = keep(scans, _scan_reason, [None] * len(scans)), keep(marks, _mark_reason, [None] * len(marks))
    sc = [x for x in (_fresh_readings(s, refused) for s in sc) if x is not None]
    lists = [st, sc, mk]
    times = np.array([x.t for lst in lists for x in lst], dtype=float)
    inside = _largest_window(times, MAX_BATCH_SPAN_S)
    if not inside.all():
        refused["batch-span"] += int((~inside).sum())
        cut, i0 = [], 0
        for lst in lists:
            cut.append([x for x, ok in zip(lst, inside[i0 : i0 + len(lst)]) if ok])
            i0 += len(lst)
        lists = cut
    st, sc, mk = (_in_order(lst, refused) for lst in lists)
    # the step rate against the previous kept step (the first step of a batch has none here)
    rated: list[StepEvent] = []
    for s in st:
        if rated:
            dt = s.t - rated[-1].t
            if dt < MIN_STEP_INTERVAL_S or s.length > MAX_STEP_SPEED_M_S * dt:
                refused["step-too-fast"] += 1
                continue
        rated.append(s)
    return tuple(rated), tuple(sc), tuple(mk), refused

"""Core data types shared by the library, the server and the clients.

All types are frozen dataclasses; their numpy arrays are copied on construction and made read-only,
so a value handed to another component can never change under it. Units and frames follow the
conventions in :mod:`hybridloc` (SI, radians, float seconds on one clock, ENU site frame).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon

from .units import wrap_angle

if TYPE_CHECKING:
    from .geo import GeodeticOrigin

#: Plausible received signal strength range, dBm. Real receivers report about -100 to -20 dBm;
#: anything outside [-130, 0] is a unit or encoding error (e.g. UJIIndoorLoc's "100 = not seen").
RSSI_MIN_DBM = -130.0
RSSI_MAX_DBM = 0.0


def rssi_in_range(rssi_dbm):
    """True where ``rssi_dbm`` is a plausible reading, in [RSSI_MIN_DBM, RSSI_MAX_DBM] dBm.

    The one range check of the code base: the readers (:mod:`hybridloc.io.msft`, :mod:`hybridloc.io.uji`),
    :class:`RfScan` and the wire's decoder all call it. A float gives a bool, an array an array of them;
    NaN compares false both ways, so it is out of range (and so is an infinity).
    """
    return (rssi_dbm >= RSSI_MIN_DBM) & (rssi_dbm <= RSSI_MAX_DBM)


def _frozen_array(a, shape_tail: tuple[int, ...] | None = None, name: str = "array", ndim: int | None = None):
    arr = np.array(a, dtype=float, copy=True)
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name}: expected {ndim}-D array, got shape {arr.shape}")
    if shape_tail is not None and arr.shape[arr.ndim - len(shape_tail) :] != shape_tail:
        raise ValueError(f"{name}: expected shape (..., {', '.join(map(str, shape_tail))}), got {arr.shape}")
    arr.setflags(write=False)
    return arr


def _check_time(t: np.ndarray, name: str = "t") -> None:
    if t.ndim != 1:
        raise ValueError(f"{name}: expected 1-D time array, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name}: non-finite timestamps")
    if t.size > 1 and np.any(np.diff(t) <= 0):
        k = int(np.argmax(np.diff(t) <= 0))
        raise ValueError(f"{name}: timestamps must be strictly increasing (t[{k}]={t[k]!r} >= t[{k + 1}]={t[k + 1]!r})")


# ----------------------------------------------------------------------------------------------
# Inertial data
#: A reading at this share of the sensor's full scale or beyond is saturated (clipped).
SATURATION_SHARE = 0.995
#: With the full scale unknown, this many consecutive identical readings of an axis beyond what the
#: carrier can plausibly produce are a clipped plateau (a live signal does not repeat exactly there).
SATURATION_REPEATS = 3
#: ... or a ceiling: a sensor that filters or calibrates after its converter clips at a level its
#: readings then wander about by a few tenths of a percent, never repeating exactly (the 3DM-GX5-25
#: of the gait-driven set: its rate plateaus at 497-511 deg/s, e.g. 505.8, 507.3, 507.5, 507.3). The
#: readings within CEILING_SHARE of an axis's extreme (one sign) are clipped when that extreme is
#: beyond the plausible range, within CEILING_NEAR_MAX of the block's largest reading on any axis (one
#: sensor, one full scale), and reached in at least CEILING_RUNS separate runs: a live signal's peaks
#: spread over tens of deg/s from swing to swing. Measured on the 13 gait-driven walks (0-226 samples
#: flagged; walk 35's 226 are 3.8 % of it, its readings at 495 deg/s or more 7.6 %) and the 28 PyShoe
#: trials (0-99): every level flagged lies at 497-556 deg/s; without the CEILING_NEAR_MAX condition,
#: 356-469 deg/s coincidences of 3 peaks were flagged too.
CEILING_SHARE = 0.99
CEILING_NEAR_MAX = 0.95
CEILING_RUNS = 3


def _ceiling(x: np.ndarray, plausible: float) -> np.ndarray:
    """Per sample, a reading at a clipping ceiling on any axis (see :data:`CEILING_SHARE`), (N,) bool."""
    out = np.zeros(len(x), bool)
    with np.errstate(invalid="ignore"):
        a = np.abs(x)
        top = np.nanmax(a) if np.isfinite(a).any() else np.nan
        if not top >= plausible:
            return out
        for k in range(x.shape[1]):
            for sign in (1.0, -1.0):
                y = sign * x[:, k]
                if not np.isfinite(y).any():
                    continue
                level = np.nanmax(y)
                if not (level >= plausible and level >= CEILING_NEAR_MAX * top):
                    continue
                near = y >= CEILING_SHARE * level
                starts = np.count_nonzero(np.diff(near.astype(np.int8), prepend=np.int8(0)) == 1)
                if starts >= CEILING_RUNS:
                    out |= near
    return out


# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ImuBlock:
    """A block of N inertial samples on one clock.

    Attributes
    ----------
    t : ndarray, shape (N,)
        Sample times, s, strictly increasing.
    accel_body : ndarray, shape (N, 3)
        Specific force in the body frame, m/s^2 (at rest it reads +g upward, e.g. (0, 0, +9.81)
        for a z-up sensor lying flat).
    gyro_body : ndarray, shape (N, 3)
        Angular rate in the body frame, rad/s.
    mag_body : ndarray, shape (N, 3) or None
        Magnetic field in the body frame, tesla; None when the unit has no magnetometer.
    source : str
        Where the block came from (file name, device id), for messages.
    accel_range, gyro_range : float or None
        The sensors' full scale, m/s^2 and rad/s (Android's ``maximumRange``), when known: a reading at
        the full scale is saturated (clipped), so the motion it stands for was larger.
    """

    t: np.ndarray
    accel_body: np.ndarray
    gyro_body: np.ndarray
    mag_body: np.ndarray | None = None
    source: str = ""
    accel_range: float | None = None
    gyro_range: float | None = None

    def __post_init__(self) -> None:
        t = _frozen_array(self.t, name="t", ndim=1)
        _check_time(t)
        acc = _frozen_array(self.accel_body, (3,), "accel_body", ndim=2)
        gyr = _frozen_array(self.gyro_body, (3,), "gyro_body", ndim=2)
        mag = None if self.mag_body is None else _frozen_array(self.mag_body, (3,), "mag_body", ndim=2)
        for name, arr in (("accel_body", acc), ("gyro_body", gyr), ("mag_body", mag)):
            if arr is not None and arr.shape[0] != t.shape[0]:
                raise ValueError(f"{name}: {arr.shape[0]} rows but {t.shape[0]} timestamps")
        for name, r in (("accel_range", self.accel_range), ("gyro_range", self.gyro_range)):
            if r is not None and not (math.isfinite(r) and r > 0):
                raise ValueError(f"{name} must be a positive full scale, got {r}")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "accel_body", acc)
        object.__setattr__(self, "gyro_body", gyr)
        object.__setattr__(self, "mag_body", mag)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def saturated(
        self, plausible_accel: float, plausible_gyro: float, repeats: int = SATURATION_REPEATS, share: float = SATURATION_SHARE
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per sample, (accelerometer saturated, gyroscope saturated), boolean (N,) each.

        With the full scale known, a reading at ``share`` of it or beyond on any axis. Unknown, the same
        reading on ``repeats`` consecutive samples of an axis beyond what the carrier can plausibly
        produce (``plausible_accel`` m/s^2, ``plausible_gyro`` rad/s): a clipped plateau; a live signal
        does not repeat exactly up there. Also unknown: the readings at a ceiling they wander about
        (:data:`CEILING_SHARE`)."""
        out = []
        for x, full, plausible in ((self.accel_body, self.accel_range, plausible_accel), (self.gyro_body, self.gyro_range, plausible_gyro)):
            with np.errstate(invalid="ignore"):
                if full is not None:
                    out.append(np.any(np.abs(x) >= share * full, axis=1))
                    continue
                # same[k]: sample k equals sample k - 1 up there (sample 0 has no predecessor)
                same = np.zeros(x.shape, bool)
                same[1:] = (x[1:] == x[:-1]) & (np.abs(x[1:]) >= plausible)
            flat = same.copy()  # flat[k]: samples k - repeats + 1 .. k all equal (the last of a plateau)
            for d in range(1, repeats - 1):
                flat[d:] &= same[:-d]
                flat[:d] = False
            # mark the whole plateau: every sample within repeats - 1 before a flagged one on that axis
            mask = flat.copy()
            for d in range(1, repeats):
                mask[:-d] |= flat[d:]
            out.append(np.any(mask, axis=1) | _ceiling(x, plausible))
        return out[0], out[1]

    @property
    def duration(self) -> float:
        """Time from first to last sample, s."""
        return float(self.t[-1] - self.t[0]) if len(self) > 1 else 0.0

    @property
    def rate_hz(self) -> float:
        """Nominal sample rate, Hz: the inverse of the median sample interval (robust to gaps)."""
        if len(self) < 2:
            return float("nan")
        return float(1.0 / np.median(np.diff(self.t)))

    def slice(self, t0: float, t1: float) -> ImuBlock:
        """Samples with t0 <= t < t1."""
        i0, i1 = np.searchsorted(self.t, [t0, t1], side="left")
        return ImuBlock(
            self.t[i0:i1],
            self.accel_body[i0:i1],
            self.gyro_body[i0:i1],
            None if self.mag_body is None else self.mag_body[i0:i1],
            self.source,
        )


# ----------------------------------------------------------------------------------------------
# Steps
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=True)
class StepEvent:
    """One step (phone PDR) or stride (foot-mounted INS), the unit of dead reckoning.

    The step moves the walker from the previous step's position by
    ``(length * cos(heading), length * sin(heading))`` in the site frame.

    Attributes
    ----------
    t : float
        Time of the step (heel strike / end of stride), s.
    length : float
        Horizontal step length, m.
    heading : float
        Direction of travel, rad, counter-clockwise from East, in (-pi, pi].
    sigma_length : float
        Standard deviation of ``length``, m.
    sigma_heading : float
        Standard deviation of ``heading``, rad.
    heading_change : float or None
        Change of heading since the previous step, rad (what a gyro measures well even when the
        absolute heading is poor); None when unknown.
    sigma_heading_change : float or None
        Its standard deviation, rad.
    height_change : float
        Vertical displacement over the step, m (foot INS; 0 for phones without a barometer).
    sigma_height_change : float
        Its standard deviation, m.
    floor_change : int
        Floors climbed (+) or descended (-) during the step; 0 almost always.
    degraded : str
        Empty when all sensors were healthy; otherwise a short reason, e.g. ``"no-mag"`` or
        ``"mag-disturbed"`` (heading from gyro only), ``"gap"``.
    """

    t: float
    length: float
    heading: float
    sigma_length: float
    sigma_heading: float
    heading_change: float | None = None
    sigma_heading_change: float | None = None
    height_change: float = 0.0
    sigma_height_change: float = 0.0
    floor_change: int = 0
    degraded: str = ""

    def __post_init__(self) -> None:
        for name in ("t", "length", "heading", "sigma_length", "sigma_heading", "height_change", "sigma_height_change"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f"StepEvent.{name} must be finite, got {v!r}")
        if self.length < 0 or self.sigma_length < 0 or self.sigma_heading < 0 or self.sigma_height_change < 0:
            raise ValueError("StepEvent: length and standard deviations must be >= 0")
        object.__setattr__(self, "heading", wrap_angle(self.heading))
        if self.heading_change is not None:
            if not math.isfinite(self.heading_change):
                raise ValueError("StepEvent.heading_change must be finite")
            object.__setattr__(self, "heading_change", wrap_angle(self.heading_change))

    @classmethod
    def _checked_already(cls, fields: dict) -> StepEvent:
        """A step from ``fields`` (every field by name) that already pass :meth:`__post_init__`'s checks,
        angles already wrapped: the wire decoder's fast path for batches of thousands of steps, which
        makes the same checks once (and is tested to give the same steps)."""
        obj = object.__new__(cls)
        obj.__dict__.update(fields)
        return obj

    @property
    def displacement_enu(self) -> np.ndarray:
        """Horizontal displacement of the step, shape (2,), m."""
        return np.array([self.length * math.cos(self.heading), self.length * math.sin(self.heading)])

    def displacement_covariance(self) -> np.ndarray:
        """Covariance of the horizontal displacement, shape (2, 2), m^2 (Kourogi et al. 2006, eqs 11-14).

        The step moves the walker by ``l d + e d_perp`` with d = (cos psi, sin psi) and
        d_perp = (-sin psi, cos psi): the stride error along d has variance sigma_l^2 and the
        direction error acts as a tangential error e of variance (l tan sigma_psi)^2, so
        Sigma_d = [d d_perp] diag(sigma_l^2, (l tan sigma_psi)^2) [d d_perp]^T.
        """
        c, s = math.cos(self.heading), math.sin(self.heading)
        A = np.array([[c, -s], [s, c]])
        return A @ np.diag([self.sigma_length**2, (self.length * math.tan(min(self.sigma_heading, 1.5))) ** 2]) @ A.T

    def propagate_position_covariance(self, C: np.ndarray) -> np.ndarray:
        """Position covariance after the step from C before it (Kourogi eq 13: C_{i+1} = A_i R_i A_i^T)."""
        return np.asarray(C, dtype=float) + self.displacement_covariance()


# ----------------------------------------------------------------------------------------------
# Radio
# ----------------------------------------------------------------------------------------------
class Technology(str, enum.Enum):
    """Radio technology of a scan."""

    WIFI = "wifi"
    BLE = "ble"
    RFID = "rfid"


#: A read-only empty mapping (a scan's missing frequencies or ages)
_EMPTY: Mapping[str, float] = MappingProxyType({})


@dataclass(frozen=True, eq=False)
class RfScan:
    """One radio scan: what a receiver heard at one moment.

    Attributes
    ----------
    t : float
        Scan time, s.
    technology : Technology
    rssi_dbm : Mapping[str, float]
        Transmitter id (BSSID; a beacon's uuid_major_minor_mac, since deployments reuse one UUID and
        major/minor for many beacons; RFID tag/reader id) -> RSSI, dBm,
        each in [RSSI_MIN_DBM, RSSI_MAX_DBM].
    frequency_hz : Mapping[str, float]
        Transmitter id -> carrier frequency, Hz, where known (WiFi); may be empty.
    age_s : Mapping[str, float]
        Transmitter id -> how old the reading was at ``t``, s (Android's ``last_seen``); may be empty.
    device_model : str
        Receiver model, for per-device RSSI offsets; empty when unknown.
    """

    t: float
    technology: Technology
    rssi_dbm: Mapping[str, float]
    frequency_hz: Mapping[str, float] = field(default_factory=dict)
    age_s: Mapping[str, float] = field(default_factory=dict)
    device_model: str = ""

    def __post_init__(self) -> None:
        if not math.isfinite(self.t):
            raise ValueError(f"RfScan.t must be finite, got {self.t!r}")
        object.__setattr__(self, "technology", Technology(self.technology))
        raw = dict(self.rssi_dbm)
        # one array check for the whole scan (a real WiFi scan has hundreds of readings; NaN and the
        # infinities fail rssi_in_range), the first offender named; readings that are already str ->
        # float are copied as they are (a dict copy costs a fraction of rebuilding one)
        plain = set(map(type, raw.values())) <= {float} and set(map(type, raw)) <= {str}
        vals = np.fromiter(raw.values(), dtype=float, count=len(raw)) if plain else np.array([float(v) for v in raw.values()], dtype=float)
        ok = rssi_in_range(vals)
        if not ok.all():
            i = int(np.argmin(ok))
            raise ValueError(f"RfScan: RSSI {vals[i]!r} dBm of {list(raw)[i]!r} outside [{RSSI_MIN_DBM}, {RSSI_MAX_DBM}]")
        rssi = raw if plain else dict(zip(map(str, raw), vals.tolist()))
        object.__setattr__(self, "rssi_dbm", MappingProxyType(rssi))
        object.__setattr__(self, "frequency_hz", MappingProxyType({str(k): float(v) for k, v in dict(self.frequency_hz).items()}))
        object.__setattr__(self, "age_s", MappingProxyType({str(k): float(v) for k, v in dict(self.age_s).items()}))

    @classmethod
    def _checked_already(cls, t: float, technology: Technology, rssi: dict, frequency_hz: dict, age_s: dict, device_model: str) -> RfScan:
        """A scan whose fields already pass :meth:`__post_init__`'s checks (t finite, ids str, readings
        float and in range, a Technology): the wire decoder's fast path, which checks a whole batch's
        readings as one array (and is tested to give the same scans)."""
        obj = object.__new__(cls)
        # one update of the instance dict (six frozen-dataclass setattrs were most of a batch's scan decoding);
        # the empty mappings share one read-only view
        obj.__dict__.update(
            t=t, technology=technology, rssi_dbm=MappingProxyType(dict(rssi)),
            frequency_hz=MappingProxyType(dict(frequency_hz)) if frequency_hz else _EMPTY,
            age_s=MappingProxyType(dict(age_s)) if age_s else _EMPTY, device_model=device_model,
        )  # fmt: skip
        return obj

    def __len__(self) -> int:
        return len(self.rssi_dbm)

    def __reduce__(self):  # picklable (for worker processes) despite the read-only mapping views
        # rebuilt without __post_init__'s checks: what is pickled is a scan that passed them (the locate
        # and ingest workers send hundreds of site1 scans a second; the checks were half of unpickling)
        return (RfScan._checked_already, (self.t, self.technology, dict(self.rssi_dbm), dict(self.frequency_hz), dict(self.age_s), self.device_model))


# ----------------------------------------------------------------------------------------------
# Absolute information
# ----------------------------------------------------------------------------------------------
class FixSource(str, enum.Enum):
    GPS = "gps"
    RFID = "rfid"
    BLE = "ble"
    WIFI = "wifi"
    SURVEY = "survey"


@dataclass(frozen=True, eq=False)
class AbsoluteFix:
    """An absolute position measurement in the site frame.

    Attributes
    ----------
    t : float
        Time of validity, s.
    pos_enu : ndarray, shape (2,) or (3,)
        Position, m.
    cov : ndarray, shape (2, 2) or (3, 3)
        Position covariance, m^2, symmetric positive definite.
    source : FixSource
    floor : str or None
        Floor name as the site names it (``"F2"``, ``"B1"``, ``"0"``), None when unknown.
    floor_prob : float
        Probability that ``floor`` is right, in [0, 1].
    """

    t: float
    pos_enu: np.ndarray
    cov: np.ndarray
    source: FixSource
    floor: str | None = None
    floor_prob: float = 1.0

    def __post_init__(self) -> None:
        p = _frozen_array(self.pos_enu, name="pos_enu", ndim=1)
        n = p.shape[0]
        if n not in (2, 3):
            raise ValueError(f"AbsoluteFix.pos_enu must have 2 or 3 elements, got {n}")
        c = _frozen_array(self.cov, (n, n), "cov", ndim=2)
        if not (math.isfinite(self.t) and np.all(np.isfinite(p)) and np.all(np.isfinite(c))):
            raise ValueError("AbsoluteFix: non-finite time, position or covariance")
        # np.allclose(c, c.T, atol) written out (|a - b| <= atol + rtol |b|, its default rtol 1e-5): the
        # same test without its wrappers, which cost more than the rest of a fix (the server builds one per scan)
        a = np.abs(c)
        if not bool(np.all(np.abs(c - c.T) <= 1e-9 * max(1.0, float(a.max())) + 1e-5 * a.T)):
            raise ValueError("AbsoluteFix.cov must be symmetric")
        if np.linalg.eigvalsh(c).min() <= 0:
            raise ValueError("AbsoluteFix.cov must be positive definite")
        if not 0.0 <= self.floor_prob <= 1.0:
            raise ValueError("AbsoluteFix.floor_prob must be in [0, 1]")
        object.__setattr__(self, "pos_enu", p)
        object.__setattr__(self, "cov", c)
        object.__setattr__(self, "source", FixSource(self.source))

    @classmethod
    def trusted(
        cls, t: float, pos_enu: np.ndarray, cov: np.ndarray, source: FixSource, floor: str | None = None, floor_prob: float = 1.0
    ) -> AbsoluteFix:
        """A fix whose caller has made what :meth:`__post_init__` checks true by construction: ``t``
        finite, ``pos_enu`` (2,) or (3,) finite, ``cov`` symmetric positive definite of the matching
        shape, ``floor_prob`` in [0, 1], ``source`` a FixSource. The arrays are copied and frozen as the
        checked constructor does; nothing is checked again (the kNN locator builds one per located scan
        and its covariance is PD by its floor term, so the checks cost as much as the rest of a fix)."""
        fix = object.__new__(cls)
        p, c = _frozen_array(pos_enu), _frozen_array(cov)
        for name, value in (("t", t), ("pos_enu", p), ("cov", c), ("source", source), ("floor", floor), ("floor_prob", floor_prob)):
            object.__setattr__(fix, name, value)
        return fix

    def __reduce__(self):  # unpickled (from a worker process) frozen as made, without the checks again
        return (AbsoluteFix.trusted, (self.t, self.pos_enu, self.cov, self.source, self.floor, self.floor_prob))

    @property
    def sigma(self) -> np.ndarray:
        """Per-axis standard deviations, m."""
        return np.sqrt(np.diag(self.cov))


@dataclass(frozen=True, eq=False)
class DisplacementFix:
    """A measured displacement of the walker between two times, in the site frame.

    Kourogi et al.'s GPS differential mode (eqs 17-18): two GPS positions free of multipath, a few
    seconds apart, differenced - the biased error e_b (ionosphere, troposphere: locally constant for
    one satellite set, eq 8) cancels and only the random error remains, so ``cov`` is
    cov(e_r(t0)) + cov(e_r(t1)), not the fixes' full covariances. It tells a filter the walker's
    heading and speed (its PDR heading bias and step scale), not where the walker is.

    Attributes
    ----------
    t0, t1 : float
        Times of the two positions, s (t1 > t0).
    delta_enu : ndarray, shape (2,)
        p(t1) - p(t0), m.
    cov : ndarray, shape (2, 2)
        Covariance of the difference, m^2, symmetric positive definite.
    source : FixSource
    """

    t0: float
    t1: float
    delta_enu: np.ndarray
    cov: np.ndarray
    source: FixSource = FixSource.GPS

    def __post_init__(self) -> None:
        d = _frozen_array(self.delta_enu, (2,), "delta_enu", ndim=1)
        c = _frozen_array(self.cov, (2, 2), "cov", ndim=2)
        if not (math.isfinite(self.t0) and math.isfinite(self.t1) and np.all(np.isfinite(d)) and np.all(np.isfinite(c))):
            raise ValueError("DisplacementFix: non-finite time, displacement or covariance")
        if not self.t1 > self.t0:
            raise ValueError("DisplacementFix needs t1 > t0")
        if not np.allclose(c, c.T, atol=1e-9 * max(1.0, float(np.abs(c).max()))) or np.linalg.eigvalsh(c).min() <= 0:
            raise ValueError("DisplacementFix.cov must be symmetric positive definite")
        object.__setattr__(self, "delta_enu", d)
        object.__setattr__(self, "cov", c)
        object.__setattr__(self, "source", FixSource(self.source))

    @property
    def t(self) -> float:
        return self.t1


@dataclass(frozen=True, eq=False)
class ContainmentRegion:
    """Where the walker is with a stated probability: polygons on one floor.

    Attributes
    ----------
    floor : str or None
        Floor name; None when the floor is unknown.
    area : shapely MultiPolygon
        The region, site frame, metres (possibly several disjoint parts, with holes).
    mass : float
        Probability that the truth lies inside, in (0, 1] (0.95 for the usual region).
    t : float
        Time of validity, s (nan when timeless).
    """

    floor: str | None
    area: MultiPolygon
    mass: float
    t: float = float("nan")

    def __post_init__(self) -> None:
        area = self.area
        if isinstance(area, Polygon):
            area = MultiPolygon([area])
        elif isinstance(area, (list, tuple)):
            area = MultiPolygon([Polygon(np.asarray(r)) if not isinstance(r, Polygon) else r for r in area])
        if not isinstance(area, MultiPolygon):
            raise TypeError(f"ContainmentRegion.area must be (Multi)Polygon, got {type(area).__name__}")
        if not 0.0 < self.mass <= 1.0:
            raise ValueError("ContainmentRegion.mass must be in (0, 1]")
        object.__setattr__(self, "area", area)

    def contains(self, xy: Sequence[float]) -> bool:
        """True when the point (x, y) is inside (or on the edge of) the region."""
        return bool(self.area.covers(shapely.Point(float(xy[0]), float(xy[1]))))

    @property
    def area_m2(self) -> float:
        return float(self.area.area)


@dataclass(frozen=True, eq=False)
class Fix:
    """The answer to one radio scan: an absolute fix with its containment region and floor
    probabilities, or "no fix" and why (what the server pushes and the ``locate`` queryable returns).

    Attributes
    ----------
    fix : AbsoluteFix or None
        The position; None for a "no fix" answer.
    region : ContainmentRegion or None
        Where the walker is with probability ``region.mass`` (usually 0.95), on ``region.floor``; None
        when not computed (and always with no fix).
    floor_probs : Mapping[str, float]
        Floor name -> probability that the walker is on it, each in [0, 1]; empty when unknown (and
        always with no fix).
    reason : str
        Why there is no fix (no radio map for the site, no known transmitter in the scan ...); empty
        with a fix.
    t : float or None
        Time the answer is about, s: the fix's own time, or for "no fix" the scan's (None when the
        sender did not say).
    """

    fix: AbsoluteFix | None
    region: ContainmentRegion | None = None
    floor_probs: Mapping[str, float] = field(default_factory=dict)
    reason: str = ""
    t: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "floor_probs", MappingProxyType({str(k): float(v) for k, v in dict(self.floor_probs).items()}))
        if self.fix is None:
            if self.region is not None or self.floor_probs:
                raise ValueError("Fix: a region or floor probabilities need a fix")
        else:
            if self.t is not None and self.t != self.fix.t:
                raise ValueError(f"Fix: t {self.t!r} differs from the fix's time {self.fix.t!r}")
            if self.reason:
                raise ValueError("Fix: a reason is only for 'no fix' answers")
            object.__setattr__(self, "t", float(self.fix.t))
        if self.t is not None:
            object.__setattr__(self, "t", float(self.t))

    def __bool__(self) -> bool:
        return self.fix is not None

    def __reduce__(self):  # picklable despite the read-only mapping view
        return (Fix, (self.fix, self.region, dict(self.floor_probs), self.reason, self.t))


@dataclass(frozen=True, eq=False)
class Pose:
    """A walker's estimated position at one moment, as a client publishes it (for monitoring).

    Attributes
    ----------
    t : float
        s.
    x, y : float
        Site frame (ENU), m.
    floor : str or None
        Floor name; None when unknown.
    cov : ndarray, shape (2, 2), or None
        Covariance of (x, y), m^2; None when the sender did not give it (clients before it was sent).
    """

    t: float
    x: float
    y: float
    floor: str | None = None
    cov: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("t", "x", "y"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if self.cov is not None:
            object.__setattr__(self, "cov", _frozen_array(self.cov, (2, 2), "cov", ndim=2))

    @property
    def pos_enu(self) -> np.ndarray:
        """(x, y), m."""
        return np.array([self.x, self.y])


# ----------------------------------------------------------------------------------------------
# Floor plans
# ----------------------------------------------------------------------------------------------
class TransitionKind(str, enum.Enum):
    STAIRS = "stairs"
    LIFT = "lift"
    ESCALATOR = "escalator"


@dataclass(frozen=True, eq=False)
class FloorTransition:
    """A place where walkers change floor (both ends share the site-frame xy, approximately)."""

    kind: TransitionKind
    floor_from: str
    floor_to: str
    pos_from: tuple[float, float]
    pos_to: tuple[float, float]


@dataclass(frozen=True, eq=False)
class Floor:
    """One floor of a site.

    Attributes
    ----------
    name : str
        Floor name as the data names it (``"F1"``, ``"B1"``, ``"2"``).
    level : int
        Ordinal, 0 = ground; negative below ground.
    height : float
        Floor elevation above the site origin, m.
    outline : MultiPolygon
        The floor's footprint.
    walkable : MultiPolygon
        Where a person can be: the footprint minus solid obstacles (in the competition's plans, minus the shops).
    walls : ndarray, shape (M, 2, 2)
        Wall segments ``[[x0, y0], [x1, y1]]``, m (what a particle may not cross).
    rooms : tuple of (name, Polygon)
        Named units (shops, offices), for display and semantic labels.
    """

    name: str
    level: int
    height: float
    outline: MultiPolygon
    walkable: MultiPolygon
    walls: np.ndarray
    rooms: tuple[tuple[str, Polygon], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "walls", _frozen_array(np.asarray(self.walls, dtype=float).reshape(-1, 2, 2), (2, 2), "walls", ndim=3))

    def bounds(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the outline, m."""
        return tuple(float(v) for v in self.outline.bounds)  # type: ignore[return-value]


@dataclass(frozen=True, eq=False)
class FloorPlan:
    """A site's floors and the transitions between them, in the site frame."""

    site: str
    floors: tuple[Floor, ...]
    transitions: tuple[FloorTransition, ...] = ()
    #: Geodetic origin of the site frame, when known (needed for NMEA and WGS84 GeoJSON output).
    origin: GeodeticOrigin | None = None

    def floor(self, name: str) -> Floor:
        for f in self.floors:
            if f.name == name:
                return f
        raise KeyError(f"site {self.site!r} has no floor {name!r} (floors: {[f.name for f in self.floors]})")

    @property
    def floor_names(self) -> list[str]:
        return [f.name for f in self.floors]


# ----------------------------------------------------------------------------------------------
# Trajectories and ground truth
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Trajectory:
    """A time series of positions in the site frame.

    Attributes
    ----------
    t : ndarray, shape (N,)
        s, strictly increasing.
    pos_enu : ndarray, shape (N, 3)
        m (2-D inputs get z = 0).
    floor : tuple of (str or None), length N, or None
        Floor name per sample; None when unknown for the whole track.
    sigma_enu : ndarray, shape (N, 3) or None
        Per-axis standard deviations, m.
    quat_wxyz : ndarray, shape (N, 4) or None
        Body-to-nav attitude, when the source has one.
    """

    t: np.ndarray
    pos_enu: np.ndarray
    floor: tuple[str | None, ...] | None = None
    sigma_enu: np.ndarray | None = None
    quat_wxyz: np.ndarray | None = None

    def __post_init__(self) -> None:
        t = _frozen_array(self.t, name="t", ndim=1)
        _check_time(t)
        p = np.asarray(self.pos_enu, dtype=float)
        if p.ndim != 2 or p.shape[1] not in (2, 3):
            raise ValueError(f"Trajectory.pos_enu must be (N, 2) or (N, 3), got {p.shape}")
        if p.shape[1] == 2:
            p = np.column_stack([p, np.zeros(len(p))])
        if p.shape[0] != t.shape[0]:
            raise ValueError(f"Trajectory: {p.shape[0]} positions but {t.shape[0]} timestamps")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "pos_enu", _frozen_array(p, (3,), "pos_enu"))
        if self.floor is not None:
            fl = tuple(None if f is None else str(f) for f in self.floor)
            if len(fl) != len(t):
                raise ValueError("Trajectory.floor must have one entry per sample")
            object.__setattr__(self, "floor", fl)
        if self.sigma_enu is not None:
            s = np.asarray(self.sigma_enu, dtype=float)
            if s.ndim == 2 and s.shape[1] == 2:
                s = np.column_stack([s, np.zeros(len(s))])
            s = _frozen_array(s, (3,), "sigma_enu", ndim=2)
            if s.shape[0] != t.shape[0]:
                raise ValueError("Trajectory.sigma_enu must have one row per sample")
            object.__setattr__(self, "sigma_enu", s)
        if self.quat_wxyz is not None:
            q = _frozen_array(self.quat_wxyz, (4,), "quat_wxyz", ndim=2)
            if q.shape[0] != t.shape[0]:
                raise ValueError("Trajectory.quat_wxyz must have one row per sample")
            object.__setattr__(self, "quat_wxyz", q)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def distance_travelled(self) -> float:
        """Path length, m (3-D)."""
        return float(np.linalg.norm(np.diff(self.pos_enu, axis=0), axis=1).sum()) if len(self) > 1 else 0.0


@dataclass(frozen=True, eq=False)
class Waypoints:
    """Ground-truth positions marked by a walker (kept apart from sensor data).

    Attributes
    ----------
    t : ndarray, shape (N,)
        s, sorted (not necessarily strictly: two marks may share a millisecond).
    pos_enu : ndarray, shape (N, 2)
        Site frame, m.
    floor : str or None
        The walk's floor (Indoor Location Competition traces: one per trace).
    floors : tuple of (str or None), or None
        Each mark's own floor, for a walk that changes floor (the simulator's walks take the stairs);
        None when every mark is on ``floor``. :meth:`floor_of` answers either way.
    """

    t: np.ndarray
    pos_enu: np.ndarray
    floor: str | None = None
    floors: tuple | None = None

    def __post_init__(self) -> None:
        t = _frozen_array(self.t, name="t", ndim=1)
        if t.size > 1 and np.any(np.diff(t) < 0):
            raise ValueError("Waypoints.t must be sorted")
        p = _frozen_array(self.pos_enu, (2,), "pos_enu", ndim=2) if len(t) else _frozen_array(np.zeros((0, 2)), (2,), "pos_enu")
        if p.shape[0] != t.shape[0]:
            raise ValueError("Waypoints: one position per time")
        if self.floors is not None:
            if len(self.floors) != t.shape[0]:
                raise ValueError("Waypoints: one floor per mark")
            object.__setattr__(self, "floors", tuple(self.floors))
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "pos_enu", p)

    def floor_of(self, i: int) -> str | None:
        """Mark i's floor: its own where the walk changes floor, else the walk's."""
        if self.floors is not None and self.floors[i] is not None:
            return self.floors[i]
        return self.floor

    def __len__(self) -> int:
        return int(self.t.shape[0])


# ----------------------------------------------------------------------------------------------
# Survey marks and walks
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SurveyMark:
    """A survey mark: the operator says "I am at (x, y) on ``floor``" at time ``t``.

    Attributes
    ----------
    t : float
        s.
    x, y : float
        Site frame (ENU), m.
    floor : str
        The mark's floor; empty when unknown.
    """

    t: float
    x: float
    y: float
    floor: str = ""

    def __post_init__(self) -> None:
        for name in ("t", "x", "y"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"SurveyMark.{name} must be a finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        object.__setattr__(self, "floor", str(self.floor or ""))

    @property
    def pos_enu(self) -> np.ndarray:
        """(x, y), m."""
        return np.array([self.x, self.y])


class WalkEnd(str, enum.Enum):
    """How a stored walk ended."""

    OPEN = "open"  # still receiving (no end marker, not idle long enough)
    MARKER = "marker"  # the device sent an end-of-walk marker
    IDLE = "idle"  # the device fell silent for longer than the idle gap


@dataclass(frozen=True, eq=False)
class Walk:
    """One device's walk: its run of batches between a start and an end (an end-of-walk marker or
    an idle gap), as the server stores it and the SLAM work reads it.

    Attributes
    ----------
    site, device : str
        Ids as on the wire.
    walk_id : int or None
        The store's id of the walk; None for a walk not (yet) stored.
    t_start, t_end : float
        Time of the first and last record of the walk, s (the recording's clock).
    device_model : str
        Phone or IMU model; empty when unknown.
    floors : tuple of str
        Floors the walk's scans, marks or fixes named, in order of first appearance.
    steps : tuple of StepEvent
        Sorted by time.
    scans : tuple of RfScan
        Sorted by time.
    marks : tuple of SurveyMark
        Sorted by time (survey walks; empty for a phone client).
    end : WalkEnd
    """

    site: str
    device: str
    walk_id: int | None
    t_start: float
    t_end: float
    device_model: str = ""
    floors: tuple[str, ...] = ()
    steps: tuple[StepEvent, ...] = ()
    scans: tuple[RfScan, ...] = ()
    marks: tuple[SurveyMark, ...] = ()
    end: WalkEnd = WalkEnd.OPEN

    def __post_init__(self) -> None:
        if not (math.isfinite(self.t_start) and math.isfinite(self.t_end)) or self.t_end < self.t_start:
            raise ValueError(f"Walk: need finite t_start <= t_end, got {self.t_start!r}, {self.t_end!r}")
        object.__setattr__(self, "end", WalkEnd(self.end))
        for name in ("floors", "steps", "scans", "marks"):
            object.__setattr__(self, name, tuple(getattr(self, name)))

    @property
    def duration(self) -> float:
        """s."""
        return self.t_end - self.t_start


#: How a walk's corrected track is tied to the site frame (the SLAM's anchoring of its piece(s)):
#: its own survey marks, fixes from a radio map, loops to walks that have either, the floor plan (a
#: group of walks placed by search), or nothing ("relative": a shape in its own frame, never used as
#: an absolute position).
TRACK_ANCHORS = ("marks", "map", "loops", "plan", "relative")


@dataclass(frozen=True, eq=False)
class CorrectedTrack:
    """A walk's drift-corrected track from the crowd SLAM: a position and covariance at every step and
    scan (what the server stores per walk and sends a device on its ``track`` key).

    Attributes
    ----------
    walk_id : int or None
        The store's id of the walk.
    t : (N,) array
        Times of the points, s (the walk's clock), non-decreasing (a scan may share a step's time).
    pos_enu : (N, 2) array
        Corrected positions in the site frame, m.
    cov : (N, 2, 2) array
        Their marginal covariances, m^2 (NaN where the solve gave none, e.g. a relative walk).
    floor : tuple of str, length N
        Floor of each point.
    kind : tuple of str, length N
        ``"step"`` or ``"scan"``: the record the point belongs to.
    anchored : str
        One of :data:`TRACK_ANCHORS` (the best of the walk's pieces).
    scale : float
        The walk's step-length scale s, the factor its PDR step lengths needed (slam.md 3.1: a segment's
        odometry residual is p_j - p_i - (a D + b D_perp) = p_j - p_i - s R(beta) D, so s = sqrt(a^2 + b^2)),
        the median over its segments; 1 = the PDR's lengths were right.
    heading_bias : float
        The walk's heading bias beta = atan2(b, a), rad, CCW, of the median segment: the angle that rotates
        the PDR's headings onto the corrected track (the filters' b_psi).
    """

    walk_id: int | None
    t: np.ndarray
    pos_enu: np.ndarray
    cov: np.ndarray
    floor: tuple[str, ...]
    kind: tuple[str, ...]
    anchored: str = "relative"
    scale: float = 1.0
    heading_bias: float = 0.0

    def __post_init__(self) -> None:
        t = _frozen_array(self.t, name="CorrectedTrack.t", ndim=1)
        n = len(t)
        if not np.all(np.isfinite(t)) or (n > 1 and np.any(np.diff(t) < 0)):
            raise ValueError("CorrectedTrack.t: finite, non-decreasing times needed")
        pos = _frozen_array(np.reshape(self.pos_enu, (n, 2)) if np.size(self.pos_enu) == 2 * n else self.pos_enu, (2,), "CorrectedTrack.pos_enu")
        cov = _frozen_array(np.reshape(self.cov, (n, 2, 2)) if np.size(self.cov) == 4 * n else self.cov, (2, 2), "CorrectedTrack.cov")
        if len(pos) != n or len(cov) != n or len(self.floor) != n or len(self.kind) != n:
            raise ValueError(
                f"CorrectedTrack: {n} times but {len(pos)} positions, {len(cov)} covariances, {len(self.floor)} floors, {len(self.kind)} kinds"
            )
        if not np.all(np.isfinite(pos)):
            raise ValueError("CorrectedTrack.pos_enu: non-finite position")
        if self.anchored not in TRACK_ANCHORS:
            raise ValueError(f"CorrectedTrack.anchored: {self.anchored!r} is not one of {TRACK_ANCHORS}")
        if not (math.isfinite(self.scale) and math.isfinite(self.heading_bias)):
            raise ValueError("CorrectedTrack: non-finite scale or heading bias")
        bad = [k for k in self.kind if k not in ("step", "scan")]
        if bad:
            raise ValueError(f"CorrectedTrack.kind: {bad[0]!r} is not 'step' or 'scan'")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "pos_enu", pos)
        object.__setattr__(self, "cov", cov)
        object.__setattr__(self, "floor", tuple(str(f) for f in self.floor))
        object.__setattr__(self, "kind", tuple(self.kind))

    def __len__(self) -> int:
        return len(self.t)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray, str] | None:
        """(position, covariance, floor) at time ``t``, linearly interpolated between the points around it
        (the nearest point's covariance and floor); None outside the track's span or for an empty track."""
        if len(self.t) == 0 or t < self.t[0] or t > self.t[-1]:
            return None
        j = int(np.clip(np.searchsorted(self.t, t, side="right"), 1, len(self.t) - 1)) if len(self.t) > 1 else 0
        i = max(j - 1, 0)
        dt = self.t[j] - self.t[i]
        u = 0.0 if dt <= 0 else float((t - self.t[i]) / dt)
        p = self.pos_enu[i] + u * (self.pos_enu[j] - self.pos_enu[i])
        k = j if u >= 0.5 else i
        return p, self.cov[k], self.floor[k]

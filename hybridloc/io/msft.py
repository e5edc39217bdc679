"""Indoor Location Competition 2.0 (Microsoft / XYZ10) traces and floor plans.

Trace format: tab-separated text, often gzipped. ``#`` lines are a header of ``key:value`` pairs
(startTime, SiteID, SiteName, FloorId, FloorName, Brand, Model, sensor specs, endTime). Data lines
are ``unix_ms  TYPE_*  values...``:

=================================  ==========================================================
``TYPE_ACCELEROMETER ax ay az acc``  m/s^2 (calibrated)
``TYPE_GYROSCOPE wx wy wz acc``      rad/s (calibrated)
``TYPE_MAGNETIC_FIELD mx my mz acc`` uT (converted to tesla here)
``TYPE_ROTATION_VECTOR x y z acc``   Android rotation vector (kept for comparison only)
``TYPE_WIFI ssid bssid rssi f last`` one line per access point; lines sharing a timestamp form one
                                     scan; ``f`` in MHz; ``last`` = last-seen Unix ms
``TYPE_BEACON uuid major minor tx rssi dist mac last``  iBeacon; id = ``uuid_major_minor_mac``
``TYPE_WAYPOINT x y [floor]``        **ground truth**, floor-plan metres; kept apart from sensors;
                                     ``floor``: our extension (the simulator's walks change floor)
=================================  ==========================================================

Header lines ``type:N name:... maximumRange:R`` give each sensor's full scale: the accelerometer's
(type 1, m/s^2) and gyroscope's (type 4, rad/s) become the IMU block's ``accel_range`` and
``gyro_range``, so saturated (clipped) readings can be told.

Beacons: many deployments give every beacon the same ``uuid major minor`` (site1's mall: 264 beacons
on F2 all ``9195b3ad-..._0_0``), so the MAC is part of a beacon's id. Each advert is its own line
with its own timestamp; the adverts heard within ``BLE_SCAN_WINDOW_S`` of the first one form one BLE
scan stamped at the newest advert, each reading with its age (the newest advert of a beacon kept).

Known types we do not use (the ``_UNCALIBRATED`` forms, ``TYPE_BLUE``/``TYPE_BLU4`` raw BLE adverts,
``TYPE_DIST1``/``TYPE_DIST2``, ``TYPE_SENSOR_MAGNETIC_FIELD_ACCURACY_CHANGED``) are counted in the
report as ``unused-record``; anything else as the problem ``unknown-record``.

Policy for bad input (see :mod:`hybridloc.io.common`): malformed lines, non-finite numbers and RSSI
out of range are problems (skipped and reported, or raised). Sensor samples out of time order are
re-sorted and exact duplicate timestamps dropped, both noted in the report.

Floor plans: ``geojson_map.json`` is in WGS84 lon/lat; its first feature (category ``floor``) is the
floor outline and the others are shops. ``floor_info.json`` gives the map's width and height in
metres. The floor-plan frame (the one waypoints use) maps the outline's lon/lat bounding box linearly
onto ``[0, width] x [0, height]`` with x east and y north. Each floor has its own bounding box, so the
floors' frames differ by up to a few metres (site1: F3 is 2.8 m taller than F1); each
:class:`~hybridloc.types.Floor` keeps its own transform.
"""

from __future__ import annotations

import json
import math
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, shape

from ..geo import GeodeticOrigin
from ..types import (
    Floor,
    FloorPlan,
    ImuBlock,
    RfScan,
    Technology,
    Waypoints,
    rssi_in_range,
)
from ..units import DEG, MHZ_TO_HZ, MS_TO_S, UT_TO_T
from .common import DataFormatError, OnError, ReadReport, iter_lines, sort_unique

SENSOR_TYPES = {
    "TYPE_ACCELEROMETER": "acc",
    "TYPE_GYROSCOPE": "gyr",
    "TYPE_MAGNETIC_FIELD": "mag",
    "TYPE_ROTATION_VECTOR": "rv",
}
UNUSED_TYPES = frozenset(
    {
        "TYPE_ACCELEROMETER_UNCALIBRATED",
        "TYPE_GYROSCOPE_UNCALIBRATED",
        "TYPE_MAGNETIC_FIELD_UNCALIBRATED",
        "TYPE_BLUE",
        "TYPE_BLU4",
        "TYPE_DIST1",
        "TYPE_DIST2",
        "TYPE_SENSOR_MAGNETIC_FIELD_ACCURACY_CHANGED",
    }
)
#: Plausible Unix time range for a recording, ms (2010-2100): catches seconds-vs-ms mix-ups.
_UNIX_MS_RANGE = (1.26e12, 4.1e12)


@dataclass(frozen=True, eq=False)
class IlcTrace:
    """One Indoor Location Competition walk.

    Attributes
    ----------
    path : str
    meta : dict
        Header fields (``SiteID``, ``SiteName``, ``FloorId``, ``FloorName``, ``Brand``, ``Model``,
        ``startTime``, ``endTime`` ...), strings as in the file.
    imu : ImuBlock or None
        Calibrated accelerometer, gyroscope and magnetometer (tesla) on the accelerometer's
        timestamps (gyro and magnetometer interpolated when their stamps differ); None when the
        trace has no accelerometer or gyroscope.
    rotation_vector : tuple (t, quat_wxyz) or None
        Android's fused attitude, for comparison only: times (N,) and unit quaternions (N, 4).
    scans : tuple of RfScan
        WiFi and BLE scans sorted by time.
    waypoints : Waypoints
        Ground truth, floor-plan frame. Never feed these to a method that claims "no survey".
    report : ReadReport
    """

    path: str
    meta: dict
    imu: ImuBlock | None
    rotation_vector: tuple[np.ndarray, np.ndarray] | None
    scans: tuple[RfScan, ...]
    waypoints: Waypoints
    report: ReadReport

    @property
    def floor(self) -> str | None:
        return self.meta.get("FloorName") or None

    @property
    def site(self) -> str | None:
        return self.meta.get("SiteID") or None

    @property
    def device_model(self) -> str:
        return " ".join(v for v in (self.meta.get("Brand", ""), self.meta.get("Model", "")) if v)

    @property
    def wifi_scans(self) -> tuple[RfScan, ...]:
        return tuple(s for s in self.scans if s.technology is Technology.WIFI)


def _floats(fields: list[str], n: int) -> list[float] | None:
    try:
        vals = [float(v) for v in fields[:n]]
    except ValueError:
        return None
    return vals


def iter_ilc_records(path: str | os.PathLike, report: ReadReport, keep=None) -> Iterator[tuple[int, str, list[str]]]:
    """Stream ``(line_number, type, fields)`` from a trace; fields[0] is the Unix ms timestamp.

    Header lines are yielded with type ``"#"`` and their tab-separated ``key:value`` parts as fields.
    Blank lines are skipped; a line without a timestamp and type is a ``malformed-line`` problem.
    ``keep`` (raw bytes -> bool) skips the other lines undecoded (:func:`~.common.iter_lines`).
    """
    for lineno, line in iter_lines(path, report, keep=keep):
        if not line.strip():
            continue
        parts = line.split("\t")
        if parts[0].startswith("#"):
            yield lineno, "#", [p for p in parts[1:] if p]
            continue
        if len(parts) < 2 or not parts[1].startswith("TYPE_"):
            report.problem(lineno, "malformed-line", f"expected 'unix_ms<TAB>TYPE_...', got {line[:60]!r}")
            continue
        yield lineno, parts[1], [parts[0]] + parts[2:]


def read_ilc_trace(path: str | os.PathLike, on_error: OnError = "skip") -> IlcTrace:
    """Read one trace (plain or gzip). See the module docstring for the format and bad-input policy."""
    path = str(path)
    report = ReadReport(path, on_error)
    meta: dict[str, str] = {}
    full_scale: dict[str, float] = {}  # Android sensor type -> maximumRange (1 accelerometer, 4 gyroscope)
    sensors: dict[str, list[list[float]]] = {k: [] for k in SENSOR_TYPES.values()}
    wifi: dict[float, dict[str, tuple[float, float, float]]] = {}
    ble: list[tuple[float, str, float]] = []  # (t, beacon id, rssi) per advert
    wps: list[tuple[float, float, float, str | None]] = []  # (t, x, y, the mark's own floor)
    for lineno, rtype, f in iter_ilc_records(path, report):
        if rtype == "#":
            line_meta = _header_fields(f)
            meta.update(line_meta)
            if "type" in line_meta and "maximumRange" in line_meta:  # a sensor's spec line (Android sensor type)
                try:
                    full_scale[line_meta["type"]] = float(line_meta["maximumRange"])
                except ValueError:
                    report.problem(lineno, "malformed-line", f"maximumRange {line_meta['maximumRange']!r}")
            continue
        t = _record_time(lineno, f, report)
        if t is None:
            continue
        if rtype in SENSOR_TYPES:
            vals = _floats(f[1:], 3) if len(f) >= 4 else None
            if vals is None:
                report.problem(lineno, "malformed-line", f"{rtype} needs 3 numbers")
                continue
            if not all(math.isfinite(v) for v in vals):
                report.problem(lineno, "non-finite", rtype)
                continue
            sensors[SENSOR_TYPES[rtype]].append([t, *vals])
        elif rtype == "TYPE_WIFI":
            # ssid may be empty (or, rarely, contain tabs): take the last four fields from the end.
            if len(f) < 6:
                report.problem(lineno, "malformed-line", "TYPE_WIFI needs ssid, bssid, rssi, frequency, last_seen")
                continue
            bssid, rssi_s, freq_s, last_s = f[-4], f[-3], f[-2], f[-1]
            try:
                rssi, freq, last = float(rssi_s), float(freq_s), float(last_s)
            except ValueError:
                report.problem(lineno, "malformed-line", "TYPE_WIFI numbers")
                continue
            if not rssi_in_range(rssi):
                report.problem(lineno, "rssi-out-of-range", f"{rssi_s} dBm")
                continue
            bssid = bssid.strip().lower()
            if not bssid:
                report.problem(lineno, "malformed-line", "empty BSSID")
                continue
            scan = wifi.setdefault(t, {})
            if bssid in scan:
                report.note("duplicate-transmitter", 1, f"line {lineno}: {bssid} twice in one scan, strongest kept")
                if scan[bssid][0] >= rssi:
                    continue
            scan[bssid] = (rssi, freq * MHZ_TO_HZ, max(0.0, t - last * MS_TO_S))
        elif rtype == "TYPE_BEACON":
            if len(f) < 9:
                report.problem(lineno, "malformed-line", "TYPE_BEACON needs uuid, major, minor, tx_power, rssi, distance, mac, last_seen")
                continue
            try:
                rssi = float(f[5])
            except ValueError:
                report.problem(lineno, "malformed-line", "TYPE_BEACON rssi")
                continue
            if not rssi_in_range(rssi):
                report.problem(lineno, "rssi-out-of-range", f"{f[5]} dBm")
                continue
            ble.append((t, f"{f[1]}_{f[2]}_{f[3]}_{f[7].strip()}".lower().rstrip("_"), rssi))
        elif rtype == "TYPE_WAYPOINT":
            _add_waypoint(wps, lineno, t, f, report)
        elif rtype in UNUSED_TYPES:
            report.note("unused-record")  # known and documented; not a problem
        else:
            report.problem(lineno, "unknown-record", rtype)

    model = " ".join(v for v in (meta.get("Brand", ""), meta.get("Model", "")) if v)
    streams = {}
    for k, v in sensors.items():
        a = np.asarray(v, dtype=float).reshape(-1, 4)
        t, (vals,) = sort_unique(a[:, 0], [a[:, 1:]], report, k)
        streams[k] = np.column_stack([t, vals])
    imu = _assemble_imu(streams, path, report, full_scale)
    rv = None
    if len(streams["rv"]):
        xyz = streams["rv"][:, 1:4]
        w = np.sqrt(np.clip(1.0 - np.sum(xyz**2, axis=1), 0.0, None))
        rv = (streams["rv"][:, 0].copy(), np.column_stack([w, xyz]))
    scans = [
        RfScan(t, Technology.WIFI, {k: v[0] for k, v in d.items()}, {k: v[1] for k, v in d.items()}, {k: v[2] for k, v in d.items()}, model)
        for t, d in wifi.items()
    ] + _ble_scans(ble, model)
    scans.sort(key=lambda s: (s.t, s.technology.value))
    _folder_floor(path, meta, report)
    return IlcTrace(path, meta, imu, rv, tuple(scans), _waypoints(wps, meta), report)


def read_ilc_waypoints(path: str | os.PathLike, on_error: OnError = "skip") -> Waypoints:
    """Only a trace's ground-truth marks and its floor (the floor folder's name in a site's layout,
    else the header's: :func:`_folder_floor`), the sensor lines skipped
    unparsed: about 3x faster than :func:`read_ilc_trace` (what comparing the routes of hundreds
    of walks needs). Same checks on what it reads."""
    report = ReadReport(str(path), on_error)
    meta: dict[str, str] = {}
    wps: list[tuple[float, float, float, str | None]] = []
    for lineno, rtype, f in iter_ilc_records(path, report, keep=lambda raw: raw.startswith(b"#") or b"\tTYPE_WAYPOINT\t" in raw):
        if rtype == "#":
            meta.update(_header_fields(f))
        else:
            t = _record_time(lineno, f, report)
            if t is not None:
                _add_waypoint(wps, lineno, t, f, report)
    _folder_floor(str(path), meta, None)
    return _waypoints(wps, meta)


def _site_floor_name(path: str) -> str | None:
    """The floor folder's name of a trace kept in a site's layout (``<floor>/path_data_files/<file>``)
    when it is a floor name (F1, B1, 1F ... :data:`_FLOOR_RE`; not a plain number); None elsewhere."""
    p = Path(path)
    if p.parent.name != "path_data_files":
        return None
    name = p.parent.parent.name
    return name if _names_a_floor(name) else None


def _names_a_floor(folder: str) -> bool:
    """Whether a floor folder's name is a floor name (F1, B1, 1F ... :data:`_FLOOR_RE`), which then
    names its plan (:func:`read_ilc_floor`) and its traces (:func:`_folder_floor`); a folder of digits
    (a year, an id) names no floor."""
    return _FLOOR_RE.match(folder) is not None


def _folder_floor(path: str, meta: dict, report: ReadReport | None) -> None:
    """One floor name per site: a trace in a floor folder takes the folder's name, the name its plan
    goes by (:func:`read_ilc_floor`) and the crowd evaluations group it under, over a header that
    spells the floor otherwise (kept as ``FloorNameInFile``; noted once in the report)."""
    folder = _site_floor_name(path)
    if folder is None or meta.get("FloorName") == folder:
        return
    if meta.get("FloorName"):
        meta["FloorNameInFile"] = meta["FloorName"]
        if report is not None:
            report.note(
                "floor-name-from-folder", 1, f"the header names floor {meta['FloorName']!r}, the folder {folder!r}: the folder's name is used"
            )
    meta["FloorName"] = folder


def _header_fields(parts: list[str]) -> dict[str, str]:
    """A header line's ``key:value`` parts."""
    out = {}
    for part in parts:
        if ":" in part:
            k, v = part.split(":", 1)
            out[k.strip()] = v.strip()
    return out


def _record_time(lineno: int, f: list[str], report: ReadReport) -> float | None:
    """A data line's time, s, from its Unix-millisecond field; None (a problem reported) when bad."""
    try:
        t_ms = float(f[0])
    except ValueError:
        report.problem(lineno, "bad-timestamp", repr(f[0]))
        return None
    if not (_UNIX_MS_RANGE[0] <= t_ms <= _UNIX_MS_RANGE[1]):
        report.problem(lineno, "bad-timestamp", f"{f[0]} is not a Unix time in milliseconds")
        return None
    return t_ms * MS_TO_S


def _add_waypoint(wps: list, lineno: int, t: float, f: list[str], report: ReadReport) -> None:
    """``x y`` and, in our extension for walks that change floor (the simulator writes it), the
    mark's floor name as a third field."""
    vals = _floats(f[1:3], 2) if len(f) >= 3 else None
    if vals is None or not all(math.isfinite(v) for v in vals):
        report.problem(lineno, "malformed-line", "TYPE_WAYPOINT needs two finite numbers")
        return
    floor = f[3].strip() if len(f) >= 4 and f[3].strip() else None
    wps.append((t, vals[0], vals[1], floor))


def _waypoints(wps: list, meta: dict) -> Waypoints:
    wps = sorted(wps, key=lambda w: w[:3])
    floors = tuple(w[3] for w in wps) if any(w[3] is not None for w in wps) else None
    return Waypoints(np.array([w[0] for w in wps]), np.array([[w[1], w[2]] for w in wps]).reshape(-1, 2), meta.get("FloorName") or None, floors)


def _interp_rows(t_src: np.ndarray, v_src: np.ndarray, t_dst: np.ndarray) -> np.ndarray:
    if len(t_src) == len(t_dst) and np.array_equal(t_src, t_dst):
        return v_src
    return np.column_stack([np.interp(t_dst, t_src, v_src[:, i]) for i in range(v_src.shape[1])])


#: BLE adverts heard within this span of a group's first one form one scan, s. Android reports each
#: advert as it arrives; a beacon advertising at 1-10 Hz is heard about once a second.
BLE_SCAN_WINDOW_S = 1.0


def _ble_scans(adverts: list[tuple[float, str, float]], model: str) -> list[RfScan]:
    """Group time-sorted adverts into scans of at most ``BLE_SCAN_WINDOW_S`` (see module docstring)."""
    out: list[RfScan] = []
    group: dict[str, tuple[float, float]] = {}
    t_first = t_last = -math.inf

    def flush():
        if group:
            out.append(
                RfScan(
                    t_last,
                    Technology.BLE,
                    {k: v[1] for k, v in group.items()},
                    age_s={k: t_last - v[0] for k, v in group.items()},
                    device_model=model,
                )
            )

    for t, key, rssi in sorted(adverts, key=lambda a: a[0]):
        if t - t_first > BLE_SCAN_WINDOW_S:
            flush()
            group, t_first = {}, t
        group[key] = (t, rssi)  # the newest advert of a beacon
        t_last = t
    flush()
    return out


def _assemble_imu(streams: dict[str, np.ndarray], path: str, report: ReadReport, full_scale: dict[str, float] | None = None) -> ImuBlock | None:
    acc, gyr, mag = streams["acc"], streams["gyr"], streams["mag"]
    if len(acc) < 2 or len(gyr) < 2:
        if len(acc) or len(gyr):
            report.problem(None, "no-imu", "accelerometer or gyroscope missing")
        return None
    # Keep accelerometer epochs inside the gyro's span (interpolation, never extrapolation).
    lo, hi = gyr[0, 0], gyr[-1, 0]
    if len(mag) >= 2:
        lo, hi = max(lo, mag[0, 0]), min(hi, mag[-1, 0])
    keep = (acc[:, 0] >= lo) & (acc[:, 0] <= hi)
    if (~keep).sum():
        report.note("trimmed-edge", int((~keep).sum()), "accelerometer samples outside the gyro/magnetometer span")
    acc = acc[keep]
    if len(acc) < 2:
        report.problem(None, "no-imu", "sensor streams do not overlap in time")
        return None
    t = acc[:, 0]
    g = _interp_rows(gyr[:, 0], gyr[:, 1:4], t)
    m = _interp_rows(mag[:, 0], mag[:, 1:4], t) * UT_TO_T if len(mag) >= 2 else None
    if m is None:
        report.note("no-magnetometer", 1, "heading will rely on the gyroscope only")
    fs = {k: v for k, v in (full_scale or {}).items() if math.isfinite(v) and v > 0}
    return ImuBlock(t, acc[:, 1:4], g, m, source=path, accel_range=fs.get("1"), gyro_range=fs.get("4"))


# ----------------------------------------------------------------------------------------------
# Floor plans
# ----------------------------------------------------------------------------------------------
#: Floor names of the Indoor Location Competition's sites: F1 / L1 (ground) and B1 (first basement) in
#: the 2020 release; 1F and 1B in the 2021 one (the Kaggle "indoor location & navigation" sites); B1F
#: as some malls sign it. ASCII digits only.
_FLOOR_RE = re.compile(r"^(?:(?P<f>F|L)(?P<fn>\d+)|(?P<fn2>\d+)F|(?P<b>B)(?P<bn>\d+)F?|(?P<bn2>\d+)B)$", re.IGNORECASE | re.ASCII)

#: Storey height assumed where the data gives none, m.
DEFAULT_STOREY_HEIGHT = 5.0


def floor_level(name: str) -> int:
    """Ordinal of a floor name: F1 / L1 / 1F -> 0, F2 / 2F -> 1, B1 / 1B / B1F -> -1; a plain integer
    is taken as is."""
    m = _FLOOR_RE.match(name.strip())
    if m and (m.group("fn") or m.group("fn2")):
        return int(m.group("fn") or m.group("fn2")) - 1
    if m and (m.group("bn") or m.group("bn2")):
        return -int(m.group("bn") or m.group("bn2"))
    try:
        return int(name)
    except ValueError:
        raise ValueError(f"cannot tell the level of floor {name!r}") from None


def floor_name(level: int, like: str, known=()) -> str:
    """The name of floor ``level``: the one of the site's ``known`` floor names at that level when there
    is one, else a name in the style of ``like`` (a floor name of the same site):
    ``floor_name(1, "F1") == "F2"``, ``floor_name(-1, "2F") == "B1"``, ``floor_name(0, "1B") == "1F"``,
    ``floor_name(2, "0") == "2"``."""
    for k in sorted(known):
        try:
            if floor_level(k) == level:
                return k
        except ValueError:
            continue
    m = _FLOOR_RE.match(like.strip())
    if m is None:
        return str(level)
    like = like.strip()
    b1f = bool(m.group("b")) and like.upper().endswith("F")
    if level >= 0:  # 1F where the site writes 1F, 1B or B1F; else F1 (L1 on an L site)
        out = f"{level + 1}F" if (m.group("fn2") or m.group("bn2") or b1f) else f"{m.group('f') or 'F'}{level + 1}"
    else:  # 1B where the site writes 1B, B1F where it writes B1F, else B1
        out = f"{-level}B" if m.group("bn2") else f"B{-level}F" if b1f else f"B{-level}"
    return out if like.upper() == like else out.lower()


@dataclass(frozen=True)
class LonLatToFloor:
    """The linear map from a floor's lon/lat bounding box onto its plan ``[0, w] x [0, h]`` metres."""

    lon0: float
    lat0: float
    lon1: float
    lat1: float
    width: float
    height: float

    def __call__(self, lonlat: np.ndarray) -> np.ndarray:
        ll = np.asarray(lonlat, dtype=float)
        x = (ll[..., 0] - self.lon0) / (self.lon1 - self.lon0) * self.width
        y = (ll[..., 1] - self.lat0) / (self.lat1 - self.lat0) * self.height
        return np.stack([x, y], axis=-1)

    def origin(self) -> GeodeticOrigin:
        """Geodetic position of the plan's (0, 0)."""
        return GeodeticOrigin(self.lat0 * DEG, self.lon0 * DEG, 0.0)


def _map_geometry(geom, fn):
    return shapely.transform(geom, lambda xy: fn(xy))


def read_ilc_floor(floor_dir: str | os.PathLike) -> tuple[Floor, LonLatToFloor]:
    """Read ``geojson_map.json`` + ``floor_info.json`` of one floor folder into a :class:`Floor`.

    The first feature (category ``"floor"``) is the footprint; the other polygons are shops, kept as
    ``rooms`` for display. In the Indoor Location Competition plans the shops have no doors and the
    recorded walkers keep to the corridors (site1: 100 / 98.4 / 99.3 % of the F1 / F2 / F3 waypoints
    lie in the footprint minus the shops, against a walkable share of 32 / 23 / 21 % of the footprint),
    so the walkable area is the footprint minus the shops (pieces under ``MIN_WALKABLE_PIECE_M2``, the
    slivers between adjacent shop outlines, dropped) and the walls are its boundary segments: the
    shop fronts are walls.

    Our extension, written by the simulator: LineString features of category ``"wall"`` list the walls
    themselves, with doors and entrances left open. A plan that lists its walls has enterable rooms:
    its walkable area is the whole footprint and its walls are the listed ones.
    """
    floor_dir = Path(floor_dir)
    gj_path, info_path = floor_dir / "geojson_map.json", floor_dir / "floor_info.json"
    try:
        gj = json.loads(gj_path.read_text(encoding="utf-8"))
        info = json.loads(info_path.read_text(encoding="utf-8"))["map_info"]
        width, height = float(info["width"]), float(info["height"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise DataFormatError(floor_dir, None, f"cannot read floor plan: {exc}") from exc
    if not (width > 0 and height > 0):
        raise DataFormatError(info_path, None, "map width and height must be positive metres")
    feats = gj.get("features") or []
    outline_feats = [f for f in feats if (f.get("properties") or {}).get("category") == "floor"] or feats[:1]
    if not outline_feats:
        raise DataFormatError(gj_path, None, "no features")
    outline_ll = shape(outline_feats[0]["geometry"])
    lon0, lat0, lon1, lat1 = outline_ll.bounds
    if not (-180 <= lon0 < lon1 <= 360 and -90 <= lat0 < lat1 <= 90):
        raise DataFormatError(gj_path, None, f"outline bounds {outline_ll.bounds} are not WGS84 lon/lat degrees")
    tf = LonLatToFloor(lon0, lat0, lon1, lat1, width, height)
    outline = _map_geometry(outline_ll, tf)
    if isinstance(outline, Polygon):
        outline = MultiPolygon([outline])
    outline = shapely.make_valid(outline)
    if not isinstance(outline, MultiPolygon):
        outline = MultiPolygon([g for g in getattr(outline, "geoms", [outline]) if isinstance(g, Polygon)])
    rooms = []
    for f in feats:
        if f is outline_feats[0] or not f.get("geometry"):
            continue
        g = _map_geometry(shape(f["geometry"]), tf)
        if isinstance(g, Polygon):
            rooms.append((str((f.get("properties") or {}).get("name") or ""), g))

    def segments(line) -> list:  # a polyline's consecutive point pairs
        c = np.asarray(line.coords)
        return list(np.stack([c[:-1], c[1:]], axis=1)) if len(c) >= 2 else []

    walls = []
    for f in feats:
        if (f.get("properties") or {}).get("category") == "wall" and (f.get("geometry") or {}).get("type") == "LineString":
            walls.extend(segments(_map_geometry(shape(f["geometry"]), tf)))
    walkable = outline
    if not walls:  # an Indoor Location Competition plan: shops are not walkable, their fronts are walls
        walkable = _footprint_minus(outline, [g for _, g in rooms])
        for poly in walkable.geoms:
            for ring in [poly.exterior, *poly.interiors]:
                walls.extend(segments(ring))
    # the folder's name when it is a floor name: the name the traces inside it go by (_folder_floor)
    name = floor_dir.name if _names_a_floor(floor_dir.name) else str((outline_feats[0].get("properties") or {}).get("name") or floor_dir.name)
    level = floor_level(name)
    return Floor(name, level, level * DEFAULT_STOREY_HEIGHT, outline, walkable, np.asarray(walls).reshape(-1, 2, 2), tuple(rooms)), tf


#: Walkable pieces smaller than this are slivers between adjacent shop outlines (drawing gaps of
#: centimetres), not places a person can stand, m^2.
MIN_WALKABLE_PIECE_M2 = 1.0


def _footprint_minus(outline: MultiPolygon, shops: list[Polygon]) -> MultiPolygon:
    """The footprint minus the shop polygons, as a MultiPolygon without slivers."""
    if not shops:
        return outline
    free = shapely.make_valid(outline.difference(shapely.union_all([shapely.make_valid(s) for s in shops])))
    parts = [g for g in getattr(free, "geoms", [free]) if isinstance(g, Polygon) and g.area >= MIN_WALKABLE_PIECE_M2]
    return MultiPolygon(parts)


def read_ilc_site(site_dir: str | os.PathLike) -> FloorPlan:
    """Read every floor folder of a site (those holding a ``geojson_map.json``) into a FloorPlan."""
    site_dir = Path(site_dir)
    floors, origin = [], None
    for d in sorted(p for p in site_dir.iterdir() if (p / "geojson_map.json").is_file()):
        fl, tf = read_ilc_floor(d)
        floors.append(fl)
        if origin is None or fl.level == 0:
            origin = tf.origin()
    if not floors:
        raise DataFormatError(site_dir, None, "no floor folders with geojson_map.json")
    floors.sort(key=lambda f: f.level)
    return FloorPlan(site_dir.name, tuple(floors), (), origin)


def find_ilc_traces(root: str | os.PathLike) -> list[Path]:
    """All trace files under a site or floor folder (``**/path_data_files/*.txt[.gz]``), sorted.

    Symbolic links to folders are followed (a site assembled from floors kept elsewhere), each real
    folder once, by its own path where a link beside it leads there too (a link cycle ends there):
    ``Path.rglob`` before Python 3.13 skips them silently, and read_ilc_site, which lists the floors,
    follows them."""
    root = Path(root)
    if root.is_file():
        return [root]
    found, seen = [], set()
    for d, dirs, files in os.walk(root, followlinks=True):
        real = os.path.realpath(d)
        if real in seen:
            dirs[:] = []
            continue
        seen.add(real)
        dirs.sort(key=lambda n: (os.path.islink(os.path.join(d, n)), n))  # a folder before a link to it
        here = Path(d)
        if here.name == "path_data_files":
            found += [here / f for f in files if f.endswith((".txt", ".txt.gz")) and (here / f).is_file()]
    return sorted(found)

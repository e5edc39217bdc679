"""Foot-mounted and plain IMU recordings: PyShoe ``.mat``, OpenShoe ``.mat``, MicroStrain SensorConnect
CSV (with the gait-driven set's footprint ``.mat``) and the plain IMU CSV.

Plain IMU CSV
-------------
A header line naming the columns, then one sample per line::

    t,ax,ay,az,gx,gy,gz[,mx,my,mz]

``t`` in seconds, accelerations in m/s^2 (or in g with ``accel_unit="g"``), angular rates in rad/s,
magnetic field in tesla (or uT with ``mag_unit="uT"``). Lines starting with ``#`` are comments.
The file may be gzipped. Rows with a wrong field count, text or NaN are problems (skipped and
reported, or raised); samples out of time order are re-sorted and duplicates dropped, both noted.

Units are checked on the whole file: an accelerometer whose median magnitude is near 1 (not 9.8)
is in g, a gyroscope peaking above 35 rad/s (2000 deg/s, the largest MEMS range) is in deg/s; both
raise :class:`~hybridloc.io.common.DataFormatError` naming the option that fixes it.

SensorConnect CSV
-----------------
What LORD MicroStrain's SensorConnect exports (:func:`read_sensorconnect_csv`): a header ``Time,<node>:<channel>,...``
(``Time`` in s), one sample per line. The unit of each channel is fixed by its MIP channel name, and the
reader converts to SI from the name, then checks the magnitudes agree (a file whose "scaled"
accelerometer already reads 9.8, or a gyro that peaks like deg/s, raises instead of being converted twice):

* ``scaledAccelX/Y/Z``: g (x :data:`~hybridloc.units.G0`); ``scaledGyroX/Y/Z``: rad/s;
  ``scaledMagX/Y/Z``: gauss (x 1e-4 T) - the sensor's calibrated IMU data;
* ``estCompensatedAccelX/Y/Z``: m/s^2; ``estAngularRateX/Y/Z``: rad/s - its estimation filter's
  bias-compensated output, each with a ``:valid`` flag (a sample flagged 0 is a problem, skipped);
* attitude columns (``roll/pitch/yaw``, ``estRoll/...``) are the sensor's own estimate and are not used.

SensorConnect stamps samples with the host's arrival time when the device's own clock is not logged:
samples then come in bunches (intervals of 20 us beside 12 ms around a 5 ms mean). When that happens on
a recording without gaps, the samples are re-spaced evenly over the same span (a noted fix-up).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io

from ..types import ImuBlock, Trajectory
from ..units import DEG, G0, GAUSS_TO_T, UT_TO_T
from .common import DataFormatError, OnError, ReadReport, iter_lines, sort_unique

IMU_CSV_COLUMNS = ("t", "ax", "ay", "az", "gx", "gy", "gz")
IMU_CSV_MAG_COLUMNS = ("mx", "my", "mz")

#: Largest plausible angular rate, rad/s (2000 deg/s is the widest common MEMS range).
MAX_PLAUSIBLE_GYRO = 2000.0 * DEG


def check_imu_units(accel: np.ndarray, gyro: np.ndarray, path: str) -> None:
    """Raise when accelerometer or gyro magnitudes betray wrong units (g instead of m/s^2, deg/s)."""
    if len(accel):
        med = float(np.median(np.linalg.norm(accel, axis=1)))
        if 0.5 < med < 2.0:
            raise DataFormatError(path, None, f"accelerometer median magnitude {med:.2f}: looks like g, not m/s^2 (use the g unit option)")
        if not 3.0 < med < 40.0:
            raise DataFormatError(path, None, f"accelerometer median magnitude {med:.3g} m/s^2 is implausible for a person (expected about 9.8)")
    if len(gyro):
        peak = float(np.max(np.abs(gyro)))
        if peak > MAX_PLAUSIBLE_GYRO * 1.5:
            raise DataFormatError(path, None, f"gyroscope peak {peak:.0f}: looks like deg/s, not rad/s")


@dataclass(frozen=True, eq=False)
class ImuRecording:
    """An IMU file's samples plus whatever ground truth and reference outputs it carries."""

    path: str
    imu: ImuBlock
    truth: Trajectory | None
    report: ReadReport
    extras: dict

    @property
    def rate_hz(self) -> float:
        return self.imu.rate_hz


def _numeric_row(parts: list[str], n_fields: int, cols, extra, lineno: int, report: ReadReport) -> tuple[list[float], list[float]] | None:
    """One CSV record's numbers: (the values of ``cols``, those of ``extra``), or None with the problem
    counted (wrong field count, a field that is no number, a NaN or infinite value in ``cols``)."""
    if len(parts) != n_fields:
        report.problem(lineno, "malformed-line", f"{len(parts)} fields, expected {n_fields}")
        return None
    try:
        vals = [float(parts[k]) for k in cols]
        more = [float(parts[k]) for k in extra]
    except ValueError:
        report.problem(lineno, "malformed-line", "not a number")
        return None
    if not all(math.isfinite(v) for v in vals):
        report.problem(lineno, "non-finite", "NaN or infinity")
        return None
    return vals, more


def read_imu_csv(path: str | os.PathLike, accel_unit: str = "m/s^2", mag_unit: str = "T", on_error: OnError = "skip") -> ImuRecording:
    """Read the plain IMU CSV (see module docstring)."""
    path = str(path)
    if accel_unit not in ("m/s^2", "g"):
        raise ValueError("accel_unit must be 'm/s^2' or 'g'")
    if mag_unit not in ("T", "uT"):
        raise ValueError("mag_unit must be 'T' or 'uT'")
    report = ReadReport(path, on_error)
    header: list[str] | None = None
    rows: list[list[float]] = []
    for lineno, line in iter_lines(path, report):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = [p.strip() for p in s.split(",")]
        if header is None:
            header = [p.lower() for p in parts]
            if tuple(header[:7]) != IMU_CSV_COLUMNS or header[7:] not in ([], list(IMU_CSV_MAG_COLUMNS)):
                raise DataFormatError(path, lineno, f"header must be {','.join(IMU_CSV_COLUMNS)}[,mx,my,mz], got {s[:80]!r}")
            continue
        got = _numeric_row(parts, len(header), range(len(header)), (), lineno, report)
        if got is not None:
            rows.append(got[0])
    if header is None or len(rows) < 2:
        raise DataFormatError(path, None, "no IMU samples")
    a = np.asarray(rows)
    t, (acc, gyr, mag) = sort_unique(a[:, 0], [a[:, 1:4], a[:, 4:7], a[:, 7:10] if a.shape[1] == 10 else np.zeros((len(a), 0))], report, "imu")
    if accel_unit == "g":
        acc = acc * G0
    check_imu_units(acc, gyr, path)
    m = None
    if mag.shape[1] == 3:
        m = mag * (UT_TO_T if mag_unit == "uT" else 1.0)
        med = float(np.median(np.linalg.norm(m, axis=1)))
        if med > 1e-2:
            raise DataFormatError(path, None, f"magnetometer median {med:.3g}: looks like uT, not tesla (use the uT unit option)")
    return ImuRecording(path, ImuBlock(t, acc, gyr, m, path), None, report, {})


def write_imu_csv(path: str | os.PathLike, imu: ImuBlock) -> None:
    """Write the plain IMU CSV (SI units, tesla)."""
    cols = [imu.t[:, None], imu.accel_body, imu.gyro_body] + ([imu.mag_body] if imu.mag_body is not None else [])
    header = ",".join(IMU_CSV_COLUMNS + (IMU_CSV_MAG_COLUMNS if imu.mag_body is not None else ()))
    # time keeps microseconds whatever its magnitude (Unix seconds need 16 digits); the rest 9 digits
    fmt = ["%.6f"] + ["%.9g"] * (sum(c.shape[1] for c in cols) - 1)
    np.savetxt(path, np.hstack(cols), delimiter=",", header=header, comments="", fmt=fmt)


def _loadmat(path: str) -> dict:
    try:
        return scipy.io.loadmat(path)
    except Exception as exc:  # noqa: BLE001 - scipy raises IndexError, MatReadError ... on corrupt files
        raise DataFormatError(path, None, f"not a readable MATLAB file: {exc.__class__.__name__}: {exc}") from exc


def _finite_rows(imu: np.ndarray, report: ReadReport) -> np.ndarray:
    bad = ~np.all(np.isfinite(imu), axis=1)
    for i in np.flatnonzero(bad):
        report.problem(None, "non-finite", f"IMU sample {i} has NaN or infinity")
    return ~bad


def read_pyshoe_mat(path: str | os.PathLike, on_error: OnError = "skip") -> ImuRecording:
    """Read a PyShoe VICON trial (``imu`` N x 6, ``ts`` 1 x N, ``gt`` N x 3, ``trial_error`` ...).

    ``truth`` is the VICON foot position at every IMU sample, converted to a right-handed x-y-up
    frame (the file's x and y swapped; see the comment in the code). ``extras`` keeps ``trial_error``
    (the authors' ARMSE per detector, metres, order shoe, ared, amvd, mbgtd, vicon),
    ``best_detector``, and the ``zv_<detector>_opt`` masks and ``G_<detector>_opt`` thresholds.
    Samples with NaN (in IMU or truth) are problems and dropped.
    """
    path = str(path)
    report = ReadReport(path, on_error)
    m = _loadmat(path)
    for k in ("imu", "ts"):
        if k not in m:
            raise DataFormatError(path, None, f"missing key {k!r}: not a PyShoe trial")
    imu = np.asarray(m["imu"], dtype=float)
    ts = np.asarray(m["ts"], dtype=float).ravel()
    if imu.ndim != 2 or imu.shape[1] != 6 or imu.shape[0] != ts.shape[0]:
        raise DataFormatError(path, None, f"imu shape {imu.shape} does not match ts {ts.shape}")
    gt = np.asarray(m["gt"], dtype=float) if "gt" in m else None
    good = _finite_rows(imu, report) & np.isfinite(ts)
    if gt is not None:
        good &= np.all(np.isfinite(gt), axis=1)
    cols = [imu[good]] + ([gt[good]] if gt is not None else [])
    extras: dict = {}
    for k, v in m.items():
        if k.startswith("zv_") and np.size(v) == len(ts):
            cols.append(np.asarray(v).ravel()[good].astype(bool))
            extras[k] = len(cols) - 1
    t, cols = sort_unique(ts[good], cols, report, "imu")
    for k in list(extras):
        extras[k] = cols[extras[k]]
    imu_s = cols[0]
    check_imu_units(imu_s[:, :3], imu_s[:, 3:], path)
    if "trial_error" in m:
        extras["trial_error"] = np.asarray(m["trial_error"], dtype=float).ravel()
        extras["trial_error_detectors"] = ("shoe", "ared", "amvd", "mbgtd", "vicon")
    if "best_detector" in m:
        extras["best_detector"] = str(np.asarray(m["best_detector"]).ravel()[0]).strip()
    for k, v in m.items():
        if k.startswith("G_") and np.size(v) == 1:
            extras[k] = float(np.asarray(v).ravel()[0])
    # PyShoe's VICON positions match the output of its NED navigator with z negated, i.e. they are
    # (north, east, up): a mirror image of ENU. Swapping x and y makes the truth right-handed ENU
    # (up to a rotation about the vertical, which every evaluation aligns anyway).
    truth = Trajectory(t, cols[1][:, [1, 0, 2]]) if gt is not None else None
    return ImuRecording(path, ImuBlock(t, imu_s[:, :3], imu_s[:, 3:], None, path), truth, report, extras)


def read_openshoe_mat(path: str | os.PathLike, rate_hz: float = 100.0, on_error: OnError = "skip") -> ImuRecording:
    """Read an OpenShoe example (``u``: 6 x N, accel m/s^2 then gyro rad/s; no timestamps).

    OpenShoe files carry no time, so ``t = i / rate_hz`` (OpenShoe units log at 100 Hz by default;
    pass the true rate when it differs). No ground truth.
    """
    path = str(path)
    if not rate_hz > 0:
        raise ValueError("rate_hz must be positive")
    report = ReadReport(path, on_error)
    m = _loadmat(path)
    if "u" not in m:
        raise DataFormatError(path, None, "missing key 'u': not an OpenShoe recording")
    u = np.asarray(m["u"], dtype=float)
    if u.ndim != 2 or 6 not in u.shape:
        raise DataFormatError(path, None, f"u has shape {u.shape}, expected 6 x N")
    if u.shape[0] != 6:
        u = u.T
    u = u.T  # N x 6
    good = _finite_rows(u, report)
    t = np.arange(len(u))[good] / rate_hz
    u = u[good]
    check_imu_units(u[:, :3], u[:, 3:], path)
    return ImuRecording(path, ImuBlock(t, u[:, :3], u[:, 3:], None, path), None, report, {"rate_hz": rate_hz})


# ------------------------------------------------------------------ MicroStrain SensorConnect CSV
#: SensorConnect (MIP) channel families: name stem -> (accel stem, gyro stem, mag stem or None, accel unit
#: factor to m/s^2, whether each channel has a ``:valid`` flag column).
SENSORCONNECT_FAMILIES = {
    "scaled": ("scaledAccel", "scaledGyro", "scaledMag", G0, False),
    "estimated": ("estCompensatedAccel", "estAngularRate", None, 1.0, True),
}

#: A SensorConnect time stamp interval shorter than this share of the mean interval is a bunched
#: (host arrival) stamp; when more than :data:`BUNCHED_SHARE` of the intervals are, the file is re-timed.
BUNCHED_INTERVAL = 0.25
BUNCHED_SHARE = 0.05


def is_sensorconnect_header(line: str) -> bool:
    cols = [c.strip() for c in line.split(",")]
    return bool(cols) and cols[0] == "Time" and any(c.endswith((":scaledAccelX", ":estCompensatedAccelX")) for c in cols[1:])


def _sensorconnect_columns(path: str, header: list[str]) -> tuple[str, list[int], list[int], list[int] | None, list[int], float]:
    """(family, accel, gyro, mag or None, valid-flag column indices, accel factor) from the header."""
    chan = {}
    for i, c in enumerate(header):
        name = c.split(":", 1)[1] if ":" in c else c
        chan[name] = i
    for fam, (acc, gyr, mag, factor, has_valid) in SENSORCONNECT_FAMILIES.items():
        need = [f"{acc}{a}" for a in "XYZ"] + [f"{gyr}{a}" for a in "XYZ"]
        if not all(n in chan for n in need):
            continue
        ia = [chan[f"{acc}{a}"] for a in "XYZ"]
        ig = [chan[f"{gyr}{a}"] for a in "XYZ"]
        im = [chan[f"{mag}{a}"] for a in "XYZ"] if mag and all(f"{mag}{a}" in chan for a in "XYZ") else None
        iv = [chan[f"{n}:valid"] for n in need if f"{n}:valid" in chan] if has_valid else []
        return fam, ia, ig, im, iv, factor
    raise DataFormatError(
        path,
        1,
        "SensorConnect header without a full accelerometer + gyroscope triple (scaledAccelX/Y/Z + scaledGyroX/Y/Z, or estCompensatedAccelX/Y/Z + estAngularRateX/Y/Z)",
    )


def read_sensorconnect_csv(path: str | os.PathLike, on_error: OnError = "skip") -> ImuRecording:
    """Read a MicroStrain SensorConnect CSV export (see the module docstring): SI units from the channel
    names, checked against the magnitudes; ``extras['family']`` says which channels were used
    (``scaled`` or ``estimated``), ``extras['retimed']`` whether bunched stamps were re-spaced."""
    path = str(path)
    report = ReadReport(path, on_error)
    header: list[str] | None = None
    rows: list[list[float]] = []
    for lineno, line in iter_lines(path, report):
        s = line.strip()
        if not s:
            continue
        parts = [p.strip() for p in s.split(",")]
        if header is None:
            if not is_sensorconnect_header(s):
                raise DataFormatError(path, lineno, f"not a SensorConnect export: header {s[:80]!r}")
            header = parts
            fam, ia, ig, im, iv, factor = _sensorconnect_columns(path, header)
            used = [0] + ia + ig + (im or [])
            continue
        got = _numeric_row(parts, len(header), used, iv, lineno, report)
        if got is None:
            continue
        vals, flags = got
        if any(f != 1.0 for f in flags):
            report.problem(lineno, "invalid-sample", "a channel's valid flag is 0")
            continue
        rows.append(vals)
    if header is None or len(rows) < 2:
        raise DataFormatError(path, None, "no IMU samples")
    a = np.asarray(rows)
    t, (acc, gyr, mag) = sort_unique(a[:, 0], [a[:, 1:4], a[:, 4:7], a[:, 7:10] if im else np.zeros((len(a), 0))], report, "imu")
    if len(t) < 2:
        raise DataFormatError(path, None, "fewer than two IMU samples with distinct times")
    med = float(np.median(np.linalg.norm(acc, axis=1)))
    acc_name = SENSORCONNECT_FAMILIES[fam][0]
    if factor != 1.0 and not 0.5 < med < 2.0:
        raise DataFormatError(
            path, None, f"{acc_name} median magnitude {med:.3g}: SensorConnect writes it in g (about 1), this file is in other units"
        )
    if factor == 1.0 and 0.5 < med < 2.0:
        raise DataFormatError(
            path, None, f"{acc_name} median magnitude {med:.3g}: SensorConnect writes it in m/s^2 (about 9.8), this file looks like g"
        )
    acc = acc * factor
    check_imu_units(acc, gyr, path)
    m = None
    if im:
        m = mag * GAUSS_TO_T
        med_b = float(np.median(np.linalg.norm(m, axis=1)))
        if not 1e-6 < med_b < 2e-4:  # the Earth's field is 25-65 uT; indoors 10-150
            raise DataFormatError(path, None, f"scaledMag median {med_b / GAUSS_TO_T:.3g}: not gauss (the Earth's field is 0.25-0.65 gauss)")
    t, retimed = _respace_bunched(t, report)
    return ImuRecording(path, ImuBlock(t, acc, gyr, m, path), None, report, {"family": fam, "retimed": retimed})


def _respace_bunched(t: np.ndarray, report: ReadReport) -> tuple[np.ndarray, bool]:
    """Host arrival stamps (module docstring): evenly re-spaced when bunched and free of gaps."""
    dt = np.diff(t)
    mean = float(t[-1] - t[0]) / (len(t) - 1)
    short = int(np.sum(dt < BUNCHED_INTERVAL * mean))
    if short <= BUNCHED_SHARE * len(dt):
        return t, False
    if float(dt.max()) > 5.0 * mean:
        report.problem(
            None, "bunched-timestamps", f"{short} of {len(dt)} sample intervals under {BUNCHED_INTERVAL:g} of the mean, and gaps: kept as stamped"
        )
        return t, False
    report.note(
        "retimed",
        len(t),
        f"{short} of {len(dt)} intervals under {BUNCHED_INTERVAL:g} of the mean {mean * 1e3:.2f} ms: host arrival stamps, re-spaced evenly",
    )
    return t[0] + mean * np.arange(len(t)), True


@dataclass(frozen=True, eq=False)
class Footprints:
    """Measured footprints of a walk (the gait-driven set's ``SensorConnectData_NN.mat``).

    ``pos_xy`` (K, 2): the foot's position in metres after stride ``stride[k]`` (stride 0 = the start),
    measured on the floor tiles (``tile_edge_m`` each); ``n_strides`` the strides walked; ``valid``
    the file's ``GCP_exist_and_correct``; ``experiment`` its ``expID``.
    """

    path: str
    pos_xy: np.ndarray
    stride: np.ndarray
    n_strides: int
    valid: bool
    experiment: int
    tile_edge_m: float

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.pos_xy, axis=0), axis=1).sum())


FOOTPRINT_KEYS = ("GCP_meters", "GCP_stride_numbers", "numberOfStrides")


def read_footprints_mat(path: str | os.PathLike) -> Footprints:
    """Read a footprint truth file (:class:`Footprints`); missing keys or inconsistent sizes raise."""
    path = str(path)
    m = _loadmat(path)
    missing = [k for k in FOOTPRINT_KEYS if k not in m]
    if missing:
        raise DataFormatError(path, None, f"missing key(s) {missing}: not a gait-driven footprint file")
    xy = np.asarray(m["GCP_meters"], dtype=float)
    k = np.asarray(m["GCP_stride_numbers"]).ravel().astype(int)
    n = int(np.asarray(m["numberOfStrides"]).ravel()[0])
    if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] != k.shape[0] or not np.all(np.isfinite(xy)):
        raise DataFormatError(path, None, f"GCP_meters {xy.shape} does not match GCP_stride_numbers {k.shape}, or holds NaN")
    if len(k) < 2 or k[0] != 0 or np.any(np.diff(k) <= 0) or k[-1] > n:
        raise DataFormatError(path, None, f"GCP_stride_numbers must rise from 0 (the start) to at most numberOfStrides={n}")
    valid = bool(np.asarray(m.get("GCP_exist_and_correct", [[1]])).ravel()[0])
    exp = int(np.asarray(m.get("expID", [[-1]])).ravel()[0])
    edge = float(np.asarray(m.get("tile_edge_length", [[float("nan")]])).ravel()[0])
    return Footprints(path, xy - xy[0], k, n, valid, exp, edge)


def footprints_beside(path: str | os.PathLike) -> Footprints | None:
    """The footprint file beside a SensorConnect CSV (``X.csv[.gz]`` -> ``X.mat``), None when absent."""
    p = Path(path)
    name = p.name
    for ext in (".gz", ".csv"):
        if name.lower().endswith(ext):
            name = name[: -len(ext)]
    mat = p.with_name(name + ".mat")
    return read_footprints_mat(mat) if mat.is_file() else None

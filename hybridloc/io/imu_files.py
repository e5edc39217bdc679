"""Foot-mounted and plain IMU recordings: PyShoe ``.mat``, OpenShoe ``.mat`` and the plain IMU CSV.

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
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import scipy.io

from ..types import ImuBlock, Trajectory
from ..units import DEG, G0, UT_TO_T
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
        if len(parts) != len(header):
            report.problem(lineno, "malformed-line", f"{len(parts)} fields, expected {len(header)}")
            continue
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            report.problem(lineno, "malformed-line", "not a number")
            continue
        if not all(math.isfinite(v) for v in vals):
            report.problem(lineno, "non-finite", "NaN or infinity")
            continue
        rows.append(vals)
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

"""What a recording holds: the logic behind ``hybridloc data inspect``.

:func:`inspect_file` reads any supported file and returns a :class:`FileSummary` (no printing);
:meth:`FileSummary.render` formats it for people.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

from .io import detect_format
from .io.common import ReadReport
from .types import ImuBlock

#: A sample interval longer than this many median intervals is reported as a gap.
GAP_FACTOR = 5.0


@dataclass
class FileSummary:
    path: str
    format: str
    duration_s: float = float("nan")
    lines: list[tuple[str, str]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    def render(self) -> str:
        out = [f"{self.path}", f"  format      {self.format}", f"  duration    {self.duration_s:.1f} s"]
        out += [f"  {k:<11} {v}" for k, v in self.lines]
        if self.problems:
            out.append("  problems:")
            out += [f"    - {p}" for p in self.problems]
        else:
            out.append("  problems    none found")
        return "\n".join(out)


def imu_gaps(t: np.ndarray, factor: float = GAP_FACTOR) -> list[tuple[float, float]]:
    """(start time, length) of every sample interval longer than ``factor`` median intervals."""
    if len(t) < 3:
        return []
    dt = np.diff(t)
    med = float(np.median(dt))
    idx = np.flatnonzero(dt > factor * med)
    return [(float(t[i]), float(dt[i])) for i in idx]


def _imu_lines(s: FileSummary, imu: ImuBlock) -> None:
    s.duration_s = imu.duration
    sensors = "accel, gyro" + (", mag" if imu.mag_body is not None else "")
    s.lines.append(("imu", f"{len(imu)} samples at {imu.rate_hz:.1f} Hz ({sensors})"))
    gaps = imu_gaps(imu.t)
    if gaps:
        worst = max(g[1] for g in gaps)
        s.problems.append(f"{len(gaps)} gaps in the IMU stream (longest {worst:.3f} s, at t={max(gaps, key=lambda g: g[1])[0]:.3f})")
        s.lines.append(("gaps", f"{len(gaps)} (longest {worst:.3f} s)"))
    else:
        s.lines.append(("gaps", "none"))
    acc_n = np.linalg.norm(imu.accel_body, axis=1)
    s.lines.append(("accel |a|", f"median {np.median(acc_n):.2f} m/s^2, max {acc_n.max():.1f}"))
    gyr_n = np.linalg.norm(imu.gyro_body, axis=1)
    s.lines.append(("gyro |w|", f"median {np.median(gyr_n):.3f} rad/s, max {gyr_n.max():.2f}"))
    if imu.mag_body is not None:
        m = np.linalg.norm(imu.mag_body, axis=1) * 1e6
        s.lines.append(("mag |B|", f"median {np.median(m):.1f} uT (range {m.min():.1f}-{m.max():.1f})"))


def _footprint_text(fp) -> str:
    return (
        f"{len(fp.stride)} measured (experiment {fp.experiment}), {fp.n_strides} strides walked, {fp.distance_m:.1f} m between footprints, "
        f"end {np.hypot(*fp.pos_xy[-1]):.2f} m from the start; tiles {fp.tile_edge_m:.3f} m (ground truth)"
    )


def _report_lines(s: FileSummary, report: ReadReport) -> None:
    if report.notes:
        s.lines.append(("fix-ups", ", ".join(f"{k} x{n}" for k, n in sorted(report.notes.items()))))
    for kind, n in sorted(report.counts.items()):
        s.problems.append(f"{kind}: {n} (skipped)")
    for issue in report.issues[:5]:
        s.problems.append(f"  e.g. line {issue.line}: {issue.reason}" if issue.line is not None else f"  e.g. {issue.reason}")


def inspect_file(path: str | os.PathLike, fmt: str | None = None, rate_hz: float | None = None) -> FileSummary:
    """Read ``path`` (format detected unless given) and summarise it."""
    path = str(path)
    fmt = fmt or detect_format(path)
    s = FileSummary(path, fmt)
    if fmt == "msft":
        from .io.msft import read_ilc_trace

        tr = read_ilc_trace(path)
        site = tr.meta.get("SiteName") or tr.meta.get("SiteID") or "?"
        s.lines.append(("site/floor", f"{site} / {tr.floor or '?'}  device {tr.device_model or '?'}"))
        if tr.imu is not None:
            _imu_lines(s, tr.imu)
        else:
            s.problems.append("no usable IMU data")
        wifi = tr.wifi_scans
        ble = [x for x in tr.scans if x.technology.value == "ble"]
        if wifi:
            ts = np.array([x.t for x in wifi])
            aps = {k for x in wifi for k in x.rssi_dbm}
            per = np.median([len(x) for x in wifi])
            period = f", every {np.median(np.diff(ts)):.2f} s" if len(ts) > 1 else ""
            ages = np.concatenate([list(x.age_s.values()) for x in wifi])
            s.lines.append(
                ("wifi", f"{len(wifi)} scans{period}, {len(aps)} APs, median {per:.0f} APs/scan, median reading age {np.median(ages):.1f} s")
            )
        else:
            s.lines.append(("wifi", "none"))
        s.lines.append(("ble", f"{len(ble)} observations, {len({k for x in ble for k in x.rssi_dbm})} beacons" if ble else "none"))
        wp = tr.waypoints
        s.lines.append(
            (
                "waypoints",
                f"{len(wp)} (ground truth)"
                + (f", {np.linalg.norm(np.diff(wp.pos_enu, axis=0), axis=1).sum():.1f} m between marks" if len(wp) > 1 else ""),
            )
        )
        if len(wp) < 2:
            s.problems.append("fewer than two waypoints: cannot be scored")
        if tr.imu is None and not tr.scans:
            s.duration_s = float("nan")
        _report_lines(s, tr.report)
    elif fmt == "footprints":
        from .io.imu_files import read_footprints_mat

        fp = read_footprints_mat(path)
        s.lines.append(("footprints", _footprint_text(fp)))
        if not fp.valid:
            s.problems.append("GCP_exist_and_correct is 0: the footprints are marked missing or wrong")
    elif fmt in ("pyshoe", "openshoe", "csv", "sensorconnect"):
        from .io.imu_files import footprints_beside, read_imu_csv, read_openshoe_mat, read_pyshoe_mat, read_sensorconnect_csv

        if fmt == "sensorconnect":
            rec = read_sensorconnect_csv(path)
        elif fmt == "pyshoe":
            rec = read_pyshoe_mat(path)
        elif fmt == "openshoe":
            rec = read_openshoe_mat(path, rate_hz or 100.0)
        else:
            rec = read_imu_csv(path)
        _imu_lines(s, rec.imu)
        if fmt == "sensorconnect":
            fam = rec.extras["family"]
            s.lines.append(
                (
                    "channels",
                    ("scaledAccel (g -> m/s^2), scaledGyro (rad/s)" + (", scaledMag (gauss -> T)" if rec.imu.mag_body is not None else ""))
                    if fam == "scaled"
                    else "estCompensatedAccel (m/s^2), estAngularRate (rad/s): the sensor filter's compensated output",
                )
            )
            if rec.extras["retimed"]:
                s.lines.append(("time", "host arrival stamps in bunches: re-spaced evenly over the recording"))
            fp = footprints_beside(path)
            s.lines.append(("footprints", _footprint_text(fp) if fp is not None else "none beside it (no .mat of the same name)"))
        if rec.truth is not None:
            s.lines.append(("truth", f"{len(rec.truth)} positions, {rec.truth.distance_travelled:.1f} m travelled"))
        if "trial_error" in rec.extras:
            te = rec.extras["trial_error"]
            s.lines.append(
                (
                    "authors",
                    "ARMSE "
                    + ", ".join(f"{d}={e:.3f} m" for d, e in zip(rec.extras["trial_error_detectors"], te))
                    + f"; best {rec.extras.get('best_detector', '?')}",
                )
            )
        _report_lines(s, rec.report)
    elif fmt == "ujiindoorloc":
        from .io.uji import read_uji

        d = read_uji(path)
        s.duration_s = float(d.t.max() - d.t.min())
        det = np.isfinite(d.rssi_dbm)
        s.lines.append(("rows", f"{len(d)} fingerprints, {len(d.waps)} WAP columns, {int(det.any(0).sum())} ever detected"))
        s.lines.append(("per row", f"median {np.median(det.sum(1)):.0f} APs detected; {int((det.sum(1) == 0).sum())} rows with none"))
        s.lines.append(
            ("buildings", ", ".join(f"{b}: floors {sorted(set(d.floor[d.building == b].tolist()))}" for b in sorted(set(d.building.tolist()))))
        )
        s.lines.append(("users/phones", f"{len(set(d.user.tolist()))} users, {len(set(d.phone.tolist()))} phones"))
        if (det.sum(1) == 0).any():
            s.problems.append(f"{int((det.sum(1) == 0).sum())} rows detect no access point (cannot be located)")
        _report_lines(s, d.report)
    else:
        raise ValueError(f"unknown format {fmt!r}")
    return s

"""Helpers shared by the command modules: recordings to IMU data, calibration files, number lists, security options."""

from __future__ import annotations

import argparse
from pathlib import Path

#: step length models of ``pdr phone --model`` and ``eval pdr-phone --model`` (hybridloc.pdr.steplength.MODELS)
LENGTH_MODELS = ("constant", "weinberg", "frequency", "kim", "height")


def load_imu(path: str, fmt: str | None, rate: float | None, accel_unit: str = "m/s^2"):
    """(imu, read report, device model, waypoints or None) of a recording."""
    from ..io import detect_format

    fmt = fmt or detect_format(path)
    if fmt == "msft":
        from ..io.msft import read_ilc_trace

        tr = read_ilc_trace(path)
        if tr.imu is None:
            raise ValueError(f"{path}: no usable IMU data ({tr.report.summary()})")
        return tr.imu, tr.report, tr.device_model, tr.waypoints
    from ..io.imu_files import read_imu_csv, read_openshoe_mat, read_pyshoe_mat

    if fmt == "csv":
        rec = read_imu_csv(path, accel_unit=accel_unit)
    elif fmt == "pyshoe":
        rec = read_pyshoe_mat(path)
    elif fmt == "openshoe":
        rec = read_openshoe_mat(path, rate or 100.0)
    else:
        raise ValueError(f"{path}: format {fmt} holds no IMU data")
    return rec.imu, rec.report, "", None


def open_calibration(path: str | None, update: bool, model_name: str):
    """(calibrator, path) of --calibration FILE, created from ``model_name`` when absent and
    ``update`` (--update-calibration) asks for it; (None, None) without a file."""
    from ..pdr import LengthCalibrator, make_model

    if path is None:
        if update:
            raise ValueError("--update-calibration needs --calibration FILE (the device's calibration; created when absent)")
        return None, None
    p = Path(path)
    if p.is_file():
        return LengthCalibrator.load(p), p
    if not update:
        raise ValueError(f"calibration {p} not found (add --update-calibration to create it)")
    return LengthCalibrator(make_model(model_name)), p


def security(args: argparse.Namespace):
    from ..wire.zconfig import Security

    devices = []
    if getattr(args, "acl_devices", None):
        devices = [ln.split(":")[0].strip() for ln in Path(args.acl_devices).read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return Security(users_file=getattr(args, "users", None), user=getattr(args, "user", None), password=getattr(args, "password", None),
                    tls_cert=getattr(args, "tls_cert", None), tls_key=getattr(args, "tls_key", None), tls_ca=getattr(args, "tls_ca", None),
                    acl_devices=devices)


def parse_floats(text: str, n: int, what: str) -> tuple[float, ...]:
    import math

    try:
        vals = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise ValueError(f"{what} expected, got {text!r}") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{what} expected ({n} finite numbers), got {text!r}")
    return vals


def stem_safe(path: str) -> str:
    import re

    from ..io.common import stem_of

    return re.sub(r"[^A-Za-z0-9_.-]", "_", stem_of(path))[:40]

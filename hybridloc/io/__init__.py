"""Readers and writers for real recording formats, and format detection.

Formats: Indoor Location Competition traces (:mod:`.msft`), PyShoe / OpenShoe ``.mat``, MicroStrain
SensorConnect CSV with the gait-driven set's footprint ``.mat``, and the plain IMU CSV (:mod:`.imu_files`), UJIIndoorLoc CSV (:mod:`.uji`); writers for trajectory CSV, GeoJSON and
NMEA-0183 (:mod:`.writers`). The bad-input policy shared by every reader is in :mod:`.common`.
"""

from __future__ import annotations

import os
from pathlib import Path

import scipy.io

from .common import DataFormatError, ReadIssue, ReadReport, open_binary, stem_of

FORMATS = ("msft", "pyshoe", "openshoe", "csv", "ujiindoorloc", "sensorconnect", "footprints")


def detect_format(path: str | os.PathLike) -> str:
    """Guess a file's format from its content (gzip is looked through): one of :data:`FORMATS`.

    Raises :class:`DataFormatError` when the content matches none.
    """
    path = str(path)
    if not Path(path).is_file():
        raise DataFormatError(path, None, "no such file")
    with open(path, "rb") as f:
        magic = f.read(128)
    if magic.startswith(b"MATLAB") or path.lower().endswith(".mat"):
        try:
            keys = {w[0] for w in scipy.io.whosmat(path)}
        except Exception as exc:  # noqa: BLE001 - scipy raises IndexError, MatReadError ... on corrupt files
            raise DataFormatError(path, None, f"not a readable MATLAB file: {exc.__class__.__name__}: {exc}") from exc
        if {"imu", "ts"} <= keys:
            return "pyshoe"
        if "u" in keys:
            return "openshoe"
        if {"GCP_meters", "GCP_stride_numbers"} <= keys:
            return "footprints"
        raise DataFormatError(path, None, f"MATLAB file with keys {sorted(keys)}: neither PyShoe (imu, ts), OpenShoe (u) nor footprints (GCP_meters)")
    try:
        with open_binary(path) as f:
            head = f.read(4096).decode("utf-8", errors="replace")
    except (EOFError, OSError) as exc:
        raise DataFormatError(path, None, f"unreadable: {exc}") from exc
    lines = [ln for ln in head.splitlines() if ln.strip()]
    first = lines[0] if lines else ""
    if first.upper().lstrip('"').startswith("WAP001"):
        return "ujiindoorloc"
    if "\tTYPE_" in head or first.startswith("#\tstartTime") or first.startswith("#\tSiteID"):
        return "msft"
    from .imu_files import is_sensorconnect_header

    if is_sensorconnect_header(first):
        return "sensorconnect"
    data_lines = [ln for ln in lines if not ln.startswith("#")]
    if data_lines and data_lines[0].replace(" ", "").lower().startswith("t,ax,ay,az,gx,gy,gz"):
        return "csv"
    raise DataFormatError(path, 1, f"unknown format (first line {first[:60]!r}); expected one of {', '.join(FORMATS)}")


__all__ = ["DataFormatError", "ReadIssue", "ReadReport", "detect_format", "stem_of", "FORMATS"]

"""Absolute fixes as CSV: ``t,x,y,floor,sigma,source[,sigma_random]``.

What the simulator writes beside every walk (``w<NNNN>_fixes.csv``: GPS and RFID), and what a GPS
logger or an RFID reader log converted to the site frame looks like: time (s, the recording's clock),
position in the site frame (m), floor name (may be empty), the per-axis standard deviation (m), the
source (``gps``, ``rfid``, ``wifi``, ``ble``), and for GPS optionally the standard deviation of the
fix's random part only (Kourogi eq 8: the biased part cancels when two fixes are differenced), which
the GPS differential mode needs. Bad rows are reported (skipped by default, or raised).
"""

from __future__ import annotations

import math
import os

from ..types import AbsoluteFix, FixSource
from .common import DataFormatError, OnError, ReadReport, iter_lines


def read_fixes_csv(path: str | os.PathLike, on_error: OnError = "skip") -> tuple[list[tuple[AbsoluteFix, float | None]], ReadReport]:
    """[(fix, sigma_random or None)] sorted by time, and the read report."""
    path = str(path)
    report = ReadReport(path, on_error)
    out: list[tuple[AbsoluteFix, float | None]] = []
    header = None
    for lineno, line in iter_lines(path, report):
        if not line.strip() or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.rstrip("\n").split(",")]
        if header is None:
            header = parts
            missing = {"t", "x", "y", "floor", "sigma", "source"} - set(header)
            if missing:
                raise DataFormatError(f"{path}: not a fixes CSV (missing columns {sorted(missing)})")
            continue
        try:
            row = dict(zip(header, parts))
            if len(parts) != len(header):
                raise ValueError(f"{len(parts)} fields, {len(header)} expected")
            t, x, y, sg = float(row["t"]), float(row["x"]), float(row["y"]), float(row["sigma"])
            if not all(math.isfinite(v) for v in (t, x, y, sg)) or sg <= 0:
                raise ValueError("non-finite value or non-positive sigma")
            src = FixSource(row["source"].lower())
            sr = float(row["sigma_random"]) if row.get("sigma_random") else None
            if sr is not None and not (math.isfinite(sr) and 0 < sr <= sg):
                raise ValueError("sigma_random must be in (0, sigma]")
            out.append((AbsoluteFix(t, [x, y], [[sg * sg, 0.0], [0.0, sg * sg]], src, row["floor"] or None), sr))
        except (ValueError, KeyError) as exc:
            report.problem(lineno, "bad-row", str(exc))
    out.sort(key=lambda a: a[0].t)
    return out, report

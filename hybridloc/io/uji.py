"""UJIIndoorLoc WiFi fingerprint database (Torres-Sospedra et al., IPIN 2014).

CSV with a header: ``WAP001..WAP520`` (RSSI dBm; **100 means "not detected"**), ``LONGITUDE``,
``LATITUDE`` (metres, EPSG:3857 projected), ``FLOOR``, ``BUILDINGID``, ``SPACEID``,
``RELATIVEPOSITION``, ``USERID``, ``PHONEID``, ``TIMESTAMP`` (Unix s). Plain or gzipped.

The reader streams rows (:func:`iter_uji_rows`) or loads the whole file into arrays
(:func:`read_uji`), where undetected access points are NaN. Rows with a wrong field count, text in
numeric columns or RSSI outside [-130, 0] dBm (other than the 100 sentinel) are problems: skipped
and reported, or raised.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ..types import RSSI_MAX_DBM, RSSI_MIN_DBM, RfScan, Technology, rssi_in_range
from .common import DataFormatError, OnError, ReadReport, iter_lines

NOT_DETECTED = 100.0
META_COLUMNS = ("LONGITUDE", "LATITUDE", "FLOOR", "BUILDINGID", "SPACEID", "RELATIVEPOSITION", "USERID", "PHONEID", "TIMESTAMP")


@dataclass(frozen=True, eq=False)
class UjiData:
    """The whole file as arrays.

    Attributes
    ----------
    waps : tuple of str
        Access point column names, length M.
    rssi_dbm : ndarray, shape (N, M)
        RSSI, dBm; NaN where not detected.
    pos : ndarray, shape (N, 2)
        (x, y), metres, EPSG:3857 (x = LONGITUDE column, y = LATITUDE column).
    floor, building, space, relpos, user, phone : ndarray of int, shape (N,)
    t : ndarray, shape (N,)
        Unix seconds.
    lines : ndarray of int, shape (N,)
        Source line of each row (for messages).
    report : ReadReport
    """

    path: str
    waps: tuple[str, ...]
    rssi_dbm: np.ndarray
    pos: np.ndarray
    floor: np.ndarray
    building: np.ndarray
    space: np.ndarray
    relpos: np.ndarray
    user: np.ndarray
    phone: np.ndarray
    t: np.ndarray
    lines: np.ndarray
    report: ReadReport

    def __len__(self) -> int:
        return int(self.rssi_dbm.shape[0])

    def scan(self, i: int) -> RfScan:
        """Row i as an :class:`RfScan` (undetected access points left out)."""
        row = self.rssi_dbm[i]
        ok = np.isfinite(row)
        return RfScan(
            float(self.t[i]),
            Technology.WIFI,
            {self.waps[j]: float(row[j]) for j in np.flatnonzero(ok)},
            device_model=f"uji-phone-{int(self.phone[i])}",
        )


def iter_uji_rows(path: str | os.PathLike, report: ReadReport) -> Iterator[tuple[int, list[str], np.ndarray, np.ndarray]]:
    """Stream ``(line, wap_names, rssi_row, meta_row)``; rssi has NaN for "not detected"."""
    header: list[str] | None = None
    n_wap = 0
    for lineno, line in iter_lines(path, report):
        if not line.strip():
            continue
        parts = line.split(",")
        if header is None:
            header = [p.strip().strip('"') for p in parts]
            n_wap = sum(1 for h in header if h.upper().startswith("WAP"))
            if n_wap == 0 or tuple(h.upper() for h in header[n_wap:]) != META_COLUMNS:
                raise DataFormatError(path, lineno, "not a UJIIndoorLoc file: header must be WAPnnn columns then " + ",".join(META_COLUMNS))
            continue
        if len(parts) != len(header):
            report.problem(lineno, "malformed-line", f"{len(parts)} fields, expected {len(header)}")
            continue
        try:
            vals = np.array([float(p) for p in parts])
        except ValueError:
            report.problem(lineno, "malformed-line", "not a number")
            continue
        if not np.all(np.isfinite(vals)):
            report.problem(lineno, "non-finite", "NaN or infinity")
            continue
        rssi = vals[:n_wap]
        bad = (rssi != NOT_DETECTED) & ~rssi_in_range(rssi)
        if bad.any():
            report.problem(
                lineno, "rssi-out-of-range", f"{int(bad.sum())} values outside [{RSSI_MIN_DBM}, {RSSI_MAX_DBM}] dBm and not {NOT_DETECTED:g}"
            )
            continue
        rssi = np.where(rssi == NOT_DETECTED, np.nan, rssi)
        yield lineno, header[:n_wap], rssi, vals[n_wap:]


def read_uji(path: str | os.PathLike, on_error: OnError = "skip") -> UjiData:
    path = str(path)
    report = ReadReport(path, on_error)
    waps: list[str] = []
    rssi, meta, lines = [], [], []
    for lineno, names, r, m in iter_uji_rows(path, report):
        waps = names
        rssi.append(r)
        meta.append(m)
        lines.append(lineno)
    if not rssi:
        raise DataFormatError(path, None, "no rows")
    R = np.vstack(rssi)
    M = np.vstack(meta)
    i = lambda k: M[:, META_COLUMNS.index(k)].astype(int)  # noqa: E731
    return UjiData(
        path,
        tuple(waps),
        R,
        M[:, 0:2].copy(),
        i("FLOOR"),
        i("BUILDINGID"),
        i("SPACEID"),
        i("RELATIVEPOSITION"),
        i("USERID"),
        i("PHONEID"),
        M[:, META_COLUMNS.index("TIMESTAMP")].astype(float),
        np.asarray(lines),
        report,
    )


def is_uji_header(first_line: str) -> bool:
    return first_line.upper().startswith("WAP001") or first_line.upper().startswith('"WAP001')

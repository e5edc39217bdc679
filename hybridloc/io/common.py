"""Shared reader machinery: transparent gzip, line streaming, and problem reports.

Every reader follows one policy for bad input, chosen by ``on_error``:

* ``"skip"`` (default): the bad record is dropped and a :class:`ReadIssue` (file, line, reason) is
  added to the :class:`ReadReport` returned with the data. Nothing silently wrong is returned: a
  record is either parsed completely and checked, or dropped and reported.
* ``"raise"``: the first problem raises :class:`DataFormatError` with file, line and reason.

Problems that make the whole file meaningless (wrong units, no data at all, unknown format) raise
:class:`DataFormatError` whatever ``on_error`` says.
"""

from __future__ import annotations

import gzip
import os
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ..errors import DataFormatError  # noqa: F401  (defined with the other errors; imported from here too)

OnError = Literal["skip", "raise"]

#: The largest number of individual issues kept per report (counts by reason are always complete).
MAX_KEPT_ISSUES = 200


@dataclass(frozen=True)
class ReadIssue:
    path: str
    line: int | None
    reason: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.reason}" if self.line is not None else f"{self.path}: {self.reason}"


@dataclass
class ReadReport:
    """What a reader met besides good data.

    ``counts`` / ``issues``: problems (bad records skipped), complete counts by kind and the first
    few individual issues. ``notes`` / ``note_details``: benign, documented fix-ups (re-sorted samples,
    duplicate readings merged, known record types not used), which never raise.
    """

    path: str
    on_error: OnError = "skip"
    issues: list[ReadIssue] = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)
    notes: Counter = field(default_factory=Counter)
    note_details: list[str] = field(default_factory=list)

    def problem(self, line: int | None, kind: str, detail: str = "") -> None:
        """Record a problem of a given kind (a short stable key, e.g. ``"bad-number"``)."""
        reason = f"{kind}: {detail}" if detail else kind
        if self.on_error == "raise":
            raise DataFormatError(self.path, line, reason)
        self.counts[kind] += 1
        if len(self.issues) < MAX_KEPT_ISSUES:
            self.issues.append(ReadIssue(self.path, line, reason))

    def note(self, kind: str, n: int = 1, detail: str = "") -> None:
        """Record a benign, documented fix-up (e.g. samples re-sorted); never raises."""
        if n <= 0:
            return
        self.notes[kind] += n
        if detail and len(self.note_details) < MAX_KEPT_ISSUES:
            self.note_details.append(f"{kind}: {detail}")

    @property
    def ok(self) -> bool:
        return not self.counts

    def summary(self) -> str:
        if not self.counts:
            return "no problems"
        return ", ".join(f"{k} x{v}" for k, v in sorted(self.counts.items()))


def is_gzip(path: str | os.PathLike) -> bool:
    with open(path, "rb") as f:
        return f.read(2) == b"\x1f\x8b"


def open_binary(path: str | os.PathLike):
    """Open a file for binary reading, decompressing gzip transparently (by magic bytes, not name)."""
    if is_gzip(path):
        return gzip.open(path, "rb")
    return open(path, "rb")


def iter_lines(path: str | os.PathLike, report: ReadReport, encoding: str = "utf-8", keep=None) -> Iterator[tuple[int, str]]:
    """Stream ``(line_number, text)`` pairs (1-based, newline stripped) from a plain or gzip file;
    with ``keep`` (raw bytes -> bool), only the lines it keeps are decoded and yielded.

    A truncated or corrupt gzip stream ends the iteration with a ``truncated`` problem in the report
    (or :class:`DataFormatError` with ``on_error="raise"``); the lines before it are kept. Bytes that
    are not valid in ``encoding`` are replaced and reported once per line.
    """
    lineno = 0
    with open_binary(path) as raw:
        try:
            for raw_line in raw:
                lineno += 1
                if keep is not None and not keep(raw_line):
                    continue
                try:
                    text = raw_line.decode(encoding)
                except UnicodeDecodeError:
                    report.problem(lineno, "bad-encoding", f"not {encoding}; bytes replaced")
                    text = raw_line.decode(encoding, errors="replace")
                # A final line cut mid-way by truncation has no newline; it is still delivered and
                # must then fail the record's own checks (field count, number parsing).
                yield lineno, text.rstrip("\r\n")
        except (EOFError, zlib.error, gzip.BadGzipFile, OSError) as exc:
            report.problem(lineno + 1, "truncated", f"compressed stream ends early ({exc.__class__.__name__}: {exc})")


def stem_of(path: str | os.PathLike) -> str:
    """File name without directory and without the data extensions (``a.txt.gz`` -> ``a``)."""
    name = Path(path).name
    for ext in (".gz", ".txt", ".csv", ".mat", ".json", ".geojson"):
        if name.lower().endswith(ext):
            name = name[: -len(ext)]
    return name


def sort_unique(t, cols: list, report: ReadReport, name: str):
    """Sort samples by time (noting how many went back) and drop repeated timestamps (noted).

    ``t`` (N,) times and ``cols`` arrays with N rows; returns (t, cols) with the same rows kept.
    """
    import numpy as np

    back = int(np.sum(np.diff(t) < 0))
    if back:
        report.note("out-of-order", back, f"{name}: {back} samples went back in time; re-sorted")
        order = np.argsort(t, kind="stable")
        t, cols = t[order], [c[order] for c in cols]
    dup = np.concatenate([[False], np.diff(t) == 0]) if len(t) else np.zeros(0, bool)
    if dup.any():
        report.note("duplicate-timestamp", int(dup.sum()), f"{name}: {int(dup.sum())} repeated timestamps dropped")
        t, cols = t[~dup], [c[~dup] for c in cols]
    return t, cols

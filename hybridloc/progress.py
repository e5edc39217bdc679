"""Progress lines for long commands (``demo``, ``eval fusion``, ``sim walk``, ``map rebuild``).

On a terminal one line is rewritten in place (carriage return). Anywhere else - a CI log, ``make demo
| tee``, a file - a carriage return does not rewrite anything, so every update would pile onto one
ever-growing line; there a new line is written only at each tenth of the way and at the end.
"""

from __future__ import annotations

import sys
from typing import TextIO


class Progress:
    """``Progress("[pipeline] surveys uploaded", n)``, then ``update(i)`` for i = 1..n."""

    def __init__(self, label: str, total: int, stream: TextIO | None = None, bar_width: int = 0, steps: int = 10):
        self.label = label
        self.total = max(int(total), 0)
        self.stream = stream if stream is not None else sys.stderr
        self.bar_width = bar_width
        self.steps = steps
        self._tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last_tenth = -1
        self._open = False  # a rewritten line is on screen, not yet ended

    def _text(self, i: int, detail: str) -> str:
        bar = ""
        if self.bar_width:
            done = int(self.bar_width * i / self.total) if self.total else self.bar_width
            bar = f"[{'#' * done}{'.' * (self.bar_width - done)}] "
        return f"{self.label} {bar}{i}/{self.total}" + (f" {detail}" if detail else "")

    def update(self, i: int, detail: str = "") -> None:
        text = self._text(i, detail)
        if self._tty:
            self.stream.write("\r" + text)
            self._open = True
            if i >= self.total:
                self.close()
            else:
                self.stream.flush()
            return
        tenth = self.steps if self.total == 0 else (self.steps * i) // self.total
        if tenth > self._last_tenth or i >= self.total:
            self._last_tenth = tenth
            self.stream.write(text + "\n")
            self.stream.flush()

    def close(self) -> None:
        """End the rewritten line (no-op when already ended or not on a terminal)."""
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False

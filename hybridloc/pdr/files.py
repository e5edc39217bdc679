"""Files written by ``hybridloc pdr phone``: ``steps.csv`` and ``trajectory.csv`` per input."""

from __future__ import annotations

import csv
import math
import os

from ..types import StepEvent

#: The public columns (a contract: extend, never rename); extra columns follow them.
STEPS_COLUMNS = ("t", "length", "heading", "sigma_length", "sigma_heading")
STEPS_EXTRA_COLUMNS = ("heading_change", "sigma_heading_change", "degraded")


def write_steps_csv(path: str | os.PathLike, steps: list[StepEvent]) -> None:
    """``t,length,heading,sigma_length,sigma_heading`` (s, m, rad, m, rad) + extra columns."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(STEPS_COLUMNS + STEPS_EXTRA_COLUMNS)
        for s in steps:
            w.writerow(
                [
                    f"{s.t:.4f}",
                    f"{s.length:.4f}",
                    f"{s.heading:.5f}",
                    f"{s.sigma_length:.4f}",
                    f"{s.sigma_heading:.5f}",
                    "" if s.heading_change is None else f"{s.heading_change:.5f}",
                    "" if s.sigma_heading_change is None else f"{s.sigma_heading_change:.5f}",
                    s.degraded,
                ]
            )


def read_steps_csv(path: str | os.PathLike) -> list[StepEvent]:
    with open(path, newline="", encoding="utf-8") as f:
        out = []
        for r in csv.DictReader(f):
            hc = r.get("heading_change") or None
            shc = r.get("sigma_heading_change") or None
            out.append(
                StepEvent(
                    float(r["t"]),
                    float(r["length"]),
                    float(r["heading"]),
                    float(r["sigma_length"]),
                    float(r["sigma_heading"]),
                    None if hc is None else float(hc),
                    None if shc is None else float(shc),
                    degraded=r.get("degraded", ""),
                )
            )
    return out


def parse_start(text: str) -> tuple[float, float, float]:
    """``x,y,heading`` (m, m, rad; a heading may end in ``deg``)."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 3:
        raise ValueError(f"--start needs x,y,heading, got {text!r}")
    x, y = float(parts[0]), float(parts[1])
    h = parts[2]
    heading = float(h[:-3]) * math.pi / 180 if h.lower().endswith("deg") else float(h)
    if not all(math.isfinite(v) for v in (x, y, heading)):
        raise ValueError("--start values must be finite")
    return x, y, heading

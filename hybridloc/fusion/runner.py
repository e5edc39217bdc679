"""Batch runner: a step-API fusion filter over a recorded stream of steps and fixes.

The agents run the filters live (``predict`` per step, ``correct`` per fix as it arrives). This runner
feeds the same filter from recorded inputs, in the same order, so a live run can be replayed exactly
and other filters or settings compared on identical inputs (``hybridloc eval fusion`` does both).

A fix is used after the ``arrival`` step count it is given (how many steps the agent had processed
when the fix reached it), or - without arrivals - as soon as the recording's clock passes its scan
time plus ``latency`` seconds.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

from ..types import AbsoluteFix, StepEvent
from .kalman import Estimate


class StepFilter(Protocol):
    initialised: bool

    def predict(self, step: StepEvent) -> Estimate: ...

    def correct(self, fix: AbsoluteFix) -> tuple[bool, Estimate]: ...


def run_fusion(
    filt: StepFilter, steps: Sequence[StepEvent], fixes: Sequence[AbsoluteFix], arrivals: Sequence[int] | None = None, latency: float = 0.0
) -> list[Estimate]:
    """Estimates as a live agent writes them: one per step once initialised, one per accepted fix."""
    if arrivals is not None and len(arrivals) != len(fixes):
        raise ValueError("one arrival step count per fix is needed")
    if arrivals is None:
        order = sorted(range(len(fixes)), key=lambda i: fixes[i].t)
        due = []
        k = 0
        for i in order:  # the number of steps with t < scan time + latency
            while k < len(steps) and steps[k].t < fixes[i].t + latency:
                k += 1
            due.append((k, i))
    else:
        due = sorted(((int(a), i) for i, a in enumerate(arrivals)), key=lambda x: x[0])
    out: list[Estimate] = []
    j = 0
    for n in range(len(steps) + 1):
        while j < len(due) and due[j][0] <= n:
            ok, e = filt.correct(fixes[due[j][1]])
            if ok:
                out.append(e)
            j += 1
        if n < len(steps):
            e = filt.predict(steps[n])
            if filt.initialised:
                out.append(e)
    return out

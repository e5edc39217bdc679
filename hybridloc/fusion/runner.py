"""Batch runner: a step-API fusion filter over a recorded stream of steps and fixes.

The agents run the filters live (``predict`` per step, ``correct`` per fix as it arrives). This runner
feeds the same filter from recorded inputs, in the same order, so a live run can be replayed exactly
and other filters or settings compared on identical inputs (``hybridloc eval fusion`` does both).

A fix is used after the ``arrival`` step count it is given (how many steps the agent had processed
when the fix reached it), or - without arrivals - as soon as the recording's clock passes its scan
time plus ``latency`` seconds.

With ``smooth_lag`` L (a filter with a ``smoothed(lag)`` method: the particle filter's ancestry), the
published track is the fixed-lag smoothed one (:func:`run_fusion_smoothed`): the position at each step
as the filter knows it L steps later (the last L steps of a walk from its final cloud), what a live
agent publishing with an L-step delay would write.
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
    filt: StepFilter,
    steps: Sequence[StepEvent],
    fixes: Sequence,
    arrivals: Sequence[int] | None = None,
    latency: float = 0.0,
    smooth_lag: int | None = None,
) -> list[Estimate]:
    """Estimates as a live agent writes them: one per step once initialised, one per accepted fix;
    with ``smooth_lag`` the fixed-lag smoothed track instead (one per step, :func:`run_fusion_smoothed`).
    ``fixes``: AbsoluteFix (or whatever the filter's ``correct`` takes, e.g. the server's whole
    :class:`~hybridloc.types.Fix` for the particle filter)."""
    if smooth_lag is not None:
        return run_fusion_smoothed(filt, steps, fixes, arrivals, latency, (smooth_lag,))[1][smooth_lag]
    return _run(filt, steps, fixes, arrivals, latency, ())[0]


def run_fusion_smoothed(
    filt, steps: Sequence[StepEvent], fixes: Sequence, arrivals: Sequence[int] | None = None, latency: float = 0.0, lags: Sequence[int] = (10,)
) -> tuple[list[Estimate], dict[int, list[Estimate]]]:
    """One run, the filtered estimates (as :func:`run_fusion`) and for each lag L of ``lags`` the
    fixed-lag smoothed track: at every step the filter's ``smoothed(L)`` (the estimate L steps back),
    the walk's last L steps from its final cloud (``backtrack``); a step whose smoothed estimate never
    came (the cloud restarted before L more steps) keeps its filtered one. One estimate per step, in
    step order."""
    if not hasattr(filt, "smoothed") or not hasattr(filt, "backtrack"):
        raise ValueError(f"{type(filt).__name__} keeps no history to smooth with (the particle filter does)")
    if any(int(lag) < 0 for lag in lags):
        raise ValueError("smoothing lags are numbers of steps >= 0")
    return _run(filt, steps, fixes, arrivals, latency, tuple(int(lag) for lag in lags))[:2]


def _run(filt, steps, fixes, arrivals, latency, lags: tuple[int, ...]) -> tuple[list[Estimate], dict[int, list[Estimate]]]:
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
    step_est: list[Estimate] = []  # the filtered estimate of each step (once initialised)
    late: dict[int, dict[float, Estimate]] = {lag: {} for lag in lags}  # lag -> step time -> smoothed estimate
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
                step_est.append(e)
                for lag in lags:
                    s = filt.smoothed(lag)
                    if s is not None:
                        late[lag][s.t] = s
    smoothed: dict[int, list[Estimate]] = {}
    if lags:
        tail = {e.t: e for e in filt.backtrack()}  # the final cloud's view of its kept steps
        for lag in lags:
            got = late[lag]
            for e in step_est[-lag:] if lag else []:
                if e.t in tail:
                    got[e.t] = tail[e.t]
            smoothed[lag] = [got.get(e.t, e) for e in step_est]
    return out, smoothed

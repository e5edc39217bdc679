"""``hybridloc demo``: the platform on the bundled real sample.

Until the end-to-end server/client demo lands, the demo runs what the library offers on the bundled
Indoor Location Competition sample: reading and checking every trace and its floor plan.
"""

from __future__ import annotations

import time
from pathlib import Path

from .inspect import inspect_file
from .io.msft import find_ilc_traces, read_ilc_site
from .samples import ILC_SITE1_F1


def run_demo(out: Path, sim: bool = False) -> int:
    if sim:
        raise ValueError("--sim needs the simulator, which is not built yet (issue: Simulator)")
    t0 = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    plan = read_ilc_site(ILC_SITE1_F1)
    traces = find_ilc_traces(ILC_SITE1_F1)
    print(f"[demo] bundled sample: {len(traces)} traces on {', '.join(plan.floor_names)} ({ILC_SITE1_F1})")
    report = []
    for i, p in enumerate(traces, 1):
        s = inspect_file(p, "msft")
        report.append(s.render())
        print(f"[demo] {i:2d}/{len(traces)} {p.name}: {s.duration_s:5.1f} s, {dict(s.lines).get('waypoints', '')}")
    (out / "inspect.txt").write_text("\n\n".join(report) + "\n", encoding="utf-8")
    print(f"[demo] wrote {out / 'inspect.txt'} in {time.monotonic() - t0:.1f} s")
    return 0

"""``hybridloc demo``: the platform on the bundled real sample.

Until the end-to-end server/client demo lands, the demo runs what the library offers on the bundled
Indoor Location Competition sample (16 traces of site1 F1): reading and checking every trace and the
floor plan, the phone PDR on every trace (steps.csv + trajectory.csv), and the PDR evaluation
against the ground-truth waypoints.
"""

from __future__ import annotations

import time
from pathlib import Path

from .inspect import inspect_file
from .io.msft import find_ilc_traces, read_ilc_site
from .samples import ILC_SITE1_F1


def run_demo(out: Path, sim: bool = False) -> int:
    from .cli import main as cli_main

    if sim:
        raise ValueError("--sim needs the simulator, which is not built yet (issue: Simulator)")
    t0 = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    plan = read_ilc_site(ILC_SITE1_F1)
    traces = find_ilc_traces(ILC_SITE1_F1)
    print(f"[demo 1/3] bundled sample: {len(traces)} traces on {', '.join(plan.floor_names)} ({ILC_SITE1_F1})", flush=True)
    report = [inspect_file(p, "msft").render() for p in traces]
    (out / "inspect.txt").write_text("\n\n".join(report) + "\n", encoding="utf-8")
    print(f"[demo 1/3] data inspection written to {out / 'inspect.txt'}", flush=True)
    print("[demo 2/3] phone PDR on every trace", flush=True)
    rc = cli_main(["pdr", "phone", *map(str, traces), "--out", str(out / "pdr")])
    print("[demo 3/3] phone PDR against the waypoints", flush=True)
    rc |= cli_main(["eval", "pdr-phone", str(ILC_SITE1_F1)])
    print(f"[demo] done in {time.monotonic() - t0:.1f} s; outputs in {out}")
    return rc

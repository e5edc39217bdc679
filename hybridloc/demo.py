"""``hybridloc demo``: the platform on the bundled real sample.

Until the end-to-end server/client demo lands, the demo runs what the library offers on the bundled
Indoor Location Competition sample (16 traces of site1 F1): reading and checking every trace and the
floor plan, the phone PDR on every trace (steps.csv + trajectory.csv), the PDR evaluation against the
ground-truth waypoints, and a radio map built from some traces used as surveys that locates the others.
"""

from __future__ import annotations

import time
from pathlib import Path

import csv

import numpy as np

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
    print("[demo 2/4] phone PDR on every trace", flush=True)
    rc = cli_main(["pdr", "phone", *map(str, traces), "--out", str(out / "pdr")])
    print("[demo 3/4] phone PDR against the waypoints", flush=True)
    rc |= cli_main(["eval", "pdr-phone", str(ILC_SITE1_F1)])
    survey, others = traces[::2] + traces[1::4], traces[3::4]
    print(f"[demo 4/4] radio map from {len(survey)} traces used as surveys; WiFi positioning of the other {len(others)}", flush=True)
    rc |= cli_main(["map", "build", "--format", "msft", *map(str, survey), "--out", str(out / "radiomap.npz")])
    rc |= cli_main(["locate", "--map", str(out / "radiomap.npz"), "--format", "msft", *map(str, others), "--out", str(out / "locate")])
    rc |= cli_main(["map", "show", str(out / "radiomap.npz"), "--out", str(out / "radiomap.png")])
    errs = _wifi_errors(others, out / "locate")
    if errs.size:
        print(f"[demo] WiFi-only error at waypoints of the {len(others)} located traces: mean {errs.mean():.2f} m, median {np.median(errs):.2f} m (n={errs.size})")
    print(f"[demo] done in {time.monotonic() - t0:.1f} s; outputs in {out}")
    return rc


def _wifi_errors(traces, loc_dir: Path) -> np.ndarray:
    """Error of each trace's WiFi fixes at its waypoints (fix track interpolated to waypoint times)."""
    from .io.common import stem_of
    from .io.msft import read_ilc_trace
    from .metrics import error_at_points

    errs = []
    for p in traces:
        rows = [r for r in csv.DictReader(open(loc_dir / f"{stem_of(p)}.csv", encoding="utf-8")) if r["x"]]
        if len(rows) < 2:
            continue
        t = np.array([float(r["t"]) for r in rows])
        xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
        t, i = np.unique(t, return_index=True)
        wp = read_ilc_trace(p).waypoints
        e = error_at_points(t, xy[i], wp.t, wp.pos_enu)
        errs.extend(e[np.isfinite(e)].tolist())
    return np.array(errs)

"""The operator dashboard under load: N simulated devices at 1 Hz each, the page in headless Chromium.

A real ``hybridloc serve --http`` (its own process, SQLite, the bundled site1 F1 floor plan) receives
the devices' poses (``hybridloc.pose/1`` with a covariance) from a publisher process (one Zenoh client
session, the devices' puts spread evenly over each second) and pushes them to the page over its
WebSocket, coalesced to at most 10 frames per second. Measured, per level of devices:

* the browser's time per update: from a WebSocket frame's arrival to the animation frame after it was
  drawn (the page's ``?perf`` hook, ``performance.now()``), p50 and p95, ms; goal p95 <= 100 ms at 300
  devices on a 2-core machine with software rendering (SwiftShader);
* the server's CPU per pose update and per pushed frame (its process's user + system time over the
  window, from /proc), so the dashboard's cost beside ingest is known;
* the same page with SVG paths instead of Leaflet's canvas renderer at the first level, and the ratio
  of their p95 (the plain way of drawing, measured in the same run).

    python -m benchmarks.bench_dashboard [--devices 300 1000] [--seconds 15]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks import headline
from hybridloc.wire.zconfig import free_port

CHROMIUM = "/usr/bin/chromium"
TOKEN = "bench-dashboard-token-0123456789"
SITE = "bench"


def _publish(ep: str, n: int, rate_hz: float, bbox: tuple, stop, seed: int) -> None:
    """N devices' poses at rate_hz each, spread over the period (a spawned process)."""
    import zenoh

    from hybridloc.types import Pose
    from hybridloc.wire import codecs as C
    from hybridloc.wire import protocol as P
    from hybridloc.wire.zconfig import client_config

    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = bbox
    pos = rng.uniform((x0, y0), (x1, y1), (n, 2))
    heading = rng.uniform(0, 2 * np.pi, n)
    cov = np.array([[2.0, 0.4], [0.4, 1.0]])
    keys = [P.key_pose(SITE, f"dev{i:04d}") for i in range(n)]
    with zenoh.open(client_config(ep)) as s:
        period = 1.0 / rate_hz
        t0 = time.monotonic()
        k = 0
        while not stop.is_set():
            i = k % n
            if i == 0 and k:
                heading += rng.normal(0, 0.3, n)
            pos[i] += 0.7 * np.array([np.cos(heading[i]), np.sin(heading[i])])
            pos[i] = np.clip(pos[i], (x0, y0), (x1, y1))
            s.put(keys[i], C.POSE.encode(Pose(k * period / n, float(pos[i, 0]), float(pos[i, 1]), "F1", cov)), encoding=C.POSE.encoding)
            k += 1
            wait = t0 + k * period / n - time.monotonic()
            if wait > 0:
                time.sleep(wait)


def _cpu_s(pid: int) -> float:
    """User + system CPU of a process, s (/proc/<pid>/stat fields 14 and 15)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _level(page, url: str, svg: bool, ep: str, n: int, seconds: float, warmup: float, bbox, pid: int, idle_share: float) -> dict:
    ctx = mp.get_context("spawn")
    stop = ctx.Event()
    pub = ctx.Process(target=_publish, args=(ep, n, 1.0, bbox, stop, n), daemon=True)
    pub.start()
    try:
        page.goto(f"{url}?perf=1{'&svg=1' if svg else ''}")
        page.wait_for_function(f"() => Number(document.body.dataset.markers) >= {int(0.9 * n)}", timeout=60_000)
        time.sleep(warmup)
        page.evaluate("window.__hlPerf.samples = []")
        cpu0, t0 = _cpu_s(pid), time.monotonic()
        time.sleep(seconds)
        samples = page.evaluate("window.__hlPerf.samples")
        cpu1, t1 = _cpu_s(pid), time.monotonic()
    finally:
        stop.set()
        pub.join(10)
    ms = np.array([s["ms"] for s in samples])
    per = np.array([s["devices"] for s in samples])
    span = t1 - t0
    poses = n * span  # 1 Hz each
    return {
        "devices": n,
        "renderer": "svg" if svg else "canvas",
        "frames": len(ms),
        "frames_per_s": len(ms) / span,
        "devices_per_frame": float(per.mean()) if len(per) else 0.0,
        "p50_ms": float(np.percentile(ms, 50)) if len(ms) else float("nan"),
        "p95_ms": float(np.percentile(ms, 95)) if len(ms) else float("nan"),
        # the server process's CPU above its idle share (the ingest loop's polling, the router's timers)
        "server_cpu_us_per_pose": 1e6 * max(cpu1 - cpu0 - idle_share * span, 0.0) / poses,
        "server_cpu_ms_per_frame": 1e3 * max(cpu1 - cpu0 - idle_share * span, 0.0) / max(len(ms), 1),
        "server_cpu_share": (cpu1 - cpu0) / span,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, nargs="+", default=[300, 1000])
    ap.add_argument("--seconds", type=float, default=15.0, help="measurement window per level, s")
    ap.add_argument("--warmup", type=float, default=3.0, help="seconds before each window")
    ap.add_argument("--no-svg", action="store_true", help="skip the SVG comparison")
    ap.add_argument("--svg-all", action="store_true", help="the SVG comparison at every level (default: the first)")
    args = ap.parse_args(argv)
    if not Path(CHROMIUM).is_file():
        print(f"bench_dashboard: no chromium at {CHROMIUM} (make chromium)", file=sys.stderr)
        return 2
    from playwright.sync_api import sync_playwright

    from hybridloc.io.msft import read_ilc_site
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.server.store import Store

    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "bench.db"
        plan = read_ilc_site(ILC_SITE1_F1)
        st = Store(str(db))
        st.save_floor_plan(SITE, plan)
        st.close()
        bbox = plan.floor("F1").walkable.bounds
        ep = f"tcp/127.0.0.1:{free_port()}"
        cmd = [sys.executable, "-m", "hybridloc.cli", "serve", "--endpoint", ep, "--db", str(db), "--no-slam"]
        cmd += ["--http", "127.0.0.1:0", "--http-token", TOKEN]
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp)
        line = ""
        while not line.startswith("hybridloc dashboard on"):
            line = proc.stdout.readline()
            if not line:
                raise SystemExit("bench_dashboard: the server did not start")
        url = re.search(r"(http://\S+/)", line).group(1)
        threading.Thread(target=proc.stdout.read, daemon=True).start()
        rows = []
        idle_share = 0.0
        try:
            time.sleep(1.0)
            c0, t0 = _cpu_s(proc.pid), time.monotonic()
            time.sleep(3.0)
            idle_share = (_cpu_s(proc.pid) - c0) / (time.monotonic() - t0)
            print(f"server idle (no device, no page): {100 * idle_share:.1f} % of a core")
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM)
                page = browser.new_page(viewport={"width": 1400, "height": 850})
                page.goto(f"{url}?token={TOKEN}")
                for i, n in enumerate(args.devices):
                    rows.append(_level(page, url, False, ep, n, args.seconds, args.warmup, bbox, proc.pid, idle_share))
                    if (i == 0 or args.svg_all) and not args.no_svg:
                        rows.append(_level(page, url, True, ep, n, args.seconds, args.warmup, bbox, proc.pid, idle_share))
                browser.close()
        finally:
            proc.terminate()
            proc.wait(20)
    print(f"{'devices':>8} {'renderer':>8} {'frames/s':>9} {'dev/frame':>9} {'p50 ms':>8} {'p95 ms':>8} {'server us/pose':>15} {'server CPU':>10}")
    for r in rows:
        print(
            f"{r['devices']:>8} {r['renderer']:>8} {r['frames_per_s']:>9.1f} {r['devices_per_frame']:>9.1f} {r['p50_ms']:>8.1f} {r['p95_ms']:>8.1f} "
            f"{r['server_cpu_us_per_pose']:>15.0f} {100 * r['server_cpu_share']:>9.1f}%"
        )
    canvas = {r["devices"]: r for r in rows if r["renderer"] == "canvas"}
    svg = [r for r in rows if r["renderer"] == "svg"]
    figures = {"server_idle_cpu_share": idle_share}
    for n, r in canvas.items():
        figures[f"p50_ms_{n}"] = r["p50_ms"]
        figures[f"p95_ms_{n}"] = r["p95_ms"]
        figures[f"frames_per_s_{n}"] = r["frames_per_s"]
        figures[f"server_cpu_us_per_pose_{n}"] = r["server_cpu_us_per_pose"]
    for r in svg:
        figures[f"svg_over_canvas_p95_{r['devices']}"] = r["p95_ms"] / canvas[r["devices"]]["p95_ms"]
    if 300 in canvas:
        print(f"goal: p95 <= 100 ms at 300 devices: {'met' if canvas[300]['p95_ms'] <= 100 else 'NOT met'} ({canvas[300]['p95_ms']:.1f} ms)")
    headline(figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())

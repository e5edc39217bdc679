"""The server's crowd-SLAM worker on real walks (issue #21 points 1 and 4): how long a finished walk
takes to be added (in the server, child process), what the acknowledgements cost meanwhile, and how
long a batch re-solve takes.

* The bundled sample (Indoor Location Competition site1 F1, 35 real walks through the phone PDR; every
  third keeps its survey marks, the others name their floor through a fix): stored as ended walks, a
  server with SLAM on the site (``Server(slam_sites=[site])``, its spawned child) adds them one by one.
  Meanwhile a device sends a batch every 20 ms and times each acknowledgement. Printed: walk add
  latency (submitted to the child -> result back, p50 / p90 / max), ack round trips while the child
  solves and while it is idle (p50 / p99), then the batch re-solve of the site on demand (seconds).
* ``--site1-floor F``: the batch re-solve (``run_batch``, as ``hybridloc slam rebuild`` runs it) of
  one floor of ../shared/data/msft-ilc/site1, in this process.

    python -m benchmarks.bench_slam_worker [--site1-floor F1]
"""

from __future__ import annotations

import argparse
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks import headline

SITE1 = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "msft-ilc" / "site1"


def _store(store, site: str, walks, floor: str | None = None) -> None:
    from hybridloc.types import AbsoluteFix, SurveyMark
    from hybridloc.wire.messages import Batch

    for i, w in enumerate(walks):
        fl = floor or (w.floors[0] if w.floors else "F1")
        recs = sorted(
            [("s", r) for r in w.steps] + [("c", r) for r in w.scans] + [("m", SurveyMark(r.t, r.x, r.y, fl)) for r in w.marks],
            key=lambda x: x[1].t,
        )
        chunks = [recs[k : k + 500] for k in range(0, len(recs), 500)] or [[]]
        dev = f"dev{i:03d}"
        store.persist(
            [
                Batch(site, dev, n, w.device_model, [r for k, r in ch if k == "s"], [r for k, r in ch if k == "c"], [r for k, r in ch if k == "m"],
                      end_of_walk=n == len(chunks))
                for n, ch in enumerate(chunks, 1)
            ]
        )  # fmt: skip
        if not w.marks and w.scans:
            store.add_fixes([(dev, AbsoluteFix(w.scans[0].t, np.zeros(2), np.eye(2), "wifi", fl))])


def _pct(v, q):
    return float(np.percentile(v, q)) if len(v) else float("nan")


def sample(out: dict) -> None:
    import zenoh

    from hybridloc.clients.uplink import Uplink
    from hybridloc.io.msft import find_ilc_traces, read_ilc_site, read_ilc_trace
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.server.service import Server
    from hybridloc.server.slam_worker import SlamOptions
    from hybridloc.server.store import Store
    from hybridloc.slam.walkgraph import walks_from_files
    from hybridloc.types import StepEvent
    from hybridloc.wire.zconfig import client_config, free_port

    paths = find_ilc_traces(ILC_SITE1_F1)
    site = read_ilc_trace(paths[0]).site
    walks = [w for w, _ in walks_from_files(paths, marks=[i % 3 == 0 for i in range(len(paths))], workers=2)]
    with tempfile.TemporaryDirectory(prefix="bench-slam-worker-") as d:
        db = str(Path(d) / "s.db")
        st = Store(db)
        st.save_floor_plan(site, read_ilc_site(ILC_SITE1_F1))
        st.close()
        ep = f"tcp/127.0.0.1:{free_port()}"
        srv = Server(
            ep, db, slam_sites=[site], slam_options=SlamOptions(poll_s=0.05, batch_every_walks=0, batch_interval_s=0, live_every_s=0)
        ).start()
        w = srv.slam_workers[site]
        acks: list[tuple[float, float, bool]] = []  # (sent, rtt, child busy)
        stop = threading.Event()

        def steady() -> None:
            with zenoh.open(client_config(ep)) as s:
                up = Uplink(s, site, "steady", Path(d) / "spool")
                up.wait_connected(10)
                k = 0
                while not stop.is_set():
                    busy = bool(w.busy)
                    t0 = time.perf_counter()
                    seq = up.send(steps=[StepEvent(10.0 * k + 0.5 * i, 0.7, 0.0, 0.05, 0.1) for i in range(10)])
                    if up.wait_acked(seq, 10):
                        acks.append((t0, time.perf_counter() - t0, busy and bool(w.busy)))
                    k += 1
                    time.sleep(0.02)
                up.close()

        th = threading.Thread(target=steady)
        try:
            th.start()
            time.sleep(3.0)  # idle acks first (the child starts meanwhile)
            st = Store(db, migrate=False)
            _store(st, site, walks)
            st.close()
            t0 = time.monotonic()
            while w.counts["walks_added"] + w.counts["walks_failed"] < len(walks) and time.monotonic() - t0 < 1800:
                time.sleep(0.2)
            t_add = time.monotonic() - t0
            srv.request_batch(site)
            v0 = w.counts["batch_runs"]
            while w.counts["batch_runs"] == v0 and time.monotonic() - t0 < 3600:
                time.sleep(0.2)
            stop.set()
            th.join(30)
        finally:
            stop.set()
            srv.stop()
        lat = sorted(w.add_seconds)
        busy = [r for _, r, b in acks if b]
        idle = [r for _, r, b in acks if not b]
        print(f"{len(walks)} sample walks added in {t_add:.1f} s")
        print(f"walk add latency (s): p50 {_pct(lat, 50):.2f}, p90 {_pct(lat, 90):.2f}, max {max(lat):.2f}")
        print(
            f"ack round trip (ms) while the child solves: p50 {1e3 * _pct(busy, 50):.1f}, p99 {1e3 * _pct(busy, 99):.1f} (n {len(busy)}); "
            f"idle: p50 {1e3 * _pct(idle, 50):.1f}, p99 {1e3 * _pct(idle, 99):.1f} (n {len(idle)})"
        )
        lb = w.last_batch or {}
        print(f"batch re-solve of the site: {lb.get('seconds', float('nan')):.1f} s, walks {lb.get('walks')}, map version {lb.get('map_version')}")
        out.update(
            sample_walks=len(walks),
            walk_add_p50_s=_pct(lat, 50),
            walk_add_p90_s=_pct(lat, 90),
            walk_add_max_s=max(lat),
            ack_busy_p50_ms=1e3 * _pct(busy, 50),
            ack_busy_p99_ms=1e3 * _pct(busy, 99),
            ack_idle_p50_ms=1e3 * _pct(idle, 50),
            ack_idle_p99_ms=1e3 * _pct(idle, 99),
            sample_batch_s=lb.get("seconds"),
        )


def site1_floor(floor: str, out: dict) -> None:
    from hybridloc.io.msft import find_ilc_traces, read_ilc_site
    from hybridloc.server.slam_batch import run_batch
    from hybridloc.server.store import Store
    from hybridloc.slam.walkgraph import walks_from_files

    if not (SITE1 / floor).is_dir():
        print(f"{SITE1 / floor}: absent, site1 floor skipped")
        return
    paths = find_ilc_traces(SITE1 / floor)
    walks = [w for w, _ in walks_from_files(paths, marks=[i % 3 == 0 for i in range(len(paths))], workers=2)]
    with tempfile.TemporaryDirectory(prefix="bench-slam-site1-") as d:
        db = str(Path(d) / "s.db")
        st = Store(db)
        st.save_floor_plan("site1", read_ilc_site(SITE1))
        _store(st, "site1", walks, floor)
        t0 = time.monotonic()
        sm = run_batch(st, "site1", [floor])
        dt = time.monotonic() - t0
        st.close()
    print(f"site1 {floor}: batch re-solve of {len(walks)} walks in {dt:.1f} s: {sm.walks}, map version {sm.map_version}, coverage {sm.coverage}")
    out.update(site1_floor=floor, site1_walks=len(walks), site1_batch_s=dt)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--site1-floor", help="also the batch re-solve of this floor of ../shared/data/msft-ilc/site1")
    args = ap.parse_args(argv)
    out: dict = {}
    sample(out)
    if args.site1_floor:
        site1_floor(args.site1_floor, out)
    headline(out)


if __name__ == "__main__":
    main()

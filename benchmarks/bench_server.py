"""Server throughput and latency with real client processes over loopback.

* Ingest: ``--clients`` processes (spawned, each its own Zenoh client session and device) send batches
  of 100 steps + 10 WiFi scans through the reliable uplink (spool + acks, at most 64 batches in
  flight); the server (``hybridloc serve`` in its own process) persists them to SQLite (WAL). Printed:
  steps/s and scans/s persisted with zero loss (checked in the database), and the cost per 1,000
  messages as the load doubles (1, 2, 4 clients). Each client makes all its batches' records first and
  the clients start together: the clock times sending, not making records. Goal: >= 20,000 steps/s with >= 2,000 scans/s.
* Locate: 200 queries/s for ``--seconds`` s against a synthetic map (1,000 transmitters); p50/p99
  latency of the round trip (goal p50 <= 5 ms, p99 <= 20 ms).
* ``--postgres``: the same ingest against a PostgreSQL server started by the benchmark (Debian's
  postgresql package, initdb in a temporary folder), figures side by side.

    python -m benchmarks.bench_server [--batches 200] [--postgres]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks import headline
from hybridloc.server.db import sqlite_path
from hybridloc.wire.zconfig import free_port


def _client(
    ep: str, device: str, n_batches: int, spool: str, q, n_steps: int = 100, n_scans: int = 10, step_columns_from: int | None = None, go=None
) -> None:
    import zenoh

    from hybridloc.clients.uplink import Uplink
    from hybridloc.types import RfScan, StepEvent
    from hybridloc.wire.zconfig import client_config

    # steps 0.1 s apart (a batch of 1,000 spans 100 s, inside the wire's batch-span limit), the batch's
    # times shifted by its span so that times keep rising from batch to batch
    span = 0.1 * n_steps
    steps = [StepEvent(float(i) * 0.1, 0.7, 0.01 * i, 0.05, 0.1, 0.01, 0.02) for i in range(n_steps)]
    scans = [RfScan(float(i) * span / n_scans, "wifi", {f"ap{j:03d}": -50.0 - j for j in range(30)}) for i in range(n_scans)]
    # every batch's records made before the clock starts: what is timed is sending them (encoding, the
    # spool, Zenoh, the server, the acks), not making them (half a client's time when it was timed)
    records = [
        (
            [
                StepEvent(st.t + k * span, st.length, st.heading, st.sigma_length, st.sigma_heading, st.heading_change, st.sigma_heading_change)
                for st in steps
            ],
            [RfScan(sc.t + k * span, sc.technology, sc.rssi_dbm) for sc in scans],
        )
        for k in range(n_batches)
    ]
    with zenoh.open(client_config(ep)) as s:
        extra = {} if step_columns_from is None else {"step_columns_from": step_columns_from}
        up = Uplink(s, "bench", device, spool, resend_after=5.0, **extra)
        up.wait_connected(20)
        if go is not None:  # every client ready: they start together
            q.put(("ready", device))
            go.wait(600)
        t0 = time.perf_counter()
        for k in range(n_batches):
            while up.pending >= 64:
                up.wait_acked(up.acked + 1, timeout=0.5)
            up.send(steps=records[k][0], scans=records[k][1])
        ok = up.wait_acked(timeout=120)
        q.put((device, time.perf_counter() - t0, ok, up.n_resent))
        up.close()


def _serve(ep: str, db: str, *extra: str) -> subprocess.Popen:
    """``hybridloc serve`` in its own process (``extra``: more serve options), once it listens."""
    p = subprocess.Popen(
        [sys.executable, "-m", "hybridloc.cli", "serve", "--endpoint", ep, "--db", db, *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    line = p.stdout.readline()
    while line.startswith(("warning", "crowd SLAM")):  # its notes before the listening line
        line = p.stdout.readline()
    if "listening" not in line:
        raise RuntimeError(f"server did not start: {line!r}")
    threading.Thread(target=lambda: [None for _ in p.stdout], daemon=True).start()  # keep its pipe drained on long runs
    return p


def ingest_run(
    db_url: str,
    n_clients: int,
    n_batches: int,
    n_steps: int = 100,
    n_scans: int = 10,
    step_columns_from: int | None = None,
    serve_args: tuple[str, ...] = (),
) -> dict:
    """``n_clients`` client processes sending ``n_batches`` batches each to a server on ``db_url`` (started
    with ``serve_args`` more); batches of at least ``step_columns_from`` steps with their steps in the
    columnar form (None: today's rows)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    server = _serve(ep, db_url, *serve_args)
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    go = ctx.Event()
    tmp = tempfile.mkdtemp()
    try:
        procs = [
            ctx.Process(target=_client, args=(ep, f"dev{i:03d}", n_batches, os.path.join(tmp, f"s{i}"), q, n_steps, n_scans, step_columns_from, go))
            for i in range(n_clients)
        ]
        for p in procs:
            p.start()
        for _ in procs:  # each has made its records and reached the server
            q.get(timeout=600)
        go.set()
        res = [q.get(timeout=600) for _ in procs]
        for p in procs:
            p.join()
        wall = max(r[1] for r in res)
    finally:
        server.terminate()
        server.wait(timeout=30)
        shutil.rmtree(tmp, ignore_errors=True)
    from sqlalchemy import func, select
    from sqlalchemy.orm import Session

    from hybridloc.server import db as m

    eng = m.make_engine(db_url)
    with Session(eng) as s:
        got_steps = s.execute(select(func.count()).select_from(m.Step)).scalar_one()
        got_scans = s.execute(select(func.count()).select_from(m.Scan)).scalar_one()
    eng.dispose()
    expect_steps, expect_scans = n_clients * n_batches * n_steps, n_clients * n_batches * n_scans
    return {
        "clients": n_clients,
        "wall": wall,
        "steps": got_steps,
        "scans": got_scans,
        "lossless": got_steps == expect_steps and got_scans == expect_scans and all(r[2] for r in res),
        "resent": sum(r[3] for r in res),
    }


def locate_run(seconds: float, rate: float = 200.0) -> np.ndarray:
    import zenoh

    from hybridloc.radio.radiomap import build_radio_map
    from hybridloc.radio.survey import LabelledScan
    from hybridloc.types import RfScan
    from hybridloc.wire import protocol as P
    from hybridloc.wire.zconfig import client_config

    rng = np.random.default_rng(1)
    aps = rng.uniform(0, 106, (1000, 2))
    names = [f"ap{i:04d}" for i in range(1000)]

    def scan(p):
        r = -45 - 35 * np.log10(np.maximum(1, np.linalg.norm(aps - p, axis=1))) + 4 * rng.standard_normal(1000)
        return {names[j]: float(r[j]) for j in np.flatnonzero(r > -90)}

    refs = [LabelledScan(RfScan(float(i), "wifi", scan(p)), p, 0.5, "F1") for i, p in enumerate(rng.uniform(0, 106, (20000, 2)))]
    tmp = Path(tempfile.mkdtemp())
    build_radio_map(refs, site="bench").save(tmp / "m.npz")
    ep = f"tcp/127.0.0.1:{free_port()}"
    p = subprocess.Popen(
        [sys.executable, "-m", "hybridloc.cli", "serve", "--endpoint", ep, "--db", str(tmp / "l.db"), "--map", f"bench={tmp / 'm.npz'}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert "listening" in p.stdout.readline()
    lat = []
    try:
        with zenoh.open(client_config(ep)) as s:
            qr = s.declare_querier(P.key_locate("bench", "devq"), timeout=2.0)
            queries = [
                json.dumps({"schema": P.LOCATE_SCHEMA, "scan": {"t": 0.0, "tech": "wifi", "rssi": scan(rng.uniform(5, 100, 2))}}) for _ in range(50)
            ]
            t_next = time.perf_counter()
            t_end = t_next + seconds
            i = 0
            while time.perf_counter() < t_end:
                t0 = time.perf_counter()
                replies = list(qr.get(payload=queries[i % len(queries)]))
                lat.append(time.perf_counter() - t0)
                assert replies and replies[0].ok
                i += 1
                t_next += 1.0 / rate
                time.sleep(max(0.0, t_next - time.perf_counter()))
            qr.undeclare()
    finally:
        p.terminate()
        p.wait(timeout=30)
        shutil.rmtree(tmp, ignore_errors=True)
    return np.array(lat) * 1e3


def start_postgres(tmp: Path) -> tuple[str, callable]:
    """A throwaway PostgreSQL server (hybridloc.server.pgtemp, the one the test suite uses) and a
    fresh database on it: (URL, stop). ``tmp`` is unused: the server keeps its own folder."""
    from hybridloc.server.pgtemp import TempPostgres

    pg = TempPostgres().start()
    return pg.database("bench"), pg.stop


def raw_insert_rate(db_url: str, rows: int = 200_000) -> float:
    """Rows/s of a plain executemany of 8-column step rows into a fresh table of the same database, in
    one transaction: the database's own ceiling on this machine, with no server around it (sqlite3 in
    WAL mode, synchronous=NORMAL as the store sets it; psycopg for PostgreSQL)."""
    params = [(i, "dev000", i * 0.1, 0.7, 0.3, 0.05, 0.1, 0.0) for i in range(rows)]
    cols = "(batch_id INTEGER, device_id TEXT, t REAL, length REAL, heading REAL, sigma_length REAL, sigma_heading REAL, heading_change REAL)"
    path = sqlite_path(db_url)
    if path is not None:
        import sqlite3

        con = sqlite3.connect(path)
        con.execute("PRAGMA journal_mode=WAL")
        con.execute("PRAGMA synchronous=NORMAL")
        con.execute(f"CREATE TABLE raw_step {cols}")
        t0 = time.perf_counter()
        with con:
            con.executemany("INSERT INTO raw_step VALUES (?,?,?,?,?,?,?,?)", params)
        dt = time.perf_counter() - t0
        con.execute("DROP TABLE raw_step")
        con.close()
        return rows / dt
    import psycopg

    dsn = db_url.replace("postgresql+psycopg://", "postgresql://")
    with psycopg.connect(dsn) as con:
        con.execute(f"CREATE TABLE raw_step {cols.replace('REAL', 'DOUBLE PRECISION')}")
        t0 = time.perf_counter()
        with con.cursor() as cur:
            cur.executemany("INSERT INTO raw_step VALUES (%s,%s,%s,%s,%s,%s,%s,%s)", params)
        con.commit()
        dt = time.perf_counter() - t0
        con.execute("DROP TABLE raw_step")
        con.commit()
    return rows / dt


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--batches", type=int, default=200, help="batches per client (100 steps + 10 scans each)")
    ap.add_argument("--seconds", type=float, default=10.0, help="duration of the locate test")
    ap.add_argument("--postgres", action="store_true")
    args = ap.parse_args(argv)
    backends = [("SQLite (WAL)", None)]
    if args.postgres:
        backends.append(("PostgreSQL", "pg"))
    figures: dict = {}
    for label, kind in backends:
        prev = None
        for n in (1, 2, 4):
            tmp = Path(tempfile.mkdtemp())
            stop = None
            try:
                if kind == "pg":
                    url, stop = start_postgres(tmp)
                else:
                    url = str(tmp / "bench.db")
                r = ingest_run(url, n, args.batches)
            finally:
                if stop:
                    stop()
                shutil.rmtree(tmp, ignore_errors=True)
            msgs = r["steps"] + r["scans"]
            cost = r["wall"] / msgs * 1000 * 1000  # ms per 1,000 messages
            growth = f", x{cost / prev:.2f} vs half the load" if prev else ""
            prev = cost
            figures[f"{label.split()[0].lower()}_{n}_clients_steps_per_s"] = r["steps"] / r["wall"]
            figures[f"{label.split()[0].lower()}_{n}_clients_scans_per_s"] = r["scans"] / r["wall"]
            figures[f"{label.split()[0].lower()}_{n}_clients_lossless"] = bool(r["lossless"])
            print(
                f"{label} ingest, {n} client process(es): {r['steps'] / r['wall']:,.0f} steps/s + {r['scans'] / r['wall']:,.0f} scans/s persisted, "
                f"{'zero loss' if r['lossless'] else 'LOSS'} ({r['steps']} steps, {r['scans']} scans, {r['resent']} resent); "
                f"{cost:.2f} ms per 1,000 messages{growth}"
            )
    lat = locate_run(args.seconds)
    print(
        f"locate at 200 queries/s over Zenoh (client -> router/server): p50 {np.percentile(lat, 50):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms "
        f"over {len(lat)} queries (goal p50 <= 5 ms, p99 <= 20 ms)"
    )
    figures.update(locate_p50_ms=np.percentile(lat, 50), locate_p99_ms=np.percentile(lat, 99))
    headline(figures)


if __name__ == "__main__":
    main()

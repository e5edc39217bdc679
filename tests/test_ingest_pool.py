"""``serve --ingest-workers N``: batches decoded and stored in worker processes (server/ingest_pool.py),
over real Zenoh on loopback, on a real SQLite file and a real PostgreSQL database."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from collections import Counter

import pytest
import zenoh
from sqlalchemy import select
from sqlalchemy.orm import Session

from hybridloc.clients.uplink import Uplink
from hybridloc.server import db as m
from hybridloc.server.ingest_pool import AUTO_INGEST_WORKERS, IngestPool, resolve_ingest_workers
from hybridloc.server.service import Server
from hybridloc.types import RfScan, StepEvent
from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import Batch
from hybridloc.wire.zconfig import client_config, free_port

from .helpers import interrupt_group, kill_group, stored_stream, wait_until

SITE = "site1"


def _steps(n: int, t0: float) -> list[StepEvent]:
    return [StepEvent(t0 + 0.5 * i, 0.7, 0.1 * i, 0.05, 0.1, 0.1, 0.02) for i in range(n)]


def _scans(n: int, t0: float) -> list[RfScan]:
    return [RfScan(t0 + i, "wifi", {"aa:bb": -50.0 - i, "cc:dd": -70.0}) for i in range(n)]


def _stored(db: str) -> tuple[dict[str, list[int]], int, int, dict[str, int]]:
    """(each device's stored sequence numbers in order, steps, scans, rejections by reason)."""
    eng = m.make_engine(db)
    with Session(eng) as s:
        seqs: dict[str, list[int]] = {}
        for dev, seq in s.execute(select(m.Batch.device_id, m.Batch.seq).order_by(m.Batch.id)):
            seqs.setdefault(dev, []).append(seq)
        steps = len(s.execute(select(m.Step.id)).all())
        scans = len(s.execute(select(m.Scan.id)).all())
        rej = Counter()
        for r in s.execute(select(m.Rejection)).scalars():
            rej[r.reason] += r.count
    eng.dispose()
    return seqs, steps, scans, dict(rej)


def _send_all(ep: str, tmp, devices: list[str], n_batches: int, resend_after: float = 2.0, midway=None) -> list[Uplink]:
    """Each device (an Uplink on one client session) sends ``n_batches`` batches of 40 steps and 3 scans,
    in columns from 20 steps; ``midway()`` runs once half are sent; every batch is acknowledged."""
    with zenoh.open(client_config(ep)) as s:
        ups = [Uplink(s, SITE, d, tmp / f"spool-{d}", resend_after=resend_after, step_columns_from=20) for d in devices]
        try:
            assert ups[0].wait_connected()
            for k in range(n_batches):
                for up in ups:
                    up.send(steps=_steps(40, 30.0 * k), scans=_scans(3, 30.0 * k))
                if midway is not None and k == n_batches // 2:
                    midway()
            for up in ups:
                assert up.wait_acked(timeout=60), (up.device, up.acked)
            return ups
        finally:
            for up in ups:
                up.close()


def test_ingest_workers_store_every_batch_once_in_order(tmp_path, db_url):
    """Four devices through two ingest workers: every batch stored once, each device's in order, the
    acknowledgements as the ingest thread gives them (the uplinks' spools emptied); a duplicate, a gap,
    a malformed message and a bad key are refused and counted as the ingest thread counts them; the
    scans to answer reach the locate thread ("no fix": no map here), one per stored batch."""
    ep = f"unixsock-stream/{tmp_path}/srv.sock"
    devices = [f"dev{i}" for i in range(4)]
    srv = Server(ep, db_url, ingest_workers=2).start()
    try:
        ups = _send_all(ep, tmp_path, devices, 12)
        assert all(up.acked == 12 for up in ups)
        assert sorted(srv._ingest_pool._devices_of) == [2, 2]  # the devices shared between the workers
        with zenoh.open(client_config(ep)) as s:
            s.put(P.key_batch(SITE, "dev0"), C.BATCH.encode(Batch(SITE, "dev0", 5, "", tuple(_steps(2, 999.0)))))  # duplicate
            s.put(P.key_batch(SITE, "dev1"), C.BATCH.encode(Batch(SITE, "dev1", 20, "", tuple(_steps(2, 999.0)))))  # gap
            s.put(P.key_batch(SITE, "dev2"), b"{not json")
            s.put(f"hl/v1/{SITE}/dev3/oops", b"{}")  # not a batch key: never delivered to the batch subscriber
            s.put(P.key_batch(SITE, "dev3"), json.dumps({"schema": "hybridloc.batch/99", "site": SITE, "device": "dev3", "seq": 13}).encode())
            assert wait_until(lambda: sum(v for k, v in srv.counts.items() if k.startswith("rejected:")) >= 4)
        c = srv.counts
        for reason in ("duplicate", "out-of-order", "malformed-json", "schema-version"):
            assert c[f"rejected:{reason}"] == 1, (reason, dict(c))
        assert c["batches-persisted"] == 48 and c["ingest-errors"] == 0
        # one answer per stored batch's newest scan (of a device's waiting together, the older ones shed)
        assert wait_until(lambda: srv.counts["no-fix-pushed"] + srv.counts["fixes-shed"] == 48), dict(srv.counts)
    finally:
        srv.stop()
    seqs, steps, scans, rej = _stored(db_url)
    assert seqs == {d: list(range(1, 13)) for d in devices}
    assert (steps, scans) == (48 * 40, 48 * 3)
    assert rej == {"duplicate": 1, "out-of-order": 1, "malformed-json": 1, "schema-version": 1}


def test_a_killed_ingest_worker_loses_nothing_acknowledged(tmp_path, db_url):
    """An ingest worker SIGKILLed while its devices send: another takes its devices, their clients
    resend what was not acknowledged, and every batch is stored exactly once, in order."""
    ep = f"unixsock-stream/{tmp_path}/srv.sock"
    devices = [f"dev{i}" for i in range(4)]
    srv = Server(ep, db_url, ingest_workers=2).start()
    killed = []

    def kill_one():
        w = srv._ingest_pool._workers[0]
        killed.append(w.proc.pid)
        os.kill(w.proc.pid, signal.SIGKILL)

    try:
        _send_all(ep, tmp_path, devices, 30, resend_after=0.5, midway=kill_one)
        assert killed and srv.counts["ingest-worker-restarts"] == 1
        assert srv._ingest_pool._workers[0].proc.pid != killed[0] and srv._ingest_pool._workers[0].proc.is_alive()
    finally:
        srv.stop()
    seqs, steps, _, _ = _stored(db_url)
    assert seqs == {d: list(range(1, 31)) for d in devices}  # none lost, none doubled, in order
    assert steps == 4 * 30 * 40


def test_stop_ingests_what_the_workers_were_sent(tmp_path):
    """Stopping the server: the workers ingest what they were sent before they exit, and what they stored
    is acknowledged (no batch is stored and left unacknowledged by the stop)."""
    ep = f"unixsock-stream/{tmp_path}/srv.sock"
    db = str(tmp_path / "s.db")
    srv = Server(ep, db, ingest_workers=2).start()
    acked: dict[str, int] = {}
    lock = threading.Lock()

    def on_ack(smp):
        a = C.ACK.decode(smp.payload.to_bytes())
        with lock:
            acked[a.device] = max(acked.get(a.device, 0), a.acked_seq)

    with zenoh.open(client_config(ep)) as s:
        sub = s.declare_subscriber(P.key_ack(SITE, "*"), on_ack)
        assert wait_until(lambda: any(r.ok for r in s.get(P.KEY_STATUS, timeout=1.0)))
        for k in range(1, 151):
            for d in ("a", "b"):
                s.put(P.key_batch(SITE, d), C.BATCH.encode(Batch(SITE, d, k, "", tuple(_steps(300, 200.0 * k)))))
        srv.stop()  # with batches still in the workers' queues and pipes
        seqs, _, _, _ = _stored(db)
        assert all(seqs.get(d) == list(range(1, len(seqs.get(d, [])) + 1)) for d in ("a", "b")), seqs
        # the acknowledgements of everything stored were published before the server's session closed
        assert wait_until(lambda: all(acked.get(d, 0) == len(seqs.get(d, [])) for d in ("a", "b"))), (acked, {d: len(v) for d, v in seqs.items()})
        sub.undeclare()


def test_each_device_stays_with_one_worker(tmp_path):
    """Devices go to the worker with the fewest devices the first time they are seen, and stay there."""
    pool = IngestPool.__new__(IngestPool)  # the assignment alone: no processes
    pool._workers = [object(), object(), object()]
    pool._devices_of = [0, 0, 0]
    pool._device_worker = {}
    first = [pool.worker_of(f"d{i}") for i in range(7)]
    assert first == [0, 1, 2, 0, 1, 2, 0]
    assert [pool.worker_of(f"d{i}") for i in reversed(range(7))] == list(reversed(first))
    assert pool._devices_of == [3, 2, 2]


def test_serve_refuses_negative_ingest_workers(tmp_path):
    with pytest.raises(ValueError, match="ingest_workers"):
        Server(f"unixsock-stream/{tmp_path}/x.sock", str(tmp_path / "x.db"), ingest_workers=-1)


def test_auto_ingest_workers_need_two_cores_and_a_shared_database(tmp_path):
    """``serve --ingest-workers auto`` (the default): workers where the server may use two cores or more
    and they can open its database; SQLite in memory takes none (each would open its own), a count is
    kept as given, and workers asked for on SQLite in memory are refused."""
    f, pg = str(tmp_path / "h.db"), "postgresql+psycopg://u@localhost/h"
    assert resolve_ingest_workers("auto", f, cores=2) == resolve_ingest_workers("auto", pg, cores=8) == AUTO_INGEST_WORKERS
    assert resolve_ingest_workers("auto", "sqlite:///" + f, cores=2) == AUTO_INGEST_WORKERS
    assert resolve_ingest_workers("auto", f, cores=1) == resolve_ingest_workers("auto", pg, cores=1) == 0
    assert resolve_ingest_workers("auto", ":memory:", cores=4) == resolve_ingest_workers("auto", "sqlite://", cores=4) == 0
    assert resolve_ingest_workers(0, pg) == 0 and resolve_ingest_workers(3, f) == 3
    for bad in (-1, "two", 1.5, True):
        with pytest.raises(ValueError, match="ingest_workers"):
            resolve_ingest_workers(bad, f)
    with pytest.raises(ValueError, match="in memory"):
        resolve_ingest_workers(2, ":memory:")
    srv = Server(f"unixsock-stream/{tmp_path}/x.sock", f, ingest_workers="auto")
    try:
        assert srv.ingest_workers == resolve_ingest_workers("auto", f)
    finally:
        srv.stop()


def test_wal_checkpointer_backfills_the_wal_beside_a_writer(tmp_path):
    """The server's WAL checkpointer (server/db.py): with the writer's own autocheckpoint off, the WAL
    it wrote is copied into the database file by the checkpointer's thread; nothing is checkpointed
    while the WAL is below its threshold."""
    import sqlite3

    from hybridloc.server.db import WalCheckpointer, sqlite_path

    assert sqlite_path(str(tmp_path / "a.db")) == str(tmp_path / "a.db")
    assert sqlite_path(f"sqlite:///{tmp_path}/a.db") == f"{tmp_path}/a.db"
    assert sqlite_path("postgresql+psycopg://u@h/db") is None and sqlite_path(":memory:") is None
    path = str(tmp_path / "w.db")
    con = sqlite3.connect(path)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA wal_autocheckpoint=0")
    con.execute("CREATE TABLE x (a REAL, b TEXT)")
    con.commit()
    ck = WalCheckpointer(path, every_s=0.05, min_bytes=1 << 20).start()
    try:
        with con:
            con.executemany("INSERT INTO x VALUES (?, ?)", [(float(i), "y" * 100) for i in range(200)])  # far below 1 MB
        assert not wait_until(lambda: ck.checkpoints > 0, timeout=0.5)
        with con:
            con.executemany("INSERT INTO x VALUES (?, ?)", [(float(i), "y" * 100) for i in range(40_000)])  # about 5 MB
        assert wait_until(lambda: ck.checkpoints > 0, timeout=10.0)
    finally:
        ck.stop()
    busy, log_frames, done = con.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
    assert busy == 0 and log_frames > 0
    con.close()
    assert ck.errors == 0 and not ck._thread.is_alive()
    assert sqlite3.connect(path).execute("SELECT count(*) FROM x").fetchone() == (40_200,)


def _hold_lock_forever(lock, held) -> None:
    with lock:
        held.set()
        threading.Event().wait()


def test_the_writer_lock_is_released_when_its_holder_dies(tmp_path):
    """SQLite's ingest workers share a WriterLock (a flock): a worker SIGKILLed inside its transaction
    must not leave the other writers waiting for ever, as a multiprocessing lock did."""
    import multiprocessing as mp
    import time

    from hybridloc.server.ingest_pool import WriterLock

    lock = WriterLock(str(tmp_path / "write.lock"))
    ctx = mp.get_context("spawn")
    held = ctx.Event()
    p = ctx.Process(target=_hold_lock_forever, args=(lock, held), daemon=True)
    p.start()
    try:
        assert held.wait(60)
        got = threading.Event()

        def take():
            with lock:
                got.set()

        t = threading.Thread(target=take, daemon=True)
        t.start()
        assert not got.wait(0.3)  # held by the other process: we wait
        os.kill(p.pid, signal.SIGKILL)
        p.join(10)
        t0 = time.monotonic()
        assert got.wait(10) and time.monotonic() - t0 < 5  # released with its holder
        t.join(5)
    finally:
        if p.is_alive():
            p.kill()


def test_close_returns_while_the_database_is_locked(tmp_path):
    """Stopping while SQLite is held by another writer (the workers' transactions wait on it, their
    pipes and queues fill): close gives the rest up after its timeout instead of hanging, and nothing
    it gave up was acknowledged (found by a review: the queue's put blocked for ever)."""
    import sqlite3
    import time

    from hybridloc.server.store import Store

    path = str(tmp_path / "t.db")
    Store(path).close()
    delivered: list = []
    pool = IngestPool(1, path, delivered.append, lambda c: None)
    holder = sqlite3.connect(path, timeout=1)
    holder.execute("BEGIN IMMEDIATE")  # the database away for the worker (its busy timeout is 30 s)
    try:
        w = pool._workers[0]
        k = 0
        t0 = time.monotonic()
        while not w.todo.full() and time.monotonic() - t0 < 20:
            k += 1
            pool.submit([(P.key_batch(SITE, "a"), C.BATCH.encode(Batch(SITE, "a", k, "", tuple(_steps(1000, 600.0 * k)))))], lambda key: "a")
        assert w.todo.full()
        t1 = time.monotonic()
        closer = threading.Thread(target=pool.close, kwargs={"timeout_s": 2.0}, daemon=True)
        closer.start()
        closer.join(15)
        assert not closer.is_alive() and time.monotonic() - t1 < 15
        assert not w.proc.is_alive() and not w.feeder.is_alive()
    finally:
        holder.rollback()
        holder.close()
    acked = max((seq for r in delivered for _, _, seq in r.acks), default=0)
    seqs, _, _, _ = _stored(path)
    assert len(seqs.get("a", [])) == acked  # nothing acknowledged that is not stored


def test_a_failing_delivery_does_not_stop_ingest(tmp_path):
    """A result whose delivery fails (a Zenoh put raising) is counted and logged; the next groups are
    still read and delivered (found by a review: one exception ended the reader thread, and with it
    every device's ingest on that worker)."""
    import time

    from hybridloc.server.store import Store

    path = str(tmp_path / "d.db")
    Store(path).close()
    delivered: list = []
    counts: Counter = Counter()

    def deliver(r):
        if not delivered:
            delivered.append(None)
            raise RuntimeError("session closed")
        delivered.append(r)

    pool = IngestPool(1, path, deliver, counts.update)
    try:
        for k in (1, 2, 3):
            pool.submit([(P.key_batch(SITE, "a"), C.BATCH.encode(Batch(SITE, "a", k, "", tuple(_steps(5, 10.0 * k)))))], lambda key: "a")
            assert wait_until(lambda k=k: len(delivered) >= k, timeout=30)
            time.sleep(0.05)
    finally:
        pool.close(timeout_s=10)
    assert [r.acks for r in delivered[1:]] == [[(SITE, "a", 2)], [(SITE, "a", 3)]]
    assert counts["ingest-errors"] == 1 and counts["batches-persisted"] == 3
    assert pool._workers[0].proc.exitcode == 0  # the same process all along, ended by close


def test_ctrl_c_at_the_terminal_stops_serve_and_its_workers_cleanly(tmp_path):
    """Ctrl-C reaches the whole process group, the default ingest workers included: they leave the
    stop to the server (which has them store and acknowledge what they were sent), so ``serve`` exits
    0 with no traceback from any process and every batch sent before is stored once."""
    db = str(tmp_path / "h.db")
    ep = f"tcp/127.0.0.1:{free_port()}"
    argv = [sys.executable, "-m", "hybridloc.cli", "serve", "--endpoint", ep, "--db", db, "--ingest-workers", "2"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        first = proc.stdout.readline()
        assert "listening" in first and "2 worker processes" in first, first
        with zenoh.open(client_config(ep)) as s:
            up = Uplink(s, SITE, "devint", tmp_path / "spool", resend_after=1.0)
            try:
                assert up.wait_connected()
                for i in range(5):
                    up.send(steps=_steps(4, 10.0 * i), scans=_scans(1, 10.0 * i))
                assert up.wait_acked(timeout=30)
            finally:
                up.close()
        out = interrupt_group(proc)
    finally:
        kill_group(proc)
    assert proc.returncode == 0, out
    assert "Traceback" not in out and "KeyboardInterrupt" not in out, out
    assert stored_stream(db, "devint") == (list(range(1, 6)), 20)

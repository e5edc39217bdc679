"""Ingest in worker processes: ``hybridloc serve --ingest-workers N``.

The ingest thread decodes, validates and persists every batch (:func:`.ingest.ingest_group`) under the
one interpreter lock of the server's process: with large batches (a spool replay's 1,000 steps and 100
scans) the server ran one core flat out while the machine's other core sat mostly idle
(``benchmarks/bench_load.py --ceiling-only``). With workers, the ingest thread only receives: each
device is given to one worker the first time it is seen (the worker with the fewest devices), and
its messages go to that worker, in the order they came, as (key expression, payload) bytes. A worker
runs the same :func:`.ingest.ingest_group` on its own connection to the database and returns the
acknowledgements, the scans to locate and its counts; the server publishes and answers them as it
does its own. A device's batches are ingested in order by one process, so go-back-N holds as in one
thread; the workers' transactions run side by side (SQLite takes one writer at a time: a worker's
transaction waits for the other's commit, its decoding does not; PostgreSQL takes both).

Nothing is acknowledged before it is committed. A worker that dies (killed, out of memory) loses only
what it had not committed and acknowledged: the server logs it, counts ``ingest-worker-restarts``,
starts another for the same devices, and their clients resend what was not acknowledged (a batch
committed but not acknowledged comes back as a duplicate, go-back-N). Workers are spawned (never
forked: the server has Zenoh's threads) and exit when the server is gone. On :meth:`IngestPool.close`
each worker ingests what it was sent, returns it, and exits.
"""

from __future__ import annotations

import fcntl
import gc
import logging
import multiprocessing as mp
import os
import queue
import shutil
import tempfile
import threading
from collections import Counter
from collections.abc import Callable
from multiprocessing.connection import Connection

from .ingest import IngestResult, Stopping, ingest_group, with_database

log = logging.getLogger("hybridloc.server")

_STOP = "stop"


# ------------------------------------------------------------------------------------------ a worker
def _worker_main(conn: Connection, db_url: str, parent_pid: int, max_group: int, write_lock) -> None:
    """A worker process: groups of (key, payload) in, an :class:`IngestResult` (or the error's text) out
    for each, until told to stop or the server is gone."""
    from .child_process import yield_to_server
    from .db import INGEST_WAL_AUTOCHECKPOINT
    from .store import Store

    yield_to_server(parent_pid, 0, "hybridloc-ingest-watch")  # ingest keeps the server's priority
    # the server migrated it before starting us; its WalCheckpointer checkpoints beside us
    store = Store(db_url, migrate=False, wal_autocheckpoint=INGEST_WAL_AUTOCHECKPOINT)
    if write_lock is not None:
        store.write_lock = write_lock
    stopping = threading.Event()
    # what the process loaded (modules, the engine) left out of the collector's scans, as the server does
    gc.collect()
    gc.freeze()
    conn.send("ready")
    try:
        while True:
            msg = conn.recv()
            if msg == _STOP:
                break
            items = list(msg)
            # whatever else is already waiting joins the group (one transaction for all of it), up to max_group
            while len(items) < max_group and conn.poll():
                more = conn.recv()
                if more == _STOP:
                    stopping.set()
                    break
                items += more
            counts: Counter = Counter()
            try:
                got: IngestResult | str = ingest_group(store, items, lambda fn, counts=counts: with_database(fn, counts, stopping), counts)
            except Stopping:  # told to stop while the database was away: this group is not stored, nor acknowledged
                got = IngestResult(counts=counts)
            except Exception as exc:  # noqa: BLE001 - reported to the server, which logs it and goes on
                got = f"{type(exc).__name__}: {exc}"
                log.exception("ingest of a group of %d messages failed in a worker", len(items))
            conn.send((len(items), got, counts))
            if stopping.is_set():
                break
    except (EOFError, OSError):
        pass  # the server closed our pipe: nothing more to ingest
    finally:
        store.close()
        conn.close()


# ------------------------------------------------------------------------------------------ the pool
def _is_sqlite(url: str) -> bool:
    return "://" not in url or url.startswith("sqlite")


class WriterLock:
    """The lock SQLite's ingest workers take around each transaction: an exclusive ``flock`` on a file,
    which the kernel releases when its holder dies (a worker SIGKILLed inside its transaction left a
    multiprocessing lock held for ever, and every other writer waiting on it). Picklable: each process
    opens the file for itself (flock locks belong to an open file, so two opens contend). Blocking in
    ``flock`` releases the interpreter lock."""

    def __init__(self, path: str):
        self.path = path
        self._fd: int | None = None

    def __getstate__(self) -> dict:
        return {"path": self.path}

    def __setstate__(self, state: dict) -> None:
        self.path, self._fd = state["path"], None

    def __enter__(self) -> WriterLock:
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        fcntl.flock(self._fd, fcntl.LOCK_EX)
        return self

    def __exit__(self, *exc) -> None:
        assert self._fd is not None
        fcntl.flock(self._fd, fcntl.LOCK_UN)


class _Worker:
    """One worker process, the thread that feeds it groups and the thread that reads its results."""

    def __init__(self, pool: IngestPool, index: int):
        self.pool, self.index = pool, index
        self.todo: queue.Queue = queue.Queue(maxsize=pool.queue_groups)
        self.in_flight = 0  # messages sent and not yet returned
        self.ready = threading.Event()  # the process has started and opened the database
        self._lock = threading.Lock()
        self._spawn()
        self.feeder = threading.Thread(target=self._feed, name=f"hybridloc-ingest-feed-{index}", daemon=True)
        self.feeder.start()

    def _spawn(self) -> None:
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(
            target=_worker_main,
            args=(child, self.pool.db_url, os.getpid(), self.pool.max_group, self.pool.write_lock),
            name=f"hybridloc-ingest-{self.index}",
            daemon=True,
        )
        self.proc.start()
        child.close()
        self.reader = threading.Thread(target=self._read, args=(self.conn, self.proc), name=f"hybridloc-ingest-read-{self.index}", daemon=True)
        self.reader.start()

    def _feed(self) -> None:
        """Send each queued group to the process (blocking while its pipe is full: the back pressure reaches
        the server's channel and, through Zenoh's congestion control, the clients)."""
        while True:
            items = self.todo.get()
            if items is None:
                try:
                    self.conn.send(_STOP)
                except (OSError, ValueError):
                    pass
                return
            with self._lock:
                conn = self.conn
                self.in_flight += len(items)
            try:
                conn.send(items)
            except (OSError, ValueError):  # the process died: its reader restarts it; these are resent by their clients
                with self._lock:
                    self.in_flight -= len(items)
                self.pool.count("ingest-messages-lost-to-restarts", len(items))

    def _read(self, conn: Connection, proc) -> None:
        try:
            if conn.recv() != "ready":
                raise EOFError
            self.ready.set()
            while True:
                n, got, counts = conn.recv()
                with self._lock:
                    self.in_flight -= n
                self.pool.count_all(counts)
                if isinstance(got, str):
                    self.pool.count("ingest-errors", 1)
                    log.error(
                        "ingest of a group of %d messages failed in worker %d (%s); what it did not store stays unacknowledged", n, self.index, got
                    )
                else:
                    self.pool.deliver(got)
        except (EOFError, OSError):
            pass
        proc.join(10.0)
        if self.pool.closing:
            return
        # died: the messages it held are not acknowledged (their clients resend them); a new process takes its devices
        with self._lock:
            lost, self.in_flight = self.in_flight, 0
            log.error("ingest worker %d ended (exit code %s) with %d messages unacknowledged: starting another", self.index, proc.exitcode, lost)
            self.pool.count("ingest-worker-restarts", 1)
            self._spawn()


class IngestPool:
    """``workers`` processes ingesting the groups the server receives (module docstring). ``deliver``
    takes each group's :class:`IngestResult` (from the workers' reader threads); ``count(key, n)`` adds
    to the server's counts."""

    def __init__(
        self,
        workers: int,
        db_url: str,
        deliver: Callable[[IngestResult], None],
        count_all: Callable[[Counter], None],
        max_group: int = 500,
        queue_groups: int = 4,
        ready_timeout_s: float = 60.0,
    ):
        if workers < 1:
            raise ValueError(f"an ingest pool needs at least one worker, got {workers}")
        self.db_url, self.deliver, self.count_all = db_url, deliver, count_all
        self.max_group, self.queue_groups = max_group, queue_groups
        self.closing = False
        # SQLite: one writer at a time, handed over by a lock at each commit (the Store's write_lock)
        self._dir = tempfile.mkdtemp(prefix="hybridloc-ingest-")
        self.write_lock = WriterLock(os.path.join(self._dir, "write.lock")) if _is_sqlite(db_url) else None
        self._device_worker: dict[str, int] = {}
        self._devices_of = [0] * workers
        self._workers = [_Worker(self, i) for i in range(workers)]
        # ready before the server says it listens (a process takes about a second to start): the first
        # batches are not held up behind the workers' start
        for w in self._workers:
            if not w.ready.wait(ready_timeout_s):
                log.warning("ingest worker %d not ready after %.0f s: its devices' batches wait for it", w.index, ready_timeout_s)

    def count(self, key: str, n: int) -> None:
        self.count_all(Counter({key: n}))

    def worker_of(self, device: str) -> int:
        """The worker that ingests ``device``'s messages: the same one every time (its batches in order)."""
        w = self._device_worker.get(device)
        if w is None:
            w = min(range(len(self._workers)), key=self._devices_of.__getitem__)
            self._device_worker[device] = w
            self._devices_of[w] += 1
        return w

    def submit(self, items: list[tuple[str, bytes]], device_of: Callable[[str], str]) -> None:
        """Send ``items`` (key expression, payload), each to its device's worker (``device_of(key)``),
        in order. Blocks while a worker's queue is full."""
        parts: dict[int, list] = {}
        for key, payload in items:
            parts.setdefault(self.worker_of(device_of(key)), []).append((key, payload))
        for w, part in parts.items():
            self._workers[w].todo.put(part)

    @property
    def in_flight(self) -> int:
        """Messages sent to the workers and not yet ingested."""
        return sum(w.in_flight + sum(map(len, list(w.todo.queue))) for w in self._workers)

    def close(self, timeout_s: float = 30.0) -> None:
        """Each worker ingests what it was sent, returns it, and exits (killed after ``timeout_s``)."""
        import time

        self.closing = True  # a worker ending from now on is not replaced
        for w in self._workers:
            w.todo.put(None)
        deadline = time.monotonic() + timeout_s
        for w in self._workers:
            w.feeder.join(max(0.0, deadline - time.monotonic()))
            w.proc.join(max(0.0, deadline - time.monotonic()))
        for w in self._workers:
            if w.proc.is_alive():
                w.proc.kill()
                w.proc.join(5.0)
            w.reader.join(5.0)
            w.conn.close()
        shutil.rmtree(self._dir, ignore_errors=True)

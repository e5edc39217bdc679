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
import threading
import time
from collections import Counter
from collections.abc import Callable
from multiprocessing.connection import Connection

from .child_process import usable_cores
from .db import sqlite_path
from .ingest import IngestResult, Stopping, ingest_group, with_database

log = logging.getLogger("hybridloc.server")

_STOP = "stop"

#: ``serve --ingest-workers auto`` (the default): this many workers when the server may use two cores or
#: more. Measured with ``benchmarks/bench_load.py`` on 2 cores (docs/deployment.md, "Load: the
#: measurements"): live, 1,000 clients held real time with either on SQLite, the workers answering
#: sooner (ack p50 about 1 s against 4 s) in about 100 MB less memory with their own counted; on
#: PostgreSQL the ingest thread held them at the edge (realtime factor 0.99-1.23), the workers with room
#: (1.37-1.52); large batches reach a higher share of the raw insert rate on SQLite.
AUTO_INGEST_WORKERS = 2


def resolve_ingest_workers(value: int | str, db_url: str, cores: int | None = None) -> int:
    """The number of ingest worker processes for ``serve --ingest-workers VALUE``: a count as given,
    ``"auto"`` :data:`AUTO_INGEST_WORKERS` when the process may use two cores or more (``cores``, else
    its CPU affinity) and the database is one the workers can open beside the server (a SQLite file or
    a database server), else 0 (the ingest thread). SQLite in memory takes no workers: each would open
    a database of its own."""
    in_memory = sqlite_path(db_url) is None and ("://" not in db_url or db_url.startswith("sqlite"))
    if value == "auto":
        cores = usable_cores() if cores is None else cores
        return AUTO_INGEST_WORKERS if cores >= 2 and not in_memory else 0
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"ingest_workers must be a count >= 0 or 'auto', got {value!r}")
    if value and in_memory:
        raise ValueError("ingest_workers need a database they can open beside the server: a SQLite file or a database server, not SQLite in memory")
    return value


# ------------------------------------------------------------------------------------------ a worker
def _worker_main(conn: Connection, db_url: str, parent_pid: int, max_group: int, write_lock, stop_event) -> None:
    """A worker process: groups of (key, payload) in, an :class:`IngestResult` (or the error's text) out
    for each, until told to stop or the server is gone. ``stop_event`` (set when the server stops) ends a
    wait for the database, as the ingest thread's does: that group is neither stored nor acknowledged."""
    from .child_process import yield_to_server
    from .db import INGEST_WAL_AUTOCHECKPOINT
    from .store import Store

    yield_to_server(parent_pid, 0, "hybridloc-ingest-watch")  # ingest keeps the server's priority
    # the server migrated it before starting us; its WalCheckpointer checkpoints beside us
    store = Store(db_url, migrate=False, wal_autocheckpoint=INGEST_WAL_AUTOCHECKPOINT)
    if write_lock is not None:
        store.write_lock = write_lock
    # what the process loaded (modules, the engine) left out of the collector's scans, as the server does
    gc.collect()
    gc.freeze()
    conn.send("ready")
    try:
        last = False
        while not last:
            msg = conn.recv()
            if msg == _STOP:
                break
            items = list(msg)
            # whatever else is already waiting joins the group (one transaction for all of it), up to max_group
            while len(items) < max_group and conn.poll():
                more = conn.recv()
                if more == _STOP:
                    last = True
                    break
                items += more
            counts: Counter = Counter()
            try:
                got: IngestResult | str = ingest_group(store, items, lambda fn, counts=counts: with_database(fn, counts, stop_event), counts)
            except Stopping:  # told to stop while the database was away: this group is not stored, nor acknowledged
                got = IngestResult(counts=counts)
            except Exception as exc:  # noqa: BLE001 - reported to the server, which logs it and goes on
                got = f"{type(exc).__name__}: {exc}"
                log.exception("ingest of a group of %d messages failed in a worker", len(items))
            conn.send((len(items), got, counts))
    except (EOFError, OSError):
        pass  # the server closed our pipe: nothing more to ingest
    finally:
        store.close()
        conn.close()


# ------------------------------------------------------------------------------------------ the pool
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
        self.ready = threading.Event()  # the process has started and opened the database
        self.closing = False  # set by the pool's close, under _lock: no process is started after it
        self._lock = threading.Lock()  # conn, proc, reader and closing change together under it
        # held by the feeder through each send, and by the reader to close a connection: closing a pipe
        # while a send is still writing to it frees its descriptor, the next pipe (the replacement
        # process's) may get the same number, and the rest of the interrupted message would reach the
        # new process as garbage (seen once: "invalid load key", a second restart)
        self._sending = threading.Lock()
        with self._lock:
            self._spawn()
        self.feeder = threading.Thread(target=self._feed, name=f"hybridloc-ingest-feed-{index}", daemon=True)
        self.feeder.start()

    def _spawn(self) -> None:  # under _lock
        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(
            target=_worker_main,
            args=(child, self.pool.db_url, os.getpid(), self.pool.max_group, self.pool.write_lock, self.pool.stop_event),
            name=f"hybridloc-ingest-{self.index}",
            daemon=True,
        )
        self.proc.start()
        child.close()
        self.reader = threading.Thread(target=self._read, args=(self.conn, self.proc), name=f"hybridloc-ingest-read-{self.index}", daemon=True)
        self.reader.start()

    def _feed(self) -> None:
        """Send each queued group to the process (blocking while its pipe is full: the back pressure reaches
        the server's channel and, through Zenoh's congestion control, the clients). A group sent to a
        process that died is not acknowledged: its clients resend it."""
        while True:
            items = self.todo.get()
            with self._lock:
                conn = self.conn
            with self._sending:
                try:
                    conn.send(_STOP if items is None else items)
                except Exception:  # noqa: BLE001 - died (its reader starts another; a send blocked on a dead
                    # process's pipe fails) or closed meanwhile by its reader (OSError): not delivered
                    if items is not None:
                        self.pool.count("ingest-messages-lost-to-restarts", len(items))
            if items is None:
                return

    def _read(self, conn: Connection, proc) -> None:
        """The process's results, each delivered (acknowledgements, scans to answer) and counted; when it
        ends, another is started for the same devices unless the pool is closing."""
        try:
            if conn.recv() != "ready":
                raise EOFError
            self.ready.set()
            while True:
                n, got, counts = conn.recv()
                try:
                    self.pool.count_all(counts)
                    if isinstance(got, str):
                        self.pool.count("ingest-errors", 1)
                        log.error(
                            "ingest of a group of %d messages failed in worker %d (%s); what it did not store stays unacknowledged",
                            n,
                            self.index,
                            got,
                        )
                    else:
                        self.pool.deliver(got)
                except Exception:  # noqa: BLE001 - one result's delivery failing (a Zenoh put) must not end the reading:
                    # what was stored and not acknowledged is resent by its clients and acknowledged as a duplicate
                    self.pool.count("ingest-errors", 1)
                    log.exception("delivering a group of %d messages from ingest worker %d failed", n, self.index)
        except (EOFError, OSError):
            pass
        except Exception:  # noqa: BLE001 - an unreadable result: the stream is not to be trusted, the process is replaced
            log.exception("ingest worker %d sent what cannot be read: replacing it", self.index)
            proc.kill()
        proc.join(10.0)
        with self._lock:
            with self._sending:  # a send in flight on this connection ends first: its process is gone, so it fails
                conn.close()
            if self.closing:
                return
            # died: what it held is not acknowledged (its clients resend it); a new process takes its devices
            log.error("ingest worker %d ended (exit code %s): starting another for its devices", self.index, proc.exitcode)
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
        #: set when the server stops: a worker waiting for the database gives its group up (as the ingest thread does)
        self.stop_event = mp.get_context("spawn").Event()
        # SQLite: one writer at a time, handed over by a lock at each commit (the Store's write_lock); its
        # file beside the database (a temporary folder's could be cleaned away under a long-running server)
        path = sqlite_path(db_url)
        self.write_lock = WriterLock(path + "-ingest.lock") if path is not None else None
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

    def submit(self, items: list[tuple[str, bytes]], device_of: Callable[[str], str], stopping: threading.Event | None = None) -> None:
        """Send ``items`` (key expression, payload), each to its device's worker (``device_of(key)``),
        in order. Blocks while a worker's queue is full; once ``stopping`` is set, a group that still
        finds its worker's queue full after 2 s is given up (not acknowledged: its clients resend it)."""
        parts: dict[int, list] = {}
        for key, payload in items:
            parts.setdefault(self.worker_of(device_of(key)), []).append((key, payload))
        for w, part in parts.items():
            waited_stopping = 0.0
            while True:
                try:
                    self._workers[w].todo.put(part, timeout=0.25)
                    break
                except queue.Full:
                    if stopping is not None and stopping.is_set():
                        waited_stopping += 0.25
                        if waited_stopping >= 2.0:
                            self.count("ingest-messages-given-up-at-stop", len(part))
                            break

    def close(self, timeout_s: float = 30.0) -> None:
        """Each worker ingests what it was sent, returns it, and exits; one waiting for the database gives
        its group up at once; what is left after ``timeout_s`` is given up (not acknowledged) and the
        processes killed."""
        self.stop_event.set()
        for w in self._workers:
            with w._lock:
                w.closing = True  # a worker ending from now on is not replaced
        deadline = time.monotonic() + timeout_s
        for w in self._workers:
            try:
                w.todo.put(None, timeout=max(0.0, deadline - time.monotonic()))
            except queue.Full:  # its feeder is stuck on a full pipe: what is queued is given up
                while True:
                    try:
                        left = w.todo.get_nowait()
                    except queue.Empty:
                        break
                    if left is not None:
                        self.count("ingest-messages-given-up-at-stop", len(left))
                w.todo.put_nowait(None)
        for w in self._workers:
            w.feeder.join(max(0.0, deadline - time.monotonic()))
            w.proc.join(max(0.0, deadline - time.monotonic()))
        for w in self._workers:
            with w._lock:
                proc, reader = w.proc, w.reader
            if proc.is_alive():
                proc.kill()
                proc.join(5.0)
            reader.join(5.0)
            w.feeder.join(5.0)  # a send blocked on the killed process's full pipe has failed by now

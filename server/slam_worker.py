"""The server's crowd-SLAM worker: one per served site, apart from the ingest path (issue #21 point 1).

A :class:`SlamWorker` is a thread of the server process that never computes anything heavy itself.
The solves run in a spawned child process (:mod:`.slam_child`) that keeps the site's crowd SLAM in
memory; the thread only decides what comes next, waits (releasing the GIL: the ingest thread and the
acknowledgements never wait on a solve) and publishes what the child returns. Its loop, every
``poll_s`` while idle:

1. close the walks whose device fell silent for ``idle_timeout_s`` (server clock; a walk also ends at
   once with the device's end-of-walk marker, :meth:`Store.persist`);
2. pick up a radio map version stored by someone else (``hybridloc slam rebuild``), load it into the
   server's locator and announce it on ``hl/v1/<site>/map/version``;
3. when a batch re-solve is due - ``batch_every_walks`` walks added since the last one, or
   ``batch_interval_s`` passed with at least one, or asked for (:meth:`request_batch`), or an
   unfinished run found at start (the server was killed during one: it resumes after the floors it
   finished) - run it in the child (:func:`.slam_batch.run_batch`), publishing its progress on
   ``hl/v1/<site>/progress``, then load and announce the new map and send the new tracks of the
   devices online;
4. else add the oldest finished walk not yet seen (incremental: its own variables solved, its
   neighbours held) and send its corrected track to its device on ``hl/v1/<site>/<device>/track``;
5. else, for a device online whose open walk grew by ``live_every_s`` of records, a provisional
   correction of the walk so far (not stored) to the device: its live pose improves after every one.

Faults: a walk the solver quarantines is stored so and counted (not held, the map untouched). An
exception while solving a walk is logged with the walk id and retried up to ``max_attempts``, then the
walk is marked failed (a later batch run tries it again); a child that dies (segfault, ``os._exit``) is
replaced and the walk counted an attempt. Nothing here can stop the ingest.
"""

from __future__ import annotations

import datetime as dt
import logging
import multiprocessing as mp
import os
import queue
import statistics
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from hybridloc.types import WalkEnd
from hybridloc.wire.codecs import MAP_VERSION, PROGRESS, TRACK
from hybridloc.wire.messages import MapVersion, Progress
from hybridloc.wire.protocol import key_map_version, key_progress, key_track

from . import db as m
from .slam_batch import LEASE_S
from .slam_store import CORRECTED, FAILED
from .store import WALK_IDLE_GAP_S, Store

log = logging.getLogger("hybridloc.server.slam")

Publish = Callable[[str, bytes, str], None]


@dataclass
class SlamOptions:
    """How a site's SLAM worker paces itself (``hybridloc serve --slam-*``)."""

    #: an open walk whose device sent nothing for this long (server clock, s) is finished
    idle_timeout_s: float = WALK_IDLE_GAP_S
    #: a batch re-solve after this many walks added since the last one (0: not by count) ...
    batch_every_walks: int = 25
    #: ... and at least this share of the walks the last one solved (0: the count alone). A batch costs
    #: more than in proportion to the walks it holds (site1: 7 s at 55 walks, 192 s at 305, on 2 cores),
    #: so at a fixed count each added walk costs ever more batch work as a site grows; at a share of the
    #: site that work per added walk stays bounded (the batches come at geometrically spaced site sizes;
    #: below batch_every_walks / share walks the count alone decides). Off by default: on site1's eval
    #: crowd, 0.25 cut the time to 1632 / 1442 s (two runs; a fixed 25: 2009 / 1956 s) but the last third
    #: of the crowd learned less on the staler maps served to it (27 / 23 % against 28 / 35 / 26 %).
    batch_share: float = 0.0
    #: a batch re-solve this long after the last one when walks were added since (s; 0: not by time)
    batch_interval_s: float = 3600.0
    #: processes a batch re-solve spreads the site's connected groups of floors over (the SLAM child and
    #: forked copies of it: :func:`.slam_batch._solve_groups`; the results are the same); 0: the usable
    #: cores. While a batch runs it then takes that many cores, at the child's lower priority. Site1's
    #: eval crowd database (305 walks, three floors): 105 s against 196-255 s in one process, 2 cores
    batch_processes: int = 0
    #: the loop's pause when there is nothing to do, s
    poll_s: float = 1.0
    #: a walk whose solve failed this many times is marked failed (the next batch run retries it)
    max_attempts: int = 3
    #: a provisional correction of an online device's open walk after this much new walking (device
    #: clock, s) and no sooner than this after the previous one (wall clock); 0: none
    live_every_s: float = 25.0
    #: a failed or refused batch run is tried again after this long, s
    retry_s: float = 60.0
    #: the batch run's lease (:data:`.slam_batch.LEASE_S`)
    lease_s: float = LEASE_S
    #: the served map grows at every added walk: the walk's scans at their corrected positions are
    #: served on top of the stored map version until a version holds them (``Server.add_labels``; the
    #: next batch's map places them again). Off by default: it lowers the live error the goals' ratios
    #: compare against (docs/slam.md, "The served map grown at every added walk")
    grow_map: bool = False
    #: solve in the worker thread itself instead of a child process (tests and debugging only: a solve
    #: then holds the server's GIL)
    in_process: bool = False
    #: "module:function" called in the child before each walk and floor solve, with its argument (tests:
    #: a slow, failing or crashing solve; see tests/slam_helpers.py)
    child_hook: str | None = None
    child_hook_arg: str = ""

    def batch_process_count(self) -> int:
        """The processes a batch re-solve uses (:attr:`batch_processes`, 0 resolved to the usable cores)."""
        from .slam_batch import usable_cores

        return self.batch_processes or usable_cores()


class ChildError(RuntimeError):
    """A call raised in the child: its exception's type name, message and the child's traceback."""

    def __init__(self, name: str, message: str, tb: str):
        self.name, self.message, self.tb = name, message, tb
        super().__init__(f"{name}: {message}")


class ChildCrashed(RuntimeError):
    """The child process died during a call."""

    def __init__(self, exitcode: int | None):
        self.exitcode = exitcode
        super().__init__(f"the SLAM child process died (exit code {exitcode})")


class _Stopping(Exception):
    pass


class _Child:
    """The spawned child process (:func:`.slam_child.child_main`) and its two queues."""

    def __init__(self, db_url: str, site: str, opts: SlamOptions):
        from .slam_child import child_main

        ctx = mp.get_context("spawn")  # never fork after zenoh.open
        self.req, self.resp = ctx.Queue(), ctx.Queue()
        self.proc = ctx.Process(
            target=child_main,
            args=(self.req, self.resp, os.getpid(), db_url, opts.child_hook, opts.child_hook_arg, log.getEffectiveLevel()),
            name=f"hybridloc-slam-{site}",
            daemon=True,
        )
        self.proc.start()
        self._next = 0
        self.busy = False

    def call(self, name: str, on_progress: Callable[..., None], stop: threading.Event, **kwargs) -> Any:
        """Run ``name`` in the child and wait for its answer (forwarding its progress); ChildError,
        ChildCrashed, or _Stopping when the worker is asked to stop meanwhile (the child stays busy)."""
        self._next += 1
        cid = self._next
        self.busy = True
        self.req.put((cid, name, kwargs))
        while True:
            try:
                msg = self.resp.get(timeout=0.25)
            except queue.Empty:
                if not self.proc.is_alive():
                    raise ChildCrashed(self.proc.exitcode) from None
                if stop.is_set():
                    raise _Stopping() from None
                continue
            if msg[1] != cid:
                continue  # left over from a call given up on
            if msg[0] == "progress":
                on_progress(*msg[2])
                continue
            self.busy = False
            if msg[2]:
                return msg[3]
            raise ChildError(*msg[3])

    def close(self) -> None:
        """End the child: asked to when idle, terminated when busy (a batch run resumes from its
        checkpoints at the next start)."""
        try:
            if not self.busy:
                self.req.put(None)
                self.proc.join(5.0)
            if self.proc.is_alive():
                self.proc.terminate()
                self.proc.join(5.0)
            if self.proc.is_alive():
                self.proc.kill()
                self.proc.join(5.0)
        finally:
            for q in (self.req, self.resp):
                q.cancel_join_thread()
                q.close()


class SlamWorker:
    """The SLAM worker of one site (module docstring).

    ``publish(key, payload, encoding)`` sends a message (the server's session); ``on_map(site)`` makes
    the server use the site's newest stored map and returns its version; ``online()`` lists the devices
    online (live corrections and the tracks sent after a batch run); ``on_added(site, walk_id)`` serves
    a walk just added (corrected) on top of the map version and returns how many walks it took
    (``SlamOptions.grow_map``)."""

    def __init__(
        self,
        db_url: str,
        site: str,
        publish: Publish,
        options: SlamOptions | None = None,
        on_map: Callable[[str], int | None] | None = None,
        online: Callable[[], set[str]] | None = None,
        on_added: Callable[[str, int], int] | None = None,
    ):
        self.db_url, self.site, self.publish = db_url, site, publish
        self.options = options or SlamOptions()
        self.on_map = on_map
        self.on_added = on_added
        self.online = online or (lambda: set())
        self.store = Store(db_url, migrate=False)
        self.counts: Counter = Counter()
        self.last_error: dict | None = None
        self.last_batch: dict | None = None
        self.add_seconds: deque[float] = deque(maxlen=500)
        self.busy = ""
        self._lock = threading.Lock()  # counts and latencies: written here, read by the status queryable
        self._stop = threading.Event()
        self._batch_asked = threading.Event()
        self._thread: threading.Thread | None = None
        self._child: _Child | None = None
        self._attempts: Counter = Counter()
        self._retry_batch_at = 0.0
        self._batch_crashes = 0
        self._map_seen: int | None = None
        self._live: dict[int, tuple[float, float]] = {}  # open walk -> (t_end corrected, monotonic time)
        self._started = m.utcnow()

    # ------------------------------------------------------------ lifecycle
    def start(self) -> SlamWorker:
        self._thread = threading.Thread(target=self._run, name=f"hybridloc-slam-{self.site}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 15.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
            self._thread = None
        self.store.close()

    def request_batch(self) -> None:
        """Re-solve every floor of the site in batch at the next turn of the loop (on demand)."""
        self._batch_asked.set()
        self._retry_batch_at = 0.0

    def _bump(self, key: str, n: int = 1) -> None:
        with self._lock:
            self.counts[key] += n

    def status(self) -> dict:
        """The worker's figures since the server started (``Status.slam[site]["worker"]``)."""
        with self._lock:
            lat = sorted(self.add_seconds)
            counts = dict(self.counts)
        return {
            "counts": counts,
            "busy": self.busy,
            "last_error": self.last_error,
            "last_batch": self.last_batch,
            "walk_add_seconds": {
                "n": len(lat),
                "median": statistics.median(lat) if lat else None,
                "max": lat[-1] if lat else None,
            },
            "in_process": self.options.in_process,
        }

    # ------------------------------------------------------------ the loop
    def _run(self) -> None:
        try:
            if self.store.slam.unfinished_runs(self.site):
                log.info("site %s: an unfinished batch run: resuming it", self.site)
                self._batch_asked.set()
            while not self._stop.is_set():
                worked = False
                try:
                    worked = self._turn()
                except _Stopping:
                    break
                except Exception as exc:  # noqa: BLE001 - the worker keeps going; the ingest never sees it
                    self._bump("errors", 1)
                    self.last_error = {"walk": None, "error": f"{type(exc).__name__}: {exc}", "at": m.utcnow().isoformat()}
                    log.exception("site %s: SLAM worker turn failed", self.site)
                if not worked:
                    self._stop.wait(self.options.poll_s)
        finally:
            self.busy = ""
            if self._child is not None:
                self._child.close()
                self._child = None

    def _turn(self) -> bool:
        n = self.store.close_idle_walks(self.options.idle_timeout_s)
        if n:
            self._bump("walks_closed_idle", n)
        self._check_map()
        if self._batch_due():
            self._batch()
            return True
        pending = self.store.slam.pending_walks(self.site, limit=1)
        if pending:
            self._add(pending[0])
            return True
        return self._live_one()

    def _call(self, name: str, **kwargs) -> Any:
        if self.options.in_process:
            from . import slam_child

            if self.options.child_hook and slam_child._HOOK is None:
                import importlib

                mod, _, fn = self.options.child_hook.partition(":")
                slam_child._HOOK = (getattr(importlib.import_module(mod), fn), self.options.child_hook_arg)
            try:
                return slam_child.CALLS[name](self.store, progress=self._progress, **kwargs)
            except Exception as exc:
                import traceback

                raise ChildError(type(exc).__name__, str(exc), traceback.format_exc()) from exc
        if self._child is None or not self._child.proc.is_alive():
            self._child = _Child(self.db_url, self.site, self.options)
        try:
            return self._child.call(name, self._progress, self._stop, **kwargs)
        except ChildCrashed:
            self._bump("child_crashes", 1)
            self._child.close()
            self._child = None
            raise

    def _progress(self, stage: str, floor: str, done: int, total: int) -> None:
        self.busy = f"batch: {stage} {floor} {done}/{total}".strip()
        self._put(key_progress(self.site), PROGRESS.encode(Progress(self.site, stage, floor, done, total, time.time())), PROGRESS.encoding)

    def _put(self, key: str, payload: bytes, encoding: str) -> None:
        try:
            self.publish(key, payload, encoding)
        except Exception:  # noqa: BLE001 - a closed session at shutdown: nothing to tell
            log.warning("site %s: could not publish on %s", self.site, key, exc_info=True)

    # ------------------------------------------------------------ walks
    def _add(self, walk_id: int) -> None:
        self.busy = f"walk {walk_id}"
        t0 = time.monotonic()
        try:
            out = self._call("add_walk", site=self.site, walk_id=walk_id)
        except (ChildError, ChildCrashed) as exc:
            self._walk_failed(walk_id, exc)
            return
        finally:
            self.busy = ""
        with self._lock:
            self.add_seconds.append(time.monotonic() - t0)
        self._attempts.pop(walk_id, None)
        # served before the walk counts as added: whoever waits for the count finds its labels in service
        if self.options.grow_map and out["status"] == CORRECTED and self.on_added is not None:
            try:
                if self.on_added(self.site, walk_id):
                    self._bump("map_walks_grown", 1)
            except Exception:  # noqa: BLE001 - the map version stays in service
                self._bump("map_grow_errors", 1)
                log.exception("site %s: serving walk %d's labels failed", self.site, walk_id)
        self._bump("walks_added", 1)
        self._bump(f"walks_{out['status']}")
        if out["status"] == "quarantined":
            log.warning("site %s: walk %d quarantined: %s", self.site, walk_id, out["reason"])
        if out["track"] is not None:
            self._put(key_track(self.site, out["device"]), out["track"], TRACK.encoding)
            self._bump("tracks_published", 1)
        self._live.pop(walk_id, None)

    def _walk_failed(self, walk_id: int, exc: Exception) -> None:
        self._attempts[walk_id] += 1
        n = self._attempts[walk_id]
        self._bump("walk_errors", 1)
        self.last_error = {"walk": walk_id, "error": str(exc), "at": m.utcnow().isoformat()}
        detail = "\n" + exc.tb if isinstance(exc, ChildError) else ""
        log.error("site %s: SLAM of walk %d failed (attempt %d of %d)%s", self.site, walk_id, n, self.options.max_attempts, detail, exc_info=exc)
        if n >= self.options.max_attempts:
            self.store.slam.mark_walk(self.site, walk_id, FAILED, f"{n} attempts: {exc}")
            self._bump("walks_failed", 1)
            self._attempts.pop(walk_id, None)

    def _open_walks(self) -> list[tuple[int, str, float, float]]:
        with Session(self.store.engine) as s:
            q = select(m.Walk.id, m.Walk.device_id, m.Walk.t_start, m.Walk.t_end).where(
                m.Walk.site_id == self.site, m.Walk.end_reason == WalkEnd.OPEN.value
            )
            return [(int(a), str(b), float(c), float(d)) for a, b, c, d in s.execute(q)]

    def _live_one(self) -> bool:
        every = self.options.live_every_s
        if not every:
            return False
        online = self.online()
        if not online:
            return False
        now = time.monotonic()
        walks = self._open_walks()
        open_ids = {w[0] for w in walks}
        for wid in [w for w in self._live if w not in open_ids]:
            del self._live[wid]
        best, backlog = None, 0.0
        for wid, dev, t0, t1 in walks:
            if dev not in online:
                continue
            t_done, wall = self._live.get(wid, (t0, -1e18))
            if t1 - t_done >= every and now - wall >= every and t1 - t_done > backlog:
                best, backlog = (wid, dev), t1 - t_done
        if best is None:
            return False
        wid, dev = best
        self.busy = f"live walk {wid}"
        try:
            out = self._call("provisional", site=self.site, walk_id=wid)
        except (ChildError, ChildCrashed) as exc:
            self._bump("live_errors", 1)
            log.warning("site %s: provisional correction of open walk %d failed: %s", self.site, wid, exc)
            self._live[wid] = (self._live.get(wid, (0.0, 0.0))[0], time.monotonic())
            return True
        finally:
            self.busy = ""
        self._live[wid] = (float(out["t_end"]), time.monotonic())
        if out["track"] is not None:
            self._put(key_track(self.site, dev), out["track"], TRACK.encoding)
            self._bump("live_tracks_published", 1)
        return True

    # ------------------------------------------------------------ batch runs
    def _since_last_batch(self) -> tuple[int, dt.datetime, int]:
        """(walks added since the newest complete batch run, when it finished - or when the worker started,
        the walks it solved: 0 without one)."""
        with Session(self.store.engine) as s:
            last = s.execute(
                select(m.SlamRun.id, m.SlamRun.finished_at, m.SlamRun.stats)
                .where(m.SlamRun.site_id == self.site, m.SlamRun.kind == "batch", m.SlamRun.status == "complete")
                .order_by(m.SlamRun.id.desc())
                .limit(1)
            ).first()
            cond = [m.SlamRun.site_id == self.site, m.SlamRun.kind == "walk"]
            if last is not None:
                cond.append(m.SlamRun.id > last[0])
            n = s.execute(select(func.count()).select_from(m.SlamRun).where(*cond)).scalar_one()
        when = last[1] if last is not None and last[1] is not None else self._started
        if when.tzinfo is None:
            when = when.replace(tzinfo=dt.UTC)
        solved = (last[2] or {}).get("walks", {}) if last is not None else {}
        return int(n), when, int(sum(solved.values())) if isinstance(solved, dict) else 0

    def _batch_due(self) -> bool:
        if time.monotonic() < self._retry_batch_at:
            return False
        if self._batch_asked.is_set() or self.store.slam.unfinished_runs(self.site):
            return True  # asked for, or a run to resume (killed midway, here or in another process)
        n, since, solved = self._since_last_batch()
        if n == 0:
            return False
        o = self.options
        if o.batch_every_walks and n >= max(o.batch_every_walks, o.batch_share * solved):
            return True
        return bool(o.batch_interval_s) and (m.utcnow() - since).total_seconds() >= o.batch_interval_s

    def _batch(self) -> None:
        self._batch_asked.clear()
        self.busy = "batch"
        t0 = time.monotonic()
        try:
            out = self._call(
                "batch",
                site=self.site,
                floors=None,
                online=sorted(self.online()),
                lease_s=self.options.lease_s,
                processes=self.options.batch_process_count(),
            )
        except (ChildError, ChildCrashed) as exc:
            self._retry_batch_at = time.monotonic() + self.options.retry_s
            if isinstance(exc, ChildError) and exc.name == "SlamBusy":
                self._bump("batch_busy", 1)
                log.info("site %s: batch re-solve not started: %s", self.site, exc.message)
                return
            if isinstance(exc, ChildError) and exc.name == "MissingData":
                return  # no ended walk with a floor yet
            if isinstance(exc, ChildCrashed):
                self._batch_crashes += 1
                if self._batch_crashes >= self.options.max_attempts:
                    # the same run kills the child every time: give it up (the previous map stays)
                    for r in self.store.slam.unfinished_runs(self.site):
                        self.store.slam.fail_run(r.run_id, f"the SLAM child process died {self._batch_crashes} times solving it")
                    self._batch_crashes = 0
            self._bump("batch_failures", 1)
            self.last_error = {"walk": None, "error": f"batch re-solve: {exc}", "at": m.utcnow().isoformat()}
            log.error("site %s: batch re-solve failed: %s%s", self.site, exc, "\n" + exc.tb if isinstance(exc, ChildError) else "")
            return
        finally:
            self.busy = ""
        self._batch_crashes = 0
        sm = out["summary"]
        self._bump("batch_runs", 1)
        self.last_batch = {k: sm[k] for k in ("run_id", "resumed", "floors", "floors_skipped", "walks", "map_version", "coverage", "seconds")}
        log.info(
            "site %s: batch run %d %s in %.1f s: walks %s, map version %s",
            self.site,
            sm["run_id"],
            "resumed and completed" if sm["resumed"] else "completed",
            time.monotonic() - t0,
            sm["walks"],
            sm["map_version"],
        )
        self._check_map()
        for dev, payload in out["tracks"].items():
            self._put(key_track(self.site, dev), payload, TRACK.encoding)
            self._bump("tracks_published", 1)

    # ------------------------------------------------------------ maps
    def _map_row(self) -> tuple[int | None, Any]:
        with Session(self.store.engine) as s:
            row = s.execute(
                select(m.RadioMapVersion.version, m.RadioMapVersion.source, m.RadioMapVersion.created_at, m.RadioMapVersion.provenance)
                .where(m.RadioMapVersion.site_id == self.site)
                .order_by(m.RadioMapVersion.version.desc())
                .limit(1)
            ).first()
        return (None, None) if row is None else (int(row[0]), row)

    def _check_map(self) -> None:
        """A newer stored map version (this worker's batch run or anyone's): serve it and announce it."""
        version, row = self._map_row()
        if version is None or version == self._map_seen:
            return
        self._map_seen = version
        if self.on_map is not None:
            self.on_map(self.site)
        prov = row[3] or {}
        created = row[2].replace(tzinfo=dt.UTC) if row[2].tzinfo is None else row[2]
        msg = MapVersion(self.site, version, str(row[1]), created.timestamp(), len(prov.get("walks", []) or []), prov.get("coverage"))
        self._put(key_map_version(self.site), MAP_VERSION.encode(msg), MAP_VERSION.encoding)
        self._bump("maps_announced", 1)
        log.info("site %s: radio map version %d (%s) in service", self.site, version, row[1])

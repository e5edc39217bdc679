"""Zenoh to the dashboard's event loop: subscriptions and the status poll.

The dashboard listens to exactly what a read-only operator may hear (:data:`hybridloc.wire.zconfig.
OPERATOR_HEARS`: every device's pose, fix and corrected track, every site's progress and new map
versions) and asks the servers' status every :attr:`Feed.status_every_s` seconds (online devices,
rejections per device, map versions, SLAM figures).

Zenoh runs the callbacks on its own threads. Each callback decodes the payload there (the codecs are
the only validation; a refused payload is counted and dropped) and hands the record to the loop with
``loop.call_soon_threadsafe``, which never blocks: the Zenoh thread goes back to the network at once,
whatever the loop is doing (records queued while a wake-up is pending ride on it: see
:meth:`Feed._hand_over`). After the loop is closed a late sample is dropped.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import Counter, deque

import zenoh

from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.zconfig import OPERATOR_HEARS

from .live import Hub

log = logging.getLogger("hybridloc.dashboard")


class Feed:
    """Subscriptions on ``session`` feeding ``hub`` on ``loop``; start() and stop() from any thread."""

    def __init__(self, session: zenoh.Session, hub: Hub, status_every_s: float = 2.0, status_timeout_s: float = 3.0):
        self.session = session
        self.hub = hub
        self.status_every_s = status_every_s
        self.status_timeout_s = status_timeout_s
        self.counts: Counter = Counter()  # decoded / refused by kind (read by tests and the log)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._subs: list = []
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None
        self._queue: deque = deque()
        self._wake_pending = False

    def start(self, loop: asyncio.AbstractEventLoop) -> Feed:
        self._loop = loop
        self._subs = [self.session.declare_subscriber(k, self._on_sample) for k in OPERATOR_HEARS]
        self._poller = threading.Thread(target=self._poll_status, name="hybridloc-dashboard-status", daemon=True)
        self._poller.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for s in self._subs:
            try:
                s.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closed already
                pass
        self._subs.clear()
        if self._poller is not None:
            self._poller.join(timeout=self.status_timeout_s + 2)
        self._loop = None

    def _hand_over(self, fn, *args) -> None:
        """Queue ``fn(*args)`` for the loop and wake it with ``call_soon_threadsafe`` unless a wake-up is
        already pending: one loop wake-up drains every record queued meanwhile (at 300 poses/s most
        records ride on a wake-up already scheduled). No lock: ``deque.append`` and ``popleft`` are
        atomic, and the drain clears the flag *before* it empties the queue, so a record appended
        after the last ``popleft`` always finds the flag clear and schedules a new drain."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        self._queue.append((fn, args))
        if self._wake_pending:
            return
        self._wake_pending = True
        try:
            loop.call_soon_threadsafe(self._drain)
        except RuntimeError:  # the loop closed in between
            pass

    def _drain(self) -> None:
        """On the loop: apply every queued record, in arrival order."""
        self._wake_pending = False
        q = self._queue
        while q:
            fn, args = q.popleft()
            try:
                fn(*args)
            except Exception:  # noqa: BLE001 - one bad record must not drop the others
                self.counts["apply-errors"] += 1
                log.exception("dashboard: applying a record failed")

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """On a Zenoh thread: decode, then hand over (never waits for the loop)."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        key = str(sample.key_expr)
        parts = key.split("/")
        received = time.time()
        try:
            payload = sample.payload.to_bytes()
            if len(parts) == 5:  # hl/v1/<site>/<device>/<kind>
                site, device, kind = P.parse_key(key)
                if kind == "pose":
                    self._hand_over(self.hub.apply_pose, site, device, C.POSE.decode(payload), received)
                elif kind == "fix":
                    self._hand_over(self.hub.apply_fix, site, device, C.FIX.decode(payload), received)
                elif kind == "track":
                    self._hand_over(self.hub.apply_track, site, device, C.TRACK.decode(payload, site, device))
                elif kind == "version" and device == "map":  # hl/v1/<site>/map/version
                    mv = C.MAP_VERSION.decode(payload)
                    if mv.site == parts[2]:
                        self._hand_over(self.hub.apply_map_version, mv)
                else:
                    return
            elif len(parts) == 4 and parts[3] == "progress":
                pr = C.PROGRESS.decode(payload)
                if pr.site == parts[2]:
                    self._hand_over(self.hub.apply_progress, pr)
            self.counts[parts[-1]] += 1
        except (P.Rejected, ValueError) as exc:
            self.counts[f"refused:{getattr(exc, 'reason', 'bad-key')}"] += 1

    def _poll_status(self) -> None:
        while not self._stop.is_set():
            try:
                replies = self.session.get(
                    P.KEY_STATUS, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=self.status_timeout_s
                )
                statuses = []
                for r in replies:
                    if r.ok is None:
                        continue
                    try:
                        statuses.append(C.STATUS.decode(r.ok.payload.to_bytes()))
                    except P.Rejected as exc:
                        self.counts[f"refused:status:{exc.reason}"] += 1
                if statuses:
                    self._hand_over(self.hub.apply_statuses, statuses)
                    self.counts["status"] += 1
            except zenoh.ZError:
                if self._stop.is_set():
                    return
                log.debug("status query failed", exc_info=True)
            except Exception:  # noqa: BLE001 - a failing poll must not end the dashboard
                log.warning("status query failed", exc_info=True)
            self._stop.wait(self.status_every_s)

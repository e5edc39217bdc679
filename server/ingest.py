"""One group of batch messages, from their bytes to what the server answers: decoded and validated,
persisted in one transaction, and the acknowledgements and scans to locate that follow.

The server runs it in its ingest thread (:meth:`.service.Server._ingest`) or, with ``serve
--ingest-workers N``, in worker processes (:mod:`.ingest_pool`); the same function either way, so the
database holds the same rows and the clients hear the same answers.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import NamedTuple

from sqlalchemy import exc as sa_exc

from hybridloc.types import RfScan, Technology
from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P

from .db import retry_unique
from .store import Store

log = logging.getLogger("hybridloc.server")


class Stopping(Exception):
    """The server stopped while ingest waited for the database."""


def with_database(fn: Callable, counts: Counter, stopping, lock: threading.Lock | None = None):
    """``fn()``, retried while the database is unreachable (PostgreSQL stopped or restarting, a network
    cut, SQLite locked past its busy timeout): each failed transaction rolled back whole, so a retry
    never doubles (a commit whose answer was lost finds its batches stored and counts them as
    duplicates, go-back-N). Backs off 0.1 s doubling to 2 s; nothing is acknowledged meanwhile, so the
    devices keep their spools. Counts ``db-retries`` and ``db-outages`` into ``counts`` (under ``lock``
    when given: other threads count into it too); raises :class:`Stopping` once ``stopping`` (a
    threading or multiprocessing Event) is set."""
    delay, down_since = 0.1, None
    while True:
        try:
            out = fn()
        except (sa_exc.OperationalError, sa_exc.InterfaceError) as exc:
            with lock or nullcontext():
                counts["db-retries"] += 1
                if down_since is None:
                    counts["db-outages"] += 1
            if down_since is None:
                down_since = time.monotonic()
                log.warning("database unreachable, ingest waits and retries: %s", str(exc).splitlines()[0][:200])
            if stopping.wait(delay):
                raise Stopping from None
            delay = min(2.0, 2 * delay)
            continue
        if down_since is not None:
            log.warning("database back after %.1f s; ingest resumes", time.monotonic() - down_since)
        return out


class BatchRef(NamedTuple):
    """The batch a scan to locate came in: its site and device (where the answer goes)."""

    site: str
    device: str


@dataclass
class IngestResult:
    """What a group's ingest leaves to do, and its counts.

    ``acks``: (site, device, highest persisted seq) to publish, in order; ``asked``: (batch, its newest
    WiFi scan) of each batch stored now, to locate; ``counts``: message counts by kind and rejection
    reason (``batches-received``, ``batches-persisted``, ``rejected:<reason>``, ``db-retries`` ...)."""

    acks: list[tuple[str, str, int]] = field(default_factory=list)
    asked: list[tuple[BatchRef, RfScan]] = field(default_factory=list)
    counts: Counter = field(default_factory=Counter)


def ingest_group(store: Store, items: list[tuple[str, bytes]], with_database: Callable, counts: Counter | None = None) -> IngestResult:
    """Ingest ``items`` (key expression, payload) as one group: every message decoded and validated, the
    group persisted in one transaction by ``with_database(fn)`` (which retries ``fn`` while the database
    is away), then the acknowledgements and the scans to answer listed. ``counts``, when given, is the
    result's counter (counted into as the group goes: what was received counts even if storing fails)."""
    out = IngestResult(counts=Counter() if counts is None else counts)
    batches, bad = [], Counter()
    for key, payload in items:
        try:
            site, device, _ = P.parse_key(key)
        except ValueError:
            bad[("?", "bad-key")] += 1
            continue
        try:
            batches.append(C.BATCH.decode(payload, site, device))
            out.counts["batches-received"] += 1
        except P.Rejected as rej:
            bad[(device, rej.reason)] += 1
    new_ids: list[tuple[str, int]] = []

    def persist():
        new_ids.clear()  # a failed attempt may have listed batches its rollback took back
        return store.persist(batches, bad, written_ids=new_ids)

    # retry_unique: another writer (a second ingest worker, a server of other sites) may add a new
    # site's row beside ours; the transaction rolled back, the next attempt finds it
    acked, rejected, written = with_database(lambda: retry_unique(persist))
    for (_, reason), n in rejected.items():
        out.counts[f"rejected:{reason}"] += n
    out.counts["batches-persisted"] += written
    site_of = {b.device: b.site for b in batches}
    out.acks = [(site_of[device], device, seq) for device, seq in acked.items()]
    # answer the newest WiFi scan of each batch that brought one: a fix, or "no fix" with the
    # reason (no map for the site, no known transmitter...), so a client always hears back.
    # Only batches stored now are answered: a resent duplicate was answered when it was stored,
    # and answering it again made the client fuse the same fix twice and count one answer too
    # many. The server's locate worker answers them, after the acknowledgements.
    stored = set(new_ids)
    for b in batches:
        if (b.device, b.seq) not in stored:
            continue
        # a resend in the same group as its original is a duplicate of it: answered once
        stored.discard((b.device, b.seq))
        scans = [sc for sc in b.scans if sc.technology is Technology.WIFI]
        if scans:
            # the decoded scan carries the batch's device model (the locators' per-device RSSI offset)
            out.asked.append((BatchRef(b.site, b.device), scans[-1]))
    return out

"""Reliable uplink from a client to the server: sequence-numbered batches, a spool on disk, resend.

Every batch gets the device's next sequence number and is written to the spool folder (one JSON file
per batch, written atomically) *before* it is published. The server acknowledges the highest batch it
has persisted; acknowledged files are deleted. Unacknowledged batches are published again, in order
from the oldest, when the acknowledgement does not advance for the retransmission timeout (a lost
message, a server restart, a reconnect): TCP's adaptive timeout (:mod:`hybridloc.wire.retransmit`),
at least ``resend_after`` seconds, longer when acknowledgements are slow, doubling after each resend,
so a loaded server is not flooded with copies of what it is still working through. The server keeps only the next batch in sequence, so a resend
can neither duplicate nor reorder data. The spool survives the client process, so a restarted client
continues its sequence where it stopped.

A full spool (the disk out of space, or ``max_spool_bytes`` reached) keeps the newest data: the
oldest unacknowledged batches are hollowed out, each replaced by an empty batch under the same
sequence number (so the server's go-back-N stream stays whole and nothing newer waits for a batch
that will never come), and their steps, scans and marks are counted in :attr:`Uplink.dropped` and
logged. A batch that cannot be written even then is kept in memory and sent (``dropped["unspooled"]``):
it survives a lost message, not a restart of the client.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import threading
import time
from collections import Counter
from pathlib import Path

import zenoh

from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import Batch
from hybridloc.wire.retransmit import RetransmitTimer

log = logging.getLogger("hybridloc.clients.uplink")
#: the errors of a full disk or quota
_FULL = (errno.ENOSPC, errno.EDQUOT)
#: the smallest spool cap: one batch's worth
MIN_SPOOL_BYTES = 4096


class Uplink:
    def __init__(
        self,
        session: zenoh.Session,
        site: str,
        device: str,
        spool_dir: str | os.PathLike,
        device_model: str = "",
        resend_after: float = 2.0,
        max_spool_bytes: int | None = None,
        step_columns_from: int | None = None,
    ):
        self.session = session
        #: batches of at least this many steps are sent with their steps in the columnar form (docs/protocol.md,
        #: "Step columns": a fraction of the encoding and decoding time, read by servers since it exists and
        #: refused by older ones); None: never, today's bytes
        self.step_columns_from = step_columns_from
        self.site, self.device = P.check_id(site, "site"), P.check_id(device, "device")
        self.device_model = device_model
        self.spool = Path(spool_dir)
        self.spool.mkdir(parents=True, exist_ok=True)
        self.resend_after = resend_after
        if max_spool_bytes is not None and max_spool_bytes < MIN_SPOOL_BYTES:
            raise ValueError(f"max_spool_bytes {max_spool_bytes} is below one batch's worth ({MIN_SPOOL_BYTES})")
        self.max_spool_bytes = max_spool_bytes
        #: what a full spool dropped: "batches" hollowed out, their "steps", "scans", "marks"; "unspooled"
        self.dropped: Counter = Counter()
        self._memory: dict[int, bytes] = {}  # batches no disk would take, until acknowledged
        self._lock = threading.Lock()
        self.acked = self._read_state().get("acked", 0)
        existing = sorted(int(p.stem) for p in self.spool.glob("*.json") if p.stem.isdigit())
        self.next_seq = max([self.acked] + existing) + 1
        self._last_progress = time.monotonic()
        self.n_resent = 0
        #: the retransmission timeout (RFC 6298): floor ``resend_after``
        self.timer = RetransmitTimer(resend_after)
        self._first_sent: dict[int, float] = {}  # seq -> monotonic time of its first send
        self._resent: set[int] = set()  # seqs sent more than once (Karn: their acks give no RTT sample)
        self._key = P.key_batch(site, device)
        self._ack_sub = session.declare_subscriber(P.key_ack(site, device), self._on_ack)
        self._acked_event = threading.Condition(self._lock)

    # ------------------------------------------------------------ state
    def _state_path(self) -> Path:
        return self.spool / "state.json"

    def _read_state(self) -> dict:
        try:
            return json.loads(self._state_path().read_text())
        except (OSError, ValueError):
            return {}

    def _write_state(self) -> None:
        tmp = self._state_path().with_suffix(".tmp")
        tmp.write_text(json.dumps({"acked": self.acked, "device": self.device, "site": self.site}))
        os.replace(tmp, self._state_path())

    @property
    def pending(self) -> int:
        return self.next_seq - 1 - self.acked

    # ------------------------------------------------------------ sending
    def send(self, steps=(), scans=(), marks=(), end_of_walk: bool = False) -> int:
        """Spool and publish one batch of StepEvent, RfScan and SurveyMark records; returns its sequence
        number. ``end_of_walk``: the walk ends with this batch (the server closes it at once)."""
        with self._lock:
            seq = self.next_seq
            self.next_seq += 1
            columns = self.step_columns_from is not None and len(steps) >= self.step_columns_from
            batch = Batch(self.site, self.device, seq, self.device_model, steps, scans, marks, time.time(), end_of_walk)
            payload = C.BATCH.encode(batch, step_columns=columns)
            if len(payload) > P.MAX_BATCH_BYTES:
                raise ValueError(f"batch of {len(payload)} bytes exceeds the protocol limit {P.MAX_BATCH_BYTES}: send smaller batches")
            self._spool(seq, payload)
            now = time.monotonic()
            if self.pending == 1:  # the first unacknowledged batch starts the timer (not an old ack)
                self._last_progress = now
            self._first_sent[seq] = now
        self._put(payload)
        return seq

    # ------------------------------------------------------------ the spool
    def _pending_files(self) -> list[Path]:
        return sorted(p for p in self.spool.glob("*.json") if p.stem.isdigit() and int(p.stem) > self.acked)

    def _write(self, path: Path, payload: bytes) -> None:
        tmp = path.with_suffix(".tmp")
        try:
            tmp.write_bytes(payload)
            os.replace(tmp, path)
        except OSError:
            tmp.unlink(missing_ok=True)
            raise

    def _spool(self, seq: int, payload: bytes) -> None:
        """Write batch ``seq`` before it is sent; on a full spool hollow out the oldest (lock held)."""
        path = self.spool / f"{seq:012d}.json"
        if self.max_spool_bytes is not None:
            used = sum(p.stat().st_size for p in self._pending_files())
            if used + len(payload) > self.max_spool_bytes:
                self._hollow(used + len(payload) - self.max_spool_bytes)
        try:
            self._write(path, payload)
            return
        except OSError as exc:
            if exc.errno not in _FULL:
                raise
        self._hollow(len(payload))  # the disk is full: free what the new batch needs, oldest first
        try:
            self._write(path, payload)
        except OSError as exc:
            if exc.errno not in _FULL:
                raise
            self._memory[seq] = payload
            self.dropped["unspooled"] += 1
            log.warning("%s: spool full, batch %d kept in memory only", self.device, seq)

    def _hollow(self, need: int) -> None:
        """Replace the oldest unacknowledged batches by empty ones under the same numbers until ``need``
        bytes are free; count what they carried."""
        freed = 0
        for p in self._pending_files():
            if freed >= need:
                break
            old = p.read_bytes()
            try:
                b = C.BATCH.decode(old)
            except P.Rejected:
                continue
            if not (b.steps or b.scans or b.marks):
                continue  # already hollow
            empty = C.BATCH.encode(Batch(b.site, b.device, b.seq, b.device_model, (), (), (), b.sent_at, b.end_of_walk))
            p.unlink()  # first: on a full disk the empty one needs the space this frees
            self._write(p, empty)
            freed += len(old) - len(empty)
            self.dropped.update(batches=1, steps=len(b.steps), scans=len(b.scans), marks=len(b.marks))
            log.warning(
                "%s: spool full, the data of batch %d dropped (%d steps, %d scans, %d marks) to keep the newest",
                self.device,
                b.seq,
                len(b.steps),
                len(b.scans),
                len(b.marks),
            )

    def _put(self, payload: bytes) -> None:
        # session.put (a declared publisher works too since the device ACL lets the device see the
        # server's batch subscription: docs/protocol.md, "Sending batches"); put has no matching state
        # to wait for, so a fresh session's first batch goes out at once.
        self.session.put(self._key, payload, encoding=C.BATCH.encoding, congestion_control=zenoh.CongestionControl.BLOCK)

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            seq = C.ACK.decode(sample.payload.to_bytes()).acked_seq
        except P.Rejected:
            return
        with self._lock:
            if seq > self.acked:
                now = time.monotonic()
                if seq in self._first_sent and seq not in self._resent:
                    self.timer.sample(now - self._first_sent[seq])
                for s in range(self.acked + 1, seq + 1):
                    self._first_sent.pop(s, None)
                    self._resent.discard(s)
                    self._memory.pop(s, None)
                    try:
                        (self.spool / f"{s:012d}.json").unlink()
                    except FileNotFoundError:
                        pass
                self.acked = seq
                self._write_state()
                self._last_progress = now
                self._acked_event.notify_all()

    def resend_if_stalled(self) -> int:
        """Publish the unacknowledged batches again (oldest first) if the ack has not moved for the
        retransmission timeout; the timeout then doubles (up to its maximum) until an ack comes."""
        with self._lock:
            if self.pending == 0 or time.monotonic() - self._last_progress < self.timer.rto:
                return 0
            files = {int(p.stem): p for p in self._pending_files()}
            memory = {k: v for k, v in self._memory.items() if k > self.acked}
            self._last_progress = time.monotonic()
            self._resent.update(set(files) | set(memory))
            self.timer.backoff()
        n = 0
        for seq in sorted(set(files) | set(memory)):
            if seq in memory:
                payload = memory[seq]
            else:
                try:
                    payload = files[seq].read_bytes()
                except FileNotFoundError:  # acknowledged (and deleted) since the listing: nothing to resend
                    continue
            self._put(payload)
            n += 1
        self.n_resent += n
        return n

    def wait_connected(self, timeout: float = 10.0) -> bool:
        """Wait until the server is reachable (its status queryable answers)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(r.ok for r in self.session.get(P.KEY_STATUS, timeout=1.0)):
                return True
            time.sleep(0.1)
        return False

    def wait_acked(self, seq: int | None = None, timeout: float = 10.0) -> bool:
        """Block until batch ``seq`` (default: every batch sent) is acknowledged, resending on stalls."""
        target = self.next_seq - 1 if seq is None else seq
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                if self.acked >= target:
                    return True
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._acked_event.wait(min(left, 0.2))
            self.resend_if_stalled()

    def close(self) -> None:
        try:
            self._ack_sub.undeclare()
        except Exception:  # noqa: BLE001 - already closed with its session
            pass

"""Live load: many phone clients at their real step and scan rates through real Zenoh on loopback.

    python -m benchmarks.bench_load [--clients 1000] [--minutes 10] [--db sqlite|postgres|URL] [--sessions N] [--window S] [--locate-workers N]
        [--ingest-workers N|auto]

The server is ``hybridloc serve`` in its own process, serving a real radio map of site1 F1 built from
the bundled sample's surveys (``hybridloc/data/ilc_site1_F1``), so every scan costs a real locate.
The load generator speaks only the protocol (docs/protocol.md): each simulated phone sends one
batch per simulated second (2 steps, and a real site1 F1 WiFi scan every 2 s), numbered from 1, and
resends what is unacknowledged when its ack stalls for the retransmission timeout (go-back-N with
RFC 6298's adaptive timeout, at least 2 s, as the client agent does; ``--fixed-resend`` keeps the
timeout at 2 s, as clients before it did).
Devices are spread over ``--sessions`` Zenoh client sessions (default one per 20 devices; a session
per device is what a phone has, but a thousand sessions in one process measure the generator).

Time is compressed as far as the machine allows: the simulated clock advances one second when no
device is more than ``--window`` simulated seconds behind on acknowledgements, so ``realtime_factor``
(simulated seconds per wall second) >= 1 means the server held real time. Compressed, the latencies
include the backlog the window allows (up to ``--window`` simulated seconds of batches in flight);
``--speed 1`` paces the clock at real time, where they are what a phone would see. Printed: steps/s and scans/s
stored, acknowledgement latency p50/p99 (first send of a batch to the ack that covers it), fixes
answered and their latency (batch sent to fix received), the server's peak memory, and lost /
doubled counted in the database against what the clients sent. The last line is one JSON object.

Faults during the load (issue #23 point 4, the long form of tests/test_server_faults.py), each
``--fault KIND@SECOND[:DOWN]`` (repeatable; SECOND is the simulated second it starts at, DOWN the wall
seconds it lasts):

- ``server-kill``: the server SIGKILLed and started again on the same endpoint and database after DOWN
  (default 0) seconds;
- ``clients-drop``: ``--drop-fraction`` of the Zenoh sessions (default 0.2) closed for DOWN (default 10)
  seconds, then opened afresh; their devices keep their unacknowledged batches (a phone's spool) and
  resend them at once when they are back;
- ``db-outage``: PostgreSQL paused for DOWN (default 10) seconds (``--db postgres`` only).

For each it prints how long after its end the first acknowledgement arrived (``first_ack_s``) and when
every batch sent before its end was acknowledged (``caught_up_s``); lost and doubled are counted over
the whole run as always. (The client spool's full-disk fault is the client agent's, which this generator
is not: tests/test_server_faults.py covers it.)
"""

from __future__ import annotations

import argparse
import gc
import json
import shutil
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from benchmarks.bench_server import _serve
from hybridloc.wire.retransmit import MAX_RTO_S, RetransmitTimer
from hybridloc.wire.zconfig import free_port

SITE = "site1"
STEP_T = (0.25, 0.75)  # two steps per simulated second, ~0.7 m: a walker at 1.4 m/s
SCAN_EVERY_S = 2
RESEND_AFTER_S = 2.0
FAULT_KINDS = {"server-kill": 0.0, "clients-drop": 10.0, "db-outage": 10.0}  # kind: default DOWN seconds


def parse_fault(text: str) -> tuple[str, int, float]:
    """``KIND@SECOND[:DOWN]`` -> (kind, simulated second, wall seconds down); ValueError when malformed."""
    kind, sep, rest = text.partition("@")
    if not sep or kind not in FAULT_KINDS:
        raise ValueError(f"fault {text!r}: expected KIND@SECOND[:DOWN] with KIND one of {', '.join(FAULT_KINDS)}")
    at, _, down = rest.partition(":")
    try:
        sec, dur = int(at), float(down) if down else FAULT_KINDS[kind]
    except ValueError:
        raise ValueError(f"fault {text!r}: SECOND must be an integer and DOWN a number of seconds") from None
    if sec < 0 or not 0.0 <= dur <= 600.0:
        raise ValueError(f"fault {text!r}: SECOND must be >= 0 and DOWN within 0-600 s")
    return kind, sec, dur


def _map_and_scans(tmp: Path) -> tuple[Path, list]:
    """A real site1 F1 radio map from the bundled surveys, and the real WiFi scans to replay."""
    from hybridloc.radio.radiomap import build_radio_map
    from hybridloc.radio.sources import labelled_from_inputs
    from hybridloc.samples import ILC_SITE1_F1

    walks = sorted(str(p) for p in (ILC_SITE1_F1 / "F1" / "path_data_files").glob("*"))
    labelled, plan, _ = labelled_from_inputs("msft", walks, None)
    rmap = build_radio_map(labelled, site=SITE, plan=plan)
    path = tmp / "site1_F1.npz"
    rmap.save(path)
    return path, [ls.scan for ls in labelled]


def _peak_rss_mb(pid: int) -> float:
    try:
        for ln in Path(f"/proc/{pid}/status").read_text().splitlines():
            if ln.startswith("VmHWM:"):
                return int(ln.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _children_peak_rss_mb(pid: int) -> float:
    """The summed peak memory of ``pid``'s child processes (the server's ingest and locate workers):
    an upper bound of what they held at once."""
    total = 0.0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:  # field 4 of /proc/PID/stat (after "pid (comm)"): the parent's pid
            peak = _peak_rss_mb(int(stat.parent.name))
            total += peak if peak == peak else 0.0
    return total


class _Load:
    """The simulated phones' state: what each sent, when, and what came back."""

    def __init__(self, devices: list[str], fixed_resend: bool = False):
        self.lock = threading.Lock()
        self.devices = devices
        self.acked = dict.fromkeys(devices, 0)
        self.sent_wall: dict[str, dict[int, float]] = defaultdict(dict)  # first send of each seq
        self.payloads: dict[str, dict[int, bytes]] = defaultdict(dict)  # unacknowledged
        self.last_progress = dict.fromkeys(devices, time.monotonic())
        self.timers = {d: RetransmitTimer(RESEND_AFTER_S, RESEND_AFTER_S if fixed_resend else MAX_RTO_S) for d in devices}
        self.resent: dict[str, set[int]] = defaultdict(set)  # Karn: a resent batch's ack gives no sample
        self.ack_lat: list[float] = []
        self.scan_sent: dict[tuple[str, float], float] = {}
        self.fix_lat: list[float] = []
        self.fixes = self.no_fix = self.resends = 0
        self.misrouted = 0  # samples a callback got for a key it did not declare, or with another key's payload
        self.down: set[str] = set()  # devices whose session is closed (a clients-drop fault): they only spool

    def on_ack(self, sample) -> None:
        from hybridloc.wire import codecs as C
        from hybridloc.wire import protocol as P

        now = time.monotonic()
        if not str(sample.key_expr).endswith("/ack"):
            with self.lock:  # callbacks run on several of Zenoh's threads
                self.misrouted += 1  # seen: a few samples of another key handed to this callback
            return
        try:
            a = C.ACK.decode(sample.payload.to_bytes())
        except P.Rejected:  # seen under load: another key's payload (a fix) on this key
            with self.lock:
                self.misrouted += 1
            return
        with self.lock:
            old = self.acked.get(a.device)
            if old is None or a.acked_seq <= old:
                return
            sent = self.sent_wall[a.device]
            if a.acked_seq in sent and a.acked_seq not in self.resent[a.device]:
                self.timers[a.device].sample(now - sent[a.acked_seq])
            for s in range(old + 1, a.acked_seq + 1):
                t = sent.pop(s, None)
                if t is not None:
                    self.ack_lat.append(now - t)
                self.payloads[a.device].pop(s, None)
                self.resent[a.device].discard(s)
            self.acked[a.device] = a.acked_seq
            self.last_progress[a.device] = now

    def on_fix(self, sample) -> None:
        from hybridloc.wire import codecs as C
        from hybridloc.wire import protocol as P

        now = time.monotonic()
        if not str(sample.key_expr).endswith("/fix"):
            with self.lock:
                self.misrouted += 1
            return
        device = str(sample.key_expr).split("/")[3]
        try:
            f = C.FIX.decode(sample.payload.to_bytes())
        except P.Rejected:  # seen under load: an ack's payload on a fix key
            with self.lock:
                self.misrouted += 1
            return
        t = f.fix.t if f.fix is not None else f.t
        with self.lock:
            if f.fix is not None:
                self.fixes += 1
            else:
                self.no_fix += 1
            t0 = self.scan_sent.pop((device, t), None)
            if t0 is not None:
                self.fix_lat.append(now - t0)


class _Faults:
    """The run's scheduled faults (:func:`parse_fault`): started at their simulated second, ended after
    their wall seconds down, and timed until the load has recovered from each."""

    def __init__(self, plan: list[tuple[str, int, float]], load: _Load, ctl: dict):
        self.todo = sorted(plan, key=lambda f: f[1])
        self.load, self.ctl = load, ctl  # ctl: kill, start, drop (-> devices), reopen, pause, resume
        self.ongoing: list[dict] = []  # started, not ended
        self.watch: list[dict] = []  # ended, not yet caught up
        self.done: list[dict] = []
        self.sent = 0  # the newest batch every device has been given (sent, or spooled while dropped)

    def active(self) -> bool:
        return bool(self.ongoing or self.watch)

    def start_due(self, sec: int, last_seq: int) -> None:
        while self.todo and self.todo[0][1] <= sec:
            kind, at, down = self.todo.pop(0)
            f = {"kind": kind, "at_s": at, "down_s": down, "t0": time.monotonic(), "devices": None}
            if kind == "server-kill":
                self.ctl["kill"]()
            elif kind == "clients-drop":
                f["devices"] = self.ctl["drop"]()
            else:
                self.ctl["pause"]()
            f["last_seq"] = last_seq
            self.ongoing.append(f)
        self.poll()

    def poll(self) -> None:
        now = time.monotonic()
        for f in [f for f in self.ongoing if now - f["t0"] >= f["down_s"]]:
            self.ongoing.remove(f)
            if f["kind"] == "server-kill":
                self.ctl["start"]()  # returns once the new server listens
            elif f["kind"] == "clients-drop":
                self.ctl["reopen"]()
            else:
                self.ctl["resume"]()
            f["t_end"] = time.monotonic()
            # caught up: every batch given to the devices before the fault ended is acknowledged
            f["last_seq"] = max(f["last_seq"], self.sent)
            devs = f["devices"] if f["devices"] is not None else self.load.devices
            with self.load.lock:
                f["acked0"] = {d: self.load.acked[d] for d in devs}
            f["devs"] = devs
            self.watch.append(f)
        if not self.watch:
            return
        now = time.monotonic()
        with self.load.lock:
            acked = self.load.acked
            for f in list(self.watch):
                if "first_ack_s" not in f and any(acked[d] > f["acked0"][d] for d in f["devs"]):
                    f["first_ack_s"] = round(now - f["t_end"], 2)
                if all(acked[d] >= f["last_seq"] for d in f["devs"]):  # everything sent before its end
                    f.setdefault("first_ack_s", 0.0)
                    f["caught_up_s"] = round(now - f["t_end"], 2)
                    self.watch.remove(f)
                    self.done.append(f)

    def report(self) -> list[dict]:
        keys = ("kind", "at_s", "down_s", "first_ack_s", "caught_up_s")
        out = [{k: f.get(k) for k in keys} | {"devices": len(f["devs"])} for f in self.done + self.watch]
        return sorted(out, key=lambda f: f["at_s"])


def run(
    clients: int,
    minutes: float,
    db: str,
    sessions: int | None = None,
    window: float = 10.0,
    speed: float = 0.0,
    fixed_resend: bool = False,
    faults: list[tuple[str, int, float]] = (),  # type: ignore[assignment]
    drop_fraction: float = 0.2,
    locate_workers: int = 0,
    ingest_workers: int | str = "auto",
) -> dict:
    """The live load (module docstring) in a temporary folder that is removed at the end (its database
    reaches hundreds of MB in 10 simulated minutes), also when the run fails or is interrupted."""
    tmp = Path(tempfile.mkdtemp(prefix="hybridloc-load-"))
    try:
        return _run_in(tmp, clients, minutes, db, sessions, window, speed, fixed_resend, faults, drop_fraction, locate_workers, ingest_workers)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run_in(
    tmp: Path,
    clients: int,
    minutes: float,
    db: str,
    sessions: int | None,
    window: float,
    speed: float,
    fixed_resend: bool,
    faults: list[tuple[str, int, float]],
    drop_fraction: float,
    locate_workers: int,
    ingest_workers: int | str,
) -> dict:
    import zenoh

    from hybridloc.server.ingest_pool import resolve_ingest_workers
    from hybridloc.types import RfScan, StepEvent, Technology
    from hybridloc.wire import codecs as C
    from hybridloc.wire import protocol as P
    from hybridloc.wire.messages import Batch
    from hybridloc.wire.zconfig import client_config

    pg = None
    if db == "sqlite":
        url, label = str(tmp / "load.db"), "sqlite"
    elif db == "postgres":
        from hybridloc.server.pgtemp import TempPostgres

        pg = TempPostgres().start()
        url, label = pg.database("load"), "postgres"
    else:
        url, label = db, db.split(":", 1)[0]
    ingest_workers = resolve_ingest_workers(ingest_workers, url)  # "auto" as the server resolves it
    map_file, scans = _map_and_scans(tmp)
    rng = np.random.default_rng(0)
    ep = f"tcp/127.0.0.1:{free_port()}"
    if any(k == "db-outage" for k, _, _ in faults) and pg is None:
        raise ValueError("a db-outage fault needs --db postgres (the benchmark's own PostgreSQL server)")
    serve_args = (
        "--map",
        f"{SITE}={map_file}",
        "--site",
        SITE,
        "--no-slam",
        "--locate-workers",
        str(locate_workers),
        "--ingest-workers",
        str(ingest_workers),
    )
    server = {"proc": _serve(ep, url, *serve_args), "rss": 0.0, "workers_rss": 0.0}
    devices = [f"load{i:05d}" for i in range(clients)]
    n_sess = sessions or max(1, min(clients, (clients + 19) // 20))
    load = _Load(devices, fixed_resend)
    sim_seconds = int(round(minutes * 60))
    sent_steps = sent_scans = 0
    t0_epoch = 1.7e9
    opened = []
    try:
        for i in range(n_sess):
            s = zenoh.open(client_config(ep))
            opened.append(s)
            # each session hears only its own devices (a wildcard here made the router send every
            # ack and fix to every session: 50 sessions, 50 copies)
            _subscribe(s, devices[i::n_sess], load)
        # wait until the server answers (its status queryable)
        deadline = time.monotonic() + 30
        while not any(r.ok for r in opened[0].get(P.KEY_STATUS, timeout=1.0)):
            if time.monotonic() > deadline:
                raise RuntimeError("the server does not answer")
        session_of = {d: opened[i % n_sess] for i, d in enumerate(devices)}
        dropped: list[int] = []

        def kill() -> None:
            server["rss"] = max(server["rss"], _peak_rss_mb(server["proc"].pid))
            server["workers_rss"] = max(server["workers_rss"], _children_peak_rss_mb(server["proc"].pid))
            server["proc"].kill()
            server["proc"].wait()

        def drop() -> list[str]:
            k = max(1, int(round(drop_fraction * n_sess)))
            dropped[:] = sorted(int(i) for i in np.random.default_rng(len(dropped) + 1).choice(n_sess, k, replace=False))
            out = [d for i in dropped for d in devices[i::n_sess]]
            with load.lock:
                load.down.update(out)
            for i in dropped:
                opened[i].close()
            return out

        def reopen() -> None:
            for i in dropped:
                s = zenoh.open(client_config(ep))
                opened[i] = s
                _subscribe(s, devices[i::n_sess], load)
                for d in devices[i::n_sess]:
                    session_of[d] = s
            back = [d for i in dropped for d in devices[i::n_sess]]
            with load.lock:
                load.down.difference_update(back)
                todo = [(d, [load.payloads[d][q] for q in sorted(load.payloads[d])]) for d in back]
                for d in back:  # back: what they spooled goes out at once, oldest first
                    load.resent[d].update(load.payloads[d])
                    load.last_progress[d] = time.monotonic()
            for d, payloads in todo:
                for p in payloads:
                    session_of[d].put(keys[d], p, encoding=C.BATCH.encoding, congestion_control=block)
                    load.resends += 1

        ctl = {
            "kill": kill,
            "start": lambda: server.__setitem__("proc", _serve(ep, url, *serve_args)),
            "drop": drop,
            "reopen": reopen,
            "pause": lambda: pg.pause(),
            "resume": lambda: pg.resume(),
        }
        fl = _Faults(list(faults), load, ctl)
        keys = {d: P.key_batch(SITE, d) for d in devices}
        scan_idx = {d: int(rng.integers(len(scans))) for d in devices}
        block = zenoh.CongestionControl.BLOCK
        wall0 = time.monotonic()
        for sec in range(sim_seconds):
            t = t0_epoch + sec
            if speed > 0:  # paced: simulated second `sec` starts at wall0 + sec / speed
                lag = wall0 + sec / speed - time.monotonic()
                if lag > 0:
                    time.sleep(lag)
            fl.start_due(sec, sec)  # batches 1..sec sent before it
            # the window: no device more than `window` simulated seconds behind on its acks (a dropped
            # device, which only spools, does not hold the others back)
            waited = time.monotonic()
            while True:
                with load.lock:
                    behind = max((sec - load.acked[d] for d in devices if d not in load.down), default=0)  # batch k is second k - 1
                if behind <= window:
                    break
                fl.poll()
                if fl.active():
                    waited = time.monotonic()
                if time.monotonic() - waited > 120:
                    raise RuntimeError(f"no acknowledgement progress for 120 s at simulated second {sec}")
                _resend_stalled(load, session_of, keys, block)
                time.sleep(0.005)
            for d in devices:
                seq = sec + 1
                steps = [StepEvent(t + dt, 0.7, 0.3, 0.05, 0.1, 0.0, 0.02) for dt in STEP_T]
                sc = ()
                if sec % SCAN_EVERY_S == 0:
                    base = scans[scan_idx[d] % len(scans)]
                    scan_idx[d] += 1
                    sc = (RfScan(t + 0.5, Technology.WIFI, dict(base.rssi_dbm), device_model=""),)
                payload = C.BATCH.encode(Batch(SITE, d, seq, "", steps, sc, ()))
                now = time.monotonic()
                with load.lock:
                    if not load.payloads[d]:  # the first unacknowledged batch starts the timer
                        load.last_progress[d] = now
                    load.sent_wall[d][seq] = now
                    load.payloads[d][seq] = payload
                    if sc:
                        load.scan_sent[(d, t + 0.5)] = now
                    down = d in load.down
                if not down:  # a dropped device spools it (sent when it is back)
                    session_of[d].put(keys[d], payload, encoding=C.BATCH.encoding, congestion_control=block)
                sent_steps += len(steps)
                sent_scans += len(sc)
            fl.sent = sec + 1
            _resend_stalled(load, session_of, keys, block)
            fl.poll()
        # drain: every batch acknowledged (resending on stalls), every fault ended
        fl.start_due(sim_seconds, sim_seconds)
        deadline = time.monotonic() + 120
        while True:
            with load.lock:
                done = all(load.acked[d] >= sim_seconds for d in devices)
            fl.poll()
            if fl.ongoing:
                deadline = time.monotonic() + 120
            if (done and not fl.active()) or time.monotonic() > deadline:
                break
            _resend_stalled(load, session_of, keys, block)
            time.sleep(0.01)
        wall = time.monotonic() - wall0
        # the answers to the last scans follow their acks: wait for them (a few seconds at most)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with load.lock:
                if load.fixes + load.no_fix >= sent_scans:
                    break
            time.sleep(0.01)
        rss = max(server["rss"], _peak_rss_mb(server["proc"].pid))
        workers_rss = max(server["workers_rss"], _children_peak_rss_mb(server["proc"].pid))
    finally:
        for s in opened:
            try:
                s.close()
            except Exception:  # noqa: BLE001 - best effort at the end of a run
                pass
        server["proc"].terminate()
        server["proc"].wait(timeout=60)
    stored = _stored(url, devices)
    if pg is not None:
        pg.stop()
    expected = dict.fromkeys(devices, sim_seconds)
    lost = sum(max(0, expected[d] - stored["batches"].get(d, 0)) for d in devices)
    doubled = sum(max(0, stored["batches"].get(d, 0) - expected[d]) for d in devices) + max(0, stored["steps"] - sent_steps)
    ack = np.array(load.ack_lat) * 1e3
    fix = np.array(load.fix_lat) * 1e3
    return {
        "clients": clients,
        "db": label,
        "minutes": minutes,
        "sessions": n_sess,
        "speed": speed,
        "lost": int(lost),
        "doubled": int(doubled),
        "steps_sent": sent_steps,
        "scans_sent": sent_scans,
        "steps_per_s": round(stored["steps"] / wall, 1),
        "scans_per_s": round(stored["scans"] / wall, 1),
        "ack_p50_ms": round(float(np.percentile(ack, 50)), 1) if ack.size else None,
        "ack_p99_ms": round(float(np.percentile(ack, 99)), 1) if ack.size else None,
        "fixes": load.fixes,
        "no_fix": load.no_fix,
        "fix_p50_ms": round(float(np.percentile(fix, 50)), 1) if fix.size else None,
        "fix_p99_ms": round(float(np.percentile(fix, 99)), 1) if fix.size else None,
        "resends": load.resends,
        "fixed_resend": fixed_resend,
        "locate_workers": locate_workers,
        "ingest_workers": ingest_workers,
        "misrouted": load.misrouted,
        "server_peak_rss_mb": round(rss, 1),
        "workers_peak_rss_mb": round(workers_rss, 1),
        "wall_s": round(wall, 1),
        "realtime_factor": round(sim_seconds / wall, 3),
        **({"faults": fl.report(), "fault_caught_up_max_s": _max_caught_up(fl.report())} if faults else {}),
    }


def _max_caught_up(report: list[dict]) -> float | None:
    """The slowest recovery of a run's faults (None when one never caught up)."""
    ts = [f["caught_up_s"] for f in report]
    return None if not ts or any(t is None for t in ts) else max(ts)


def _subscribe(session, devices: list[str], load: _Load) -> None:
    """Each device's ack and fix keys on its session, answered on Zenoh's own receiving thread
    (``indirect=False``). The default callback gives every subscriber a Python thread of its own:
    with 20 devices a session that is 2,000 threads at 1,000 clients, each answer a handover of the
    interpreter lock between them, and the load generator spent more of the machine's two cores than
    the server it loads (1.26 cores against 0.7, measured with /proc). A real phone holds two such
    subscribers, not forty. The callbacks only take ``load.lock`` and record a time.

    Never close a session, put or declare while holding ``load.lock``: ``Session.close`` waits for a
    running callback, which may be waiting for that lock. The latencies recorded include the wait of a
    callback for the interpreter lock while the generator's main thread runs (up to its 5 ms switch
    interval), as with a thread per subscriber."""
    import zenoh

    from hybridloc.wire import protocol as P

    try:  # ``indirect`` is marked unstable in zenoh-python: a version without it gets plain callbacks
        on_ack = zenoh.handlers.Callback(load.on_ack, indirect=False)
        on_fix = zenoh.handlers.Callback(load.on_fix, indirect=False)
    except TypeError:
        on_ack, on_fix = load.on_ack, load.on_fix
    for d in devices:
        session.declare_subscriber(P.key_ack(SITE, d), on_ack)
        session.declare_subscriber(P.key_fix(SITE, d), on_fix)


def _resend_stalled(load: _Load, session_of, keys, block) -> None:
    """Go-back-N as the client agent does it: a device whose ack has not moved for its retransmission timeout
    sends every unacknowledged batch again, oldest first."""
    from hybridloc.wire import codecs as C

    now = time.monotonic()
    todo = []
    with load.lock:
        for d, t in load.last_progress.items():
            if load.payloads[d] and now - t > load.timers[d].rto and d not in load.down:
                todo.append((d, [load.payloads[d][s] for s in sorted(load.payloads[d])]))
                load.last_progress[d] = now
                load.resent[d].update(load.payloads[d])
                load.timers[d].backoff()
    for d, payloads in todo:
        for p in payloads:
            session_of[d].put(keys[d], p, encoding=C.BATCH.encoding, congestion_control=block)
            load.resends += 1


def _stored(url: str, devices: list[str]) -> dict:
    from sqlalchemy import func, select
    from sqlalchemy.orm import Session

    from hybridloc.server import db as m

    eng = m.make_engine(url)
    with Session(eng) as s:
        batches = dict(s.execute(select(m.Batch.device_id, func.count()).group_by(m.Batch.device_id)).all())
        steps = s.execute(select(func.count()).select_from(m.Step)).scalar_one()
        scans = s.execute(select(func.count()).select_from(m.Scan)).scalar_one()
    eng.dispose()
    return {"batches": batches, "steps": int(steps), "scans": int(scans)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clients", type=int, default=1000)
    ap.add_argument("--minutes", type=float, default=10.0, help="simulated minutes of walking")
    ap.add_argument("--db", default="sqlite", help="sqlite, postgres (a throwaway server) or a database URL")
    ap.add_argument("--sessions", type=int, help="Zenoh client sessions carrying the devices (default one per 20)")
    ap.add_argument("--fixed-resend", action="store_true", help="resend after a fixed 2 s stall (clients before the adaptive timeout)")
    ap.add_argument("--window", type=float, default=10.0, help="simulated seconds a device may be behind on acks before the clock waits")
    ap.add_argument(
        "--speed", type=float, default=0.0, help="pace the simulated clock at this many times real time (default 0: as fast as the window allows)"
    )
    ap.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="KIND@SECOND[:DOWN]",
        help=f"a fault during the load ({', '.join(FAULT_KINDS)}) at a simulated second, lasting DOWN wall seconds; repeatable",
    )
    ap.add_argument("--drop-fraction", type=float, default=0.2, help="share of the Zenoh sessions a clients-drop fault closes")
    ap.add_argument("--no-ceiling", action="store_true", help="skip the large-batch ceiling and the raw insert rate")
    ap.add_argument(
        "--locate-workers", type=int, default=0, help="the server's locate worker processes (serve --locate-workers; 0: its locate thread)"
    )
    ap.add_argument(
        "--ingest-workers",
        type=_count_or_auto,
        default="auto",
        help="the server's ingest worker processes, for the live load and the ceiling (serve --ingest-workers; 0: its ingest thread; "
        "default auto, the server's own default: 2 on 2 cores or more)",
    )
    ap.add_argument(
        "--ceiling-batches",
        type=int,
        default=100,
        help="batches of 1,000 steps + 100 scans per device for the ceiling (default 100: about a second of ingest, long enough to ride out a shared machine's pauses)",
    )
    ap.add_argument("--ceiling-only", action="store_true", help="only the large-batch ceiling and the raw insert rate (no live load)")
    ap.add_argument(
        "--ceiling-steps",
        choices=("columns", "rows"),
        default="columns",
        help="the ceiling's clients send steps in the columnar form (default, as the client agent sends large batches) or as rows",
    )
    args = ap.parse_args(argv)
    if args.clients < 1 or args.minutes <= 0:
        ap.error("--clients must be >= 1 and --minutes > 0")
    if not 0.0 < args.drop_fraction <= 1.0:
        ap.error("--drop-fraction must be in (0, 1]")
    try:
        faults = [parse_fault(f) for f in args.fault]
    except ValueError as e:
        ap.error(str(e))
    if any(sec >= args.minutes * 60 for _, sec, _ in faults):
        ap.error("a fault's SECOND must fall inside the run (< --minutes x 60)")
    if any(k == "db-outage" for k, _, _ in faults) and args.db != "postgres":
        ap.error("a db-outage fault needs --db postgres (the benchmark pauses its own PostgreSQL server)")
    if args.locate_workers < 0:
        ap.error("--locate-workers must be >= 0")
    if args.ceiling_only and (args.no_ceiling or faults):
        ap.error("--ceiling-only runs no live load: it takes neither --no-ceiling nor --fault")
    if args.ceiling_only:
        r = {"db": args.db.split(":", 1)[0] if "://" in args.db else args.db, "ceiling_only": True}
        _print_ceiling(r, args.db, args.ceiling_batches, args.ceiling_steps, args.ingest_workers)
        r["ingest_workers"] = r["ceiling_ingest_workers"]
        print(json.dumps(r))
        return r
    r = run(
        args.clients,
        args.minutes,
        args.db,
        args.sessions,
        args.window,
        args.speed,
        args.fixed_resend,
        faults,
        args.drop_fraction,
        args.locate_workers,
        args.ingest_workers,
    )
    held = r["realtime_factor"] >= 1.0 and r["lost"] == 0 and r["doubled"] == 0
    print(
        f"load: {r['clients']} clients x {r['minutes']:g} simulated min on {r['db']} ({r['sessions']} sessions): "
        f"realtime factor {r['realtime_factor']:.2f} ({'held real time' if held else 'did NOT hold real time'}), "
        f"stored {r['steps_per_s']:.0f} steps/s + {r['scans_per_s']:.0f} scans/s, ack p50 {r['ack_p50_ms']} ms p99 {r['ack_p99_ms']} ms, "
        f"fixes {r['fixes']} (+{r['no_fix']} no-fix) p50 {r['fix_p50_ms']} ms p99 {r['fix_p99_ms']} ms, resends {r['resends']}, "
        f"server peak {r['server_peak_rss_mb']} MB (its worker processes {r['workers_peak_rss_mb']} MB), lost {r['lost']}, doubled {r['doubled']}"
    )
    for f in r.get("faults", []):
        print(
            f"fault {f['kind']} at simulated second {f['at_s']} for {f['down_s']:g} s ({f['devices']} devices): "
            f"first ack {f['first_ack_s']} s after it ended, every batch sent before its end acknowledged after {f['caught_up_s']} s"
        )
    if not args.no_ceiling:
        _print_ceiling(r, args.db, args.ceiling_batches, args.ceiling_steps, args.ingest_workers)
    print(json.dumps(r))
    return r


def _count_or_auto(text: str) -> int | str:
    if text == "auto":
        return text
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0 or auto, got {text!r}")
    return int(text)


def _print_ceiling(r: dict, db: str, n_batches: int, step_form: str, ingest_workers: int | str = "auto") -> None:
    """Run :func:`ceiling` into ``r`` and print its lines."""
    r.update(ceiling(db, n_batches, step_form, ingest_workers))
    print(
        f"ceiling on {r['db']}: {r['ceiling_steps_per_s']:,.0f} steps/s + {r['ceiling_scans_per_s']:,.0f} scans/s stored end to end "
        f"(2 devices, batches of 1,000 steps as {step_form} + 100 scans through Zenoh, decoding, validation and the database, "
        f"{'the server ingesting in ' + str(r['ceiling_ingest_workers']) + ' worker processes' if r['ceiling_ingest_workers'] else 'the server ingesting in its ingest thread'}, "
        f"{'zero loss' if r['ceiling_lossless'] else 'LOSS'}); plain executemany of 8-column step rows on the same database: "
        f"{r['raw_rows_per_s']:,.0f} rows/s (before the run {r['raw_rows_per_s_before']:,.0f}, after it {r['raw_rows_per_s_after']:,.0f}); ratio {r['ceiling_ratio']:.1%} (goal >= 20 %)"
    )
    cpu = r["batch_encode_ms"] + r["batch_decode_ms"] + r["batch_store_ms"]
    print(
        f"  where a batch's time goes (in one process, ms per batch of 1,000 steps + 100 scans): client encode {r['batch_encode_ms']:.1f}, "
        f"server decode {r['batch_decode_ms']:.1f} (the general path {r['batch_decode_general_ms']:.1f}), store {r['batch_store_ms']:.1f}; "
        f"its 1,000 step rows by the raw executemany {r['batch_raw_steps_ms']:.2f} (into the store's own step table, 13 columns and "
        f"its index: {'-' if r['batch_schema_steps_ms'] is None else format(r['batch_schema_steps_ms'], '.2f')}). These alone, on 2 cores with nothing else, bound the "
        f"ratio at about {2 * r['batch_raw_steps_ms'] / cpu:.0%} (the server's share alone at {r['batch_raw_steps_ms'] / (r['batch_decode_ms'] + r['batch_store_ms']):.0%})"
    )
    if r.get("batch_encode_rows_ms") is not None:
        print(
            f"  the same batches with today's step rows: client encode {r['batch_encode_rows_ms']:.1f}, "
            f"server decode {r['batch_decode_rows_ms']:.1f} ms per batch"
        )


def ceiling(db: str, n_batches: int, step_form: str = "columns", ingest_workers: int | str = "auto") -> dict:
    """Ingest with large batches (1,000 steps + 100 scans) from 2 client processes, end to end, next to
    the raw insert rate of the same kind of database on this machine (each on a fresh database).
    ``step_form``: the clients send the steps in the columnar form (``columns``, what the client agent
    sends for large batches) or as today's rows (``rows``); ``ingest_workers``: the server's
    (``serve --ingest-workers``)."""
    from benchmarks.bench_server import ingest_run, raw_insert_rate
    from hybridloc.server.ingest_pool import resolve_ingest_workers

    tmp = Path(tempfile.mkdtemp(prefix="hybridloc-ceiling-"))
    pg = None
    try:
        if db == "sqlite":
            url_ingest, url_raw = str(tmp / "ceiling.db"), str(tmp / "raw.db")
        elif db == "postgres":
            from hybridloc.server.pgtemp import TempPostgres

            pg = TempPostgres().start()
            url_ingest, url_raw = pg.database("ceiling"), pg.database("raw")
        else:
            url_ingest = url_raw = db
        ingest_workers = resolve_ingest_workers(ingest_workers, url_ingest)
        # the raw rate before and after the run, their mean the ratio's denominator: a shared machine's
        # speed drifts within seconds (508,000-884,000 rows/s between runs in the tenth session)
        raw_before = raw_insert_rate(url_raw)
        r = ingest_run(
            url_ingest,
            2,
            n_batches,
            n_steps=1000,
            n_scans=100,
            step_columns_from=1 if step_form == "columns" else None,
            serve_args=("--ingest-workers", str(ingest_workers)),
        )
        raw_after = raw_insert_rate(url_raw)
        raw = 0.5 * (raw_before + raw_after)
        costs = batch_costs(str(tmp / "costs.db") if db == "sqlite" else (pg.database("costs") if pg is not None else db), step_form=step_form)
    finally:
        if pg is not None:
            pg.stop()
        shutil.rmtree(tmp, ignore_errors=True)  # its databases: hundreds of MB a run
    steps_per_s = r["steps"] / r["wall"]
    return {
        "ceiling_steps_per_s": round(steps_per_s, 1),
        "ceiling_scans_per_s": round(r["scans"] / r["wall"], 1),
        "ceiling_lossless": bool(r["lossless"]),
        "raw_rows_per_s": round(raw, 1),
        "raw_rows_per_s_before": round(raw_before, 1),
        "raw_rows_per_s_after": round(raw_after, 1),
        "ceiling_ratio": round(steps_per_s / raw, 4),
        "ceiling_step_form": step_form,
        "ceiling_ingest_workers": ingest_workers,
        **costs,
    }


def batch_costs(db_url: str, n: int = 20, step_form: str = "columns") -> dict:
    """Where a large batch's time goes, in this process, on the ceiling's own batches (1,000 steps +
    100 scans of 30 readings) in its step form: the client's encoding, the server's decoding (the typed
    fast path that takes such a batch, and the general path beside it) and storing (groups of 4, as the
    ingest loop groups them), each in ms per batch; the same for today's rows beside them when the form
    is ``columns`` (``*_rows_ms``); a batch's 1,000 step rows by the raw executemany for scale."""
    from benchmarks.bench_server import raw_insert_rate
    from hybridloc.server.store import Store
    from hybridloc.types import RfScan, StepEvent
    from hybridloc.wire import codecs as C
    from hybridloc.wire.messages import Batch

    def batch(k: int) -> Batch:
        steps = tuple(StepEvent(100.0 * k + 0.1 * i, 0.7, 0.01 * i, 0.05, 0.1, 0.01, 0.02) for i in range(1000))
        scans = tuple(RfScan(100.0 * k + float(i), "wifi", {f"ap{j:03d}": -50.0 - j for j in range(30)}) for i in range(100))
        return Batch("bench", "costs", k + 1, "", steps, scans)

    records = [batch(k) for k in range(n)]
    # what lived before (the records, the ceiling run's leftovers) is frozen out of the collector's
    # scans, so each path's time is its own allocations', not the age of the process
    gc.collect()
    gc.freeze()
    columns = step_form == "columns"
    encode = (lambda b: C.BATCH.encode(b, step_columns=True)) if columns else C.BATCH.encode
    for fn in (C.BATCH.decode, C.BATCH.decode_general):  # warm both paths (allocator, caches) before timing
        for enc in {encode, C.BATCH.encode}:
            fn(enc(batch(n)), "bench", "costs")
    t0 = time.perf_counter()
    payloads = [encode(b) for b in records]
    t1 = time.perf_counter()
    row_payloads = [C.BATCH.encode(b) for b in records]
    t_rows = time.perf_counter() - t1

    def best_of_two(
        fn, payloads=payloads
    ) -> tuple[float, list]:  # seconds for all n (the faster of two runs: a shared machine's pauses), the batches
        times, got = [], []
        for _ in range(2):
            t = time.perf_counter()
            got = [fn(p, "bench", "costs") for p in payloads]
            times.append(time.perf_counter() - t)
        return min(times), got

    fast_s, decoded = best_of_two(C.BATCH.decode)
    general_s, _ = best_of_two(C.BATCH.decode_general)
    rows_s = best_of_two(C.BATCH.decode, row_payloads)[0] if columns else None
    store = Store(db_url)
    try:
        t4 = time.perf_counter()
        for i in range(0, n, 4):
            store.persist(decoded[i : i + 4])
        t5 = time.perf_counter()
    finally:
        store.close()
        gc.unfreeze()
    per = lambda a, b: round(1e3 * (b - a) / n, 2)  # noqa: E731
    schema_ms: float | None = None  # (null in the JSON line: measured on SQLite only)
    if "://" not in db_url:  # the same 1,000 step rows by a plain sqlite3 executemany into the store's own step table (its index, its 13 columns)
        import sqlite3

        from hybridloc.server.store import _step_insert_sql

        rows = [(1, "costs", 1e6 + 0.1 * i, 0.7, 0.1, 0.05, 0.1, 0.01, 0.02, 0.0, 0.0, 0, "") for i in range(1000 * n)]
        con = sqlite3.connect(db_url)
        con.execute("PRAGMA synchronous=NORMAL")
        t6 = time.perf_counter()
        with con:
            con.executemany(_step_insert_sql("qmark"), rows)
        schema_ms = per(t6, time.perf_counter())
        con.close()
    return {
        "batch_schema_steps_ms": schema_ms,
        "batch_step_form": step_form,
        "batch_encode_ms": per(t0, t1),
        "batch_encode_rows_ms": per(0.0, t_rows) if columns else None,
        "batch_decode_rows_ms": per(0.0, rows_s) if rows_s is not None else None,
        "batch_decode_ms": per(0.0, fast_s),
        "batch_decode_general_ms": per(0.0, general_s),
        "batch_store_ms": per(t4, t5),
        "batch_raw_steps_ms": round(1e3 * 1000 / raw_insert_rate(db_url, rows=20_000), 2),
    }


if __name__ == "__main__":
    main()

"""Server over real Zenoh sessions on loopback, real SQLite files and real Alembic migrations."""

import dataclasses
import json
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import zenoh
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from hybridloc.clients.uplink import Uplink
from hybridloc.server import db as m
from hybridloc.server.migrate import upgrade
from hybridloc.server.service import Server
from hybridloc.types import RfScan, StepEvent, SurveyMark
from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import Batch, LocateRequest
from hybridloc.wire.zconfig import Security, client_config, free_port

from .helpers import stored_stream
from .helpers import wait_until as _wait

SITE = "site1"


def _steps(n, t0=0.0):
    return [StepEvent(t0 + i * 0.5, 0.7, 0.1 * i, 0.05, 0.1, 0.1, 0.02) for i in range(n)]


def _scans(n, t0=0.0):
    return [RfScan(t0 + i, "wifi", {"aa:bb": -50.0 - i, "cc:dd": -70.0}) for i in range(n)]


def _batch(site, device, seq, steps=(), scans=(), marks=()):
    return C.BATCH.encode(Batch(site, device, seq, "", steps, scans, marks))


def _count(db, model):
    eng = m.make_engine(str(db))  # a SQLite path or any URL
    with Session(eng) as s:
        n = s.execute(select(func.count()).select_from(model)).scalar_one()
    eng.dispose()
    return n


def test_models_and_migrations_agree(tmp_path):
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    eng = m.make_engine(str(tmp_path / "a.db"))
    upgrade(eng)
    upgrade(eng)  # idempotent
    with eng.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), m.Base.metadata)
        mode = conn.exec_driver_sql("PRAGMA journal_mode").scalar()
    eng.dispose()
    assert diff == []
    assert mode == "wal"


@pytest.fixture
def server(tmp_path, db_url):
    """A server on each engine (SQLite file, PostgreSQL database): (server, endpoint, folder, db URL)."""
    ep = f"unixsock-stream/{tmp_path}/srv.sock"
    srv = Server(ep, db_url).start()
    try:
        yield srv, ep, tmp_path, db_url
    finally:
        srv.stop()


def test_ingest_ack_duplicates_gaps_and_bad_messages(server):
    srv, ep, tmp, db = server
    with zenoh.open(client_config(ep)) as s:
        up = Uplink(s, SITE, "dev01", tmp / "spool")
        try:
            assert up.wait_connected()
            for i in range(5):
                up.send(steps=_steps(10, 10.0 * i), scans=_scans(2, 10.0 * i))
            assert up.wait_acked(timeout=10)
            assert up.acked == 5 and not list((tmp / "spool").glob("0*.json"))  # spool emptied by acks
            raw = s.declare_publisher(P.key_batch(SITE, "dev01"), congestion_control=zenoh.CongestionControl.BLOCK)
            raw.put(_batch(SITE, "dev01", 3, _steps(2)))  # duplicate
            raw.put(_batch(SITE, "dev01", 9, _steps(2)))  # gap
            raw.put(b"{not json")
            raw.put(json.dumps({"schema": "hybridloc.batch/99", "site": SITE, "device": "dev01", "seq": 6}).encode())
            raw.put(b'{"schema":"hybridloc.batch/1","site":"site1","device":"dev01","seq":6,"steps":[{"t":NaN}]}')
            raw.put(b"x" * (P.MAX_BATCH_BYTES + 1))
            raw.put(_batch(SITE, "dev02", 1, _steps(1)))  # payload device != key device
            assert _wait(lambda: sum(v for k, v in srv.counts.items() if k.startswith("rejected:")) >= 7)
            c = srv.counts
            for reason in ("duplicate", "out-of-order", "malformed-json", "schema-version", "non-finite", "too-large", "key-mismatch"):
                assert c[f"rejected:{reason}"] == 1, (reason, dict(c))
            # the server keeps serving: the next batch in sequence is taken
            up.send(steps=_steps(3))
            assert up.wait_acked(timeout=10) and up.acked == 6
            raw.undeclare()
            replies = [r for r in s.get(P.KEY_STATUS, timeout=5.0) if r.ok]
            st = C.STATUS.decode(replies[0].ok.payload.to_bytes())
            assert st.db["batches"] == 6 and st.db["steps"] == 53 and st.db["scans"] == 10
            assert st.db["rejections"]["duplicate"] == 1
        finally:
            up.close()
    assert _count(db, m.Batch) == 6 and _count(db, m.Step) == 53


def test_locate_queryable_and_pushed_fix(server):
    from hybridloc.radio.radiomap import BuildParams, build_radio_map
    from hybridloc.radio.survey import LabelledScan
    from hybridloc.types import RfScan

    srv, ep, tmp, _ = server
    rng = np.random.default_rng(0)
    aps = {"a1": (0, 0), "a2": (20, 0), "a3": (0, 20), "a4": (20, 20)}

    def reading(p):
        return {k: -40 - 30 * np.log10(max(1.0, np.hypot(p[0] - q[0], p[1] - q[1]))) + rng.normal(0, 1.5) for k, q in aps.items()}

    refs = [LabelledScan(RfScan(float(i), "wifi", reading(p)), p, 0.5, "F1") for i, p in enumerate(rng.uniform(0, 20, (600, 2)))]
    rmap = build_radio_map(refs, site=SITE, params=BuildParams())
    rmap.save(tmp / "m.npz")
    assert srv.load_map(SITE, (tmp / "m.npz").read_bytes()) == 1
    with zenoh.open(client_config(ep)) as s:
        q = C.LOCATE.encode(LocateRequest(RfScan(1.0, "wifi", reading((5.0, 5.0)))))
        rep = [r for r in s.get(P.key_locate(SITE, "dev05"), payload=q, timeout=5.0) if r.ok]
        a = C.FIX.decode(rep[0].ok.payload.to_bytes())
        assert np.hypot(a.fix.pos_enu[0] - 5, a.fix.pos_enu[1] - 5) < 4.0 and a.region.floor == "F1" and a.region.contains(a.fix.pos_enu)
        assert a.floor_probs == {"F1": 1.0}  # one floor in the map
        rep = [r for r in s.get(P.key_locate("othersite", "dev05"), payload=q, timeout=5.0) if r.ok]
        a = C.FIX.decode(rep[0].ok.payload.to_bytes())
        assert a.fix is None and a.reason == "no radio map for site 'othersite'" and a.t == 1.0  # no map: a reason, no made-up fix
        bad = C.LOCATE.encode(LocateRequest(RfScan(1.0, "wifi", {}))).replace(b"{}", b'{"a1": 5.0}')  # a reading above 0 dBm
        errs = [r.err.payload.to_bytes() for r in s.get(P.key_locate(SITE, "dev05"), payload=bad, timeout=5.0) if not r.ok]
        assert errs and b"rssi-out-of-range" in errs[0] and srv.counts["rejected:bad-locate"] == 1
        got, fixes = threading.Event(), []
        sub = s.declare_subscriber(P.key_fix(SITE, "dev05"), lambda smp: (fixes.append(smp.payload.to_bytes()), got.set()))
        up = Uplink(s, SITE, "dev05", tmp / "spool5")
        try:
            assert up.wait_connected()
            scan = RfScan(2.0, "wifi", reading((10.0, 12.0)))
            up.send(scans=[scan])
            assert got.wait(10.0)  # the server pushed a fix for the new scan
            # the same batch resent (a late ack): acknowledged again, stored and answered once
            s.put(P.key_batch(SITE, "dev05"), _batch(SITE, "dev05", 1, scans=[scan]))
            deadline = time.monotonic() + 10.0
            while srv.counts["rejected:duplicate"] < 1 and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.5)  # a second answer would be put right after the duplicate was counted
            assert srv.counts["rejected:duplicate"] == 1 and len(fixes) == 1
            # a batch and its resend back to back (one ingest group, as a resend storm makes them):
            # stored once and answered once (a duplicate inside the group was answered again)
            twice = _batch(SITE, "dev05", 2, scans=[RfScan(3.0, "wifi", reading((11.0, 12.0)))])
            s.put(P.key_batch(SITE, "dev05"), twice)
            s.put(P.key_batch(SITE, "dev05"), twice)
            deadline = time.monotonic() + 10.0
            while srv.counts["rejected:duplicate"] < 2 and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.5)
            assert srv.counts["rejected:duplicate"] == 2 and len(fixes) == 2
        finally:
            up.close()
            sub.undeclare()


def _start_server(ep, db, *extra):
    proc = subprocess.Popen(
        [sys.executable, "-m", "hybridloc.cli", "serve", "--endpoint", ep, "--db", str(db), *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines = [proc.stdout.readline()]
    while "listening" not in lines[-1] and lines[-1].startswith(("warning", "crowd SLAM")):  # notes before it
        lines.append(proc.stdout.readline())
    assert "listening" in lines[-1], lines
    return proc


def test_sigkill_mid_ingest_loses_nothing_acknowledged_and_resend_completes(tmp_path, db_url):
    ep = f"tcp/127.0.0.1:{free_port()}"
    db = db_url  # SQLite file or PostgreSQL database
    proc = _start_server(ep, db)
    n_batches = 300
    conf = client_config(ep)
    conf.insert_json5("mode", '"peer"')  # a peer keeps retrying its connection while the server is down
    with zenoh.open(conf) as s:
        up = Uplink(s, SITE, "devk", tmp_path / "spool", resend_after=1.0)
        try:
            assert up.wait_connected()
            for i in range(n_batches):
                up.send(steps=_steps(20, i * 10.0), scans=_scans(2, i * 10.0))
                if i == n_batches // 2:
                    proc.send_signal(signal.SIGKILL)  # mid-ingest
                    proc.wait()
            acked_at_kill = up.acked
            assert _count(db, m.Batch) >= acked_at_kill  # every acknowledged batch was committed
            proc = _start_server(ep, db)
            assert up.wait_acked(timeout=60), f"acked {up.acked} of {up.next_seq - 1}"
        finally:
            up.close()
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=20)
    seqs, n_steps = stored_stream(db, "devk")
    assert seqs == list(range(1, n_batches + 1))  # nothing missing, nothing doubled
    assert n_steps == 20 * n_batches


def test_wrong_password_refused_and_devices_confined(tmp_path):
    users = tmp_path / "users.txt"
    users.write_text("server:srvpw\ndev01:pw1\ndev02:pw2\n")
    ep = f"tcp/127.0.0.1:{free_port()}"
    sec = Security(users_file=str(users), acl_devices=["dev01", "dev02"])
    srv = Server(ep, str(tmp_path / "s.db"), sec)
    # the server's own session authenticates as "server" towards nobody: it is the router
    srv.start()
    try:
        with pytest.raises(zenoh.ZError):
            zenoh.open(client_config(ep, Security(user="dev01", password="wrong")))
        with (
            zenoh.open(client_config(ep, Security(user="dev01", password="pw1"))) as s1,
            zenoh.open(client_config(ep, Security(user="dev02", password="pw2"))) as s2,
        ):
            seen = []
            sub = s2.declare_subscriber(P.key_fix(SITE, "dev01"), lambda smp: seen.append(smp))  # dev02 spying on dev01
            # dev01 writes under dev02's key: refused by the ACL, never stored
            s1.put(P.key_batch(SITE, "dev02"), _batch(SITE, "dev02", 1, _steps(2)))
            up = Uplink(s1, SITE, "dev01", tmp_path / "sp1", resend_after=0.5)
            try:
                assert up.wait_connected()
                up.send(steps=_steps(2))
                assert up.wait_acked(timeout=10)  # its own key works
                srv.session.put(P.key_fix(SITE, "dev01"), b"{}")  # a fix for dev01 ...
                time.sleep(0.5)
                assert seen == []  # ... never reaches dev02
            finally:
                up.close()
                sub.undeclare()
        time.sleep(0.3)
        assert _count(tmp_path / "s.db", m.Batch) == 1
        assert srv.store.last_seq("dev02") == 0
    finally:
        srv.stop()


def _two_batches_through_a_fresh_publisher(ep: str, d: str) -> tuple[bool, list[int]]:
    """A fresh session of device ``d`` declares a publisher and puts batch 1 at once, then batch 2 once
    the publisher sees the server's subscription; returns (it saw it, the acks heard)."""
    with zenoh.open(client_config(ep, Security(user=d, password=f"pw-{d}"))) as s:
        acks = s.declare_subscriber(P.key_ack(SITE, d))  # declared before the put, on the same link
        pub = s.declare_publisher(P.key_batch(SITE, d), congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(_batch(SITE, d, 1, _steps(2)))
        matched = _wait(lambda: pub.matching_status.matching, timeout=5.0)
        pub.put(_batch(SITE, d, 2, _steps(2, t0=1.0)))
        seen: list[int] = []

        def both_acked():
            while (smp := acks.try_recv()) is not None:
                seen.append(C.ACK.decode(smp.payload.to_bytes()).acked_seq)
            return 2 in seen

        _wait(both_acked, timeout=10.0)
        pub.undeclare()
        acks.undeclare()
    return matched, seen


def test_acl_every_first_batch_of_20_fresh_sessions_acknowledged(tmp_path):
    """Under the device ACL a declared publisher works like a plain put: 20 fresh sessions each declare
    a publisher and put batch 1 at once (the race with the router's answer to the publisher's
    interest), then batch 2 once the publisher sees the server's subscription (it never did when the
    router hid the declaration: the put was then dropped at the device). Every batch is acknowledged,
    with no resend, and stored once (a cumulative ack of 2 covers 1)."""
    devices = [f"dev{i:02d}" for i in range(20)]
    users = tmp_path / "users.txt"
    users.write_text("server:srvpw\n" + "".join(f"{d}:pw-{d}\n" for d in devices))
    ep = f"tcp/127.0.0.1:{free_port()}"
    srv = Server(ep, str(tmp_path / "s.db"), Security(users_file=str(users), acl_devices=devices)).start()
    try:
        for d in devices:
            matched, seen = _two_batches_through_a_fresh_publisher(ep, d)
            assert matched, f"{d}: the publisher never saw the server's subscription"
            assert max(seen, default=0) == 2, f"{d}: acks {seen}"
    finally:
        srv.stop()
    assert _count(tmp_path / "s.db", m.Batch) == 2 * len(devices)


def test_tls_with_the_test_ca_script(tmp_path):
    import shutil
    from pathlib import Path

    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    script = Path(__file__).resolve().parents[1] / "scripts" / "make-test-certs.sh"
    subprocess.run(["bash", str(script), str(tmp_path / "pki")], check=True, capture_output=True)
    subprocess.run(["bash", str(script), str(tmp_path / "other")], check=True, capture_output=True)
    ep = f"tls/localhost:{free_port()}"
    pki = tmp_path / "pki"
    srv = Server(ep, str(tmp_path / "t.db"), Security(tls_cert=str(pki / "server.pem"), tls_key=str(pki / "server.key"))).start()
    try:
        with zenoh.open(client_config(ep, Security(tls_ca=str(pki / "ca.pem")))) as s:
            up = Uplink(s, SITE, "devtls", tmp_path / "sp")
            try:
                assert up.wait_connected()
                up.send(steps=_steps(3))
                assert up.wait_acked(timeout=10)
            finally:
                up.close()
        with pytest.raises(zenoh.ZError):  # a client trusting another CA refuses the server
            zenoh.open(client_config(ep, Security(tls_ca=str(tmp_path / "other" / "ca.pem"))))
    finally:
        srv.stop()


def test_map_rebuild_from_stored_surveys_is_incremental(tmp_path):
    from hybridloc.io.msft import find_ilc_traces, read_ilc_trace
    from hybridloc.pdr.phone import run_phone_pdr
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.server.rebuild import rebuild
    from hybridloc.server.store import Store

    st = Store(str(tmp_path / "r.db"))
    batches = []
    for i, p in enumerate(find_ilc_traces(ILC_SITE1_F1)[:6]):
        tr = read_ilc_trace(p)
        steps, _ = run_phone_pdr(tr.imu)
        scans = [RfScan(s.t, "wifi", s.rssi_dbm) for s in tr.wifi_scans]
        marks = [SurveyMark(float(t), float(x), float(y), "F1") for t, (x, y) in zip(tr.waypoints.t, tr.waypoints.pos_enu)]
        chunks = [dict(steps=steps, marks=marks)] + [dict(scans=scans[k : k + 8]) for k in range(0, len(scans), 8)]
        for seq, c in enumerate(chunks, 1):  # batches stay under the protocol's size limit
            batches.append(C.BATCH.decode(_batch("mall", f"surveyor{i}", seq, **c)))
    st.persist(batches)
    v, n, relabelled = rebuild(st, "mall", tmp_path / "cache")
    assert v == 1 and n > 50 and relabelled == 6
    v2, n2, relabelled2 = rebuild(st, "mall", tmp_path / "cache")  # nothing changed: all from the cache
    assert v2 == 2 and n2 == n and relabelled2 == 0
    st.close()
    r = subprocess.run(
        [sys.executable, "-m", "hybridloc.cli", "map", "export", "--site", "mall", "--db", str(tmp_path / "r.db"), "--out", str(tmp_path / "m.npz")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    from hybridloc.radio.radiomap import RadioMap

    assert RadioMap.load(tmp_path / "m.npz").site == "mall"


def test_two_server_processes_split_the_sites_on_one_mesh(tmp_path, db_url):
    """Two ``hybridloc serve`` processes, one database: A serves site sA, B serves sB and joins A's router
    (``--connect``). Each device connects to the *other* site's process; its batches cross the mesh to
    its own site's process, which alone stores and acknowledges them. Each process's status names its
    sites and counts only its site's batches; a site nobody serves gets no acknowledgement."""
    ep_a, ep_b = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    procs = [_start_server(ep_a, db_url, "--site", "sA", "--no-slam")]
    procs.append(_start_server(ep_b, db_url, "--site", "sB", "--no-slam", "--connect", ep_a))
    try:
        for site, dev, ep in (("sA", "devA", ep_b), ("sB", "devB", ep_a)):
            with zenoh.open(client_config(ep)) as s:
                up = Uplink(s, site, dev, tmp_path / dev, resend_after=0.5)
                try:
                    assert up.wait_connected(20)
                    for k in range(10):
                        up.send(steps=_steps(3, 10.0 * k))
                    assert up.wait_acked(timeout=20), f"{dev}: acked {up.acked}"
                finally:
                    up.close()
        with zenoh.open(client_config(ep_a)) as s:
            up = Uplink(s, "sC", "devC", tmp_path / "devC", resend_after=0.5)
            try:
                up.send(steps=_steps(3))
                assert not up.wait_acked(timeout=2)  # no process serves sC
            finally:
                up.close()
            replies = [
                C.STATUS.decode(r.ok.payload.to_bytes())
                for r in s.get(P.KEY_STATUS, timeout=5.0, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE)
                if r.ok
            ]
    finally:
        for p in procs:
            p.send_signal(signal.SIGTERM)
            p.wait(timeout=20)
    by_sites = {st.sites: st for st in replies}
    assert set(by_sites) == {("sA",), ("sB",)}
    assert by_sites[("sA",)].counts["batches-persisted"] == 10 and by_sites[("sB",)].counts["batches-persisted"] == 10
    eng = m.make_engine(db_url)
    with Session(eng) as ses:
        rows = ses.execute(select(m.Batch.device_id, m.Batch.seq).order_by(m.Batch.device_id, m.Batch.seq)).all()
    eng.dispose()
    assert rows == [("devA", k) for k in range(1, 11)] + [("devB", k) for k in range(1, 11)]


def test_a_backlog_of_one_devices_scans_is_answered_newest_first_and_the_rest_shed(tmp_path):
    """Load shedding in the locate worker: of a device's scans waiting together, only the newest is
    located; the older get "no fix, superseded", so each stored batch still hears back exactly once."""
    ep = f"unixsock-stream/{tmp_path}/srv.sock"
    got = []
    with Server(ep, str(tmp_path / "s.db")) as srv, zenoh.open(client_config(ep)) as s:
        sub = s.declare_subscriber(P.key_fix(SITE, "dev1"), lambda smp: got.append(C.FIX.decode(smp.payload.to_bytes())))
        other = s.declare_subscriber(P.key_fix(SITE, "dev2"), lambda smp: got.append(C.FIX.decode(smp.payload.to_bytes())))
        time.sleep(0.3)
        b = [Batch(SITE, d, k + 1, "", (), _scans(1, 10.0 * k), ()) for d in ("dev1", "dev2") for k in range(3)]
        srv._answer([(x, x.scans[-1]) for x in b])  # what the ingest worker hands over after storing them
        _wait(lambda: len(got) == 6)
        sub.undeclare()
        other.undeclare()
        assert srv.counts["fixes-shed"] == 4
    by_t = {(a.t, a.reason.startswith("superseded")) for a in got}
    # the newest of each device (t = 20) is located (no map here: "no radio map"), the older two shed
    assert by_t == {(0.0, True), (10.0, True), (20.0, False)}


def _synthetic_map(tmp_path, rng):
    from hybridloc.radio.radiomap import BuildParams, build_radio_map
    from hybridloc.radio.survey import LabelledScan

    aps = {"a1": (0, 0), "a2": (20, 0), "a3": (0, 20), "a4": (20, 20)}

    def reading(p):
        return {k: -40 - 30 * np.log10(max(1.0, np.hypot(p[0] - q[0], p[1] - q[1]))) + rng.normal(0, 1.5) for k, q in aps.items()}

    refs = [LabelledScan(RfScan(float(i), "wifi", reading(p)), p, 0.5, "F1") for i, p in enumerate(rng.uniform(0, 20, (400, 2)))]
    path = tmp_path / "m.npz"
    build_radio_map(refs, site=SITE, params=BuildParams()).save(path)
    return path.read_bytes(), reading


def test_locate_workers_answer_byte_for_byte_as_the_locate_thread(tmp_path):
    """``serve --locate-workers``: the answers (FIX messages and the fixes stored) are the locate
    thread's, byte for byte; a worker killed mid-run is answered for in-process and counted, and the
    next group goes to a new pool; a new map version reaches the workers."""
    rng = np.random.default_rng(3)
    blob, reading = _synthetic_map(tmp_path, rng)
    scans = [RfScan(100.0 + i, "wifi", reading(p), age_s={"a1": 0.5}) for i, p in enumerate(rng.uniform(0, 20, (40, 2)))]
    scans.append(RfScan(200.0, "wifi", {"zz": -60.0}))  # no known transmitter: "no fix" with its reason
    here = Server(f"unixsock-stream/{tmp_path}/a.sock", str(tmp_path / "a.db"))
    pooled = Server(f"unixsock-stream/{tmp_path}/b.sock", str(tmp_path / "b.db"), locate_workers=2)
    try:
        for srv in (here, pooled):
            assert srv.load_map(SITE, blob) == 1
        want = here._answer_site(SITE, scans)
        got = pooled._answer_site(SITE, scans)
        assert [g[0] for g in got] == [w[0] for w in want]  # the messages, byte for byte
        for (_, a), (_, b) in zip(got, want):
            assert (a is None) == (b is None)
            if a is not None:
                assert (
                    a.pos_enu.tobytes() == b.pos_enu.tobytes()
                    and a.cov.tobytes() == b.cov.tobytes()
                    and (a.floor, a.floor_prob) == (b.floor, b.floor_prob)
                )
        assert got[-1][1] is None and b"no known transmitter" in got[-1][0]
        assert pooled.counts["locate-pool-failures"] == 0
        # a worker killed: this group is answered here (the same answers), the next by a new pool
        for p in list(pooled._pool._executor()._processes.values()):
            p.kill()
            p.join(5.0)
        assert [g[0] for g in pooled._answer_site(SITE, scans)] == [w[0] for w in want]
        assert pooled.counts["locate-pool-failures"] == 1 and pooled._pool.restarts == 1
        assert [g[0] for g in pooled._answer_site(SITE, scans)] == [w[0] for w in want]
        assert pooled.counts["locate-pool-failures"] == 1
        # a new map version (labels moved 3 m east): the workers answer from it
        import io

        from hybridloc.radio.radiomap import RadioMap

        moved = RadioMap.load(io.BytesIO(blob))
        moved.references = [dataclasses.replace(r, pos_enu=np.asarray(r.pos_enu) + [3.0, 0.0]) for r in moved.references]
        moved.save(tmp_path / "m2.npz")
        for srv in (here, pooled):
            assert srv.load_map(SITE, (tmp_path / "m2.npz").read_bytes()) == 2
        v2 = here._answer_site(SITE, scans)
        assert [g[0] for g in pooled._answer_site(SITE, scans)] == [w[0] for w in v2] != [w[0] for w in want]
        assert pooled._answer_site("othersite", scans[:1])[0][1] is None  # no map there: "no radio map"
        # versions replaced before any worker read them (fresh workers load lazily): the newest answers,
        # the replaced files are removed at the next call, none too early
        pooled._pool._restart()
        for srv in (here, pooled):
            assert srv.load_map(SITE, blob) == 3
            assert srv.load_map(SITE, (tmp_path / "m2.npz").read_bytes()) == 4
        assert [g[0] for g in pooled._answer_site(SITE, scans)] == [w[0] for w in v2]
        assert pooled.counts["locate-pool-failures"] == 1
        assert sorted(p.name for p in pooled._pool._dir.iterdir()) == [f"{SITE}-4.npz"]
        # a closed pool answers nothing: the server answers in-process
        pooled._pool.close()
        assert [g[0] for g in pooled._answer_site(SITE, scans)] == [w[0] for w in v2]
    finally:
        here.stop()
        pooled.stop()

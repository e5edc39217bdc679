"""The server's crowd-SLAM worker (issue #21 points 1, 4 and 5) on the real parts: real Zenoh sessions on
loopback, real SQLite files with the real migrations, the bundled sample's 35 real walks, a spawned SLAM
child process, ``hybridloc serve`` and ``hybridloc slam rebuild`` as real subprocesses killed with SIGKILL.

* a server with SLAM on a site: surveys then phones replayed through real agents (end-of-walk marker),
  and a walk closed by the idle timeout; every finished walk gets its state and track in the database and
  its device its track; live provisional tracks during a walk; a batch run on demand, announced, and the
  locator moves to the new map (:func:`test_live_crowd_slam_server`);
* a blocked, failing and crashing solve never delays an acknowledgement; errors are logged with the walk
  id and counted, the walk ends failed (:func:`test_a_slow_failing_or_crashing_solve_never_delays_ingest`);
* a walk with 10 m steps is quarantined and counted; the map in service stays
  (:func:`test_a_walk_with_impossible_steps_is_quarantined_and_the_map_stays`);
* the server SIGKILLed during a batch run loses no acknowledged batch and resumes the run after the floor
  it finished (:func:`test_server_killed_during_a_batch_run_resumes_and_loses_nothing`);
* ``slam rebuild``: progress, atomic, resumable after SIGKILL, one JSON line; bad input exits 2; a run on
  the local Dask cluster (the default) killed midway leaves no worker process and is resumed by ``--serial``
  (:func:`test_slam_rebuild_cli_is_atomic_and_resumes_after_a_kill`);
* two batch runs of a site never run at once (:func:`test_one_batch_run_per_site_and_stale_leases_resume`).
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import io
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import zenoh
from sqlalchemy import select
from sqlalchemy.orm import Session

from hybridloc.server import db as m
from hybridloc.server.slam_batch import lease_is_stale, run_batch
from hybridloc.server.slam_store import CORRECTED, FAILED, QUARANTINED, SlamBusy
from hybridloc.server.slam_worker import SlamOptions
from hybridloc.server.store import Store
from hybridloc.types import WalkEnd
from hybridloc.wire.codecs import MAP_VERSION, PROGRESS, TRACK
from hybridloc.wire.zconfig import client_config, free_port

from .slam_helpers import SITE, sample_plan, sample_walks, store_walks, straight_steps, stretched

HOOK = "tests.slam_helpers:hook"
CLI = [sys.executable, "-m", "hybridloc.cli"]


@pytest.fixture(scope="module")
def walks():
    return sample_walks()


def _wait(cond, timeout: float, what: str = "") -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what or cond}")


def _conf(ep: str, peer: bool = False) -> zenoh.Config:
    conf = client_config(ep)
    if peer:
        conf.insert_json5("mode", '"peer"')  # a peer keeps retrying its connection while the server is down
    return conf


class _Listen:
    """A plain session recording every sample under ``hl/v1/<site>/**`` (key, bytes, arrival)."""

    def __init__(self, ep: str, site: str = SITE, peer: bool = False):
        self.got: list[tuple[str, bytes, float]] = []
        self._lock = threading.Lock()
        self.session = zenoh.open(_conf(ep, peer))
        self._sub = self.session.declare_subscriber(f"hl/v1/{site}/**", self._on)

    def _on(self, smp: zenoh.Sample) -> None:
        with self._lock:
            self.got.append((str(smp.key_expr), smp.payload.to_bytes(), time.monotonic()))

    def of(self, suffix: str) -> list[bytes]:
        with self._lock:
            return [p for k, p, _ in self.got if k.endswith(suffix)]

    def close(self) -> None:
        self._sub.undeclare()
        self.session.close()


def _send_walk(up, walk, end_of_walk: bool = True) -> int:
    """A stored-walk's records through an uplink, in batches under the protocol's size limit (scans
    are the big items: 8 per batch, as the agent sends them); the last batch carries the marker."""
    seq = up.send(steps=walk.steps, marks=walk.marks)
    for k in range(0, len(walk.scans), 8):
        seq = up.send(scans=walk.scans[k : k + 8], end_of_walk=end_of_walk and k + 8 >= len(walk.scans))
    return seq


def _states(db: str, site: str = SITE) -> dict[int, str]:
    st = Store(db, migrate=False)
    try:
        return {w: s.status for w, s in st.slam.walk_states(site).items()}
    finally:
        st.close()


def _floors_done(db: str, run_id: int) -> dict[str, float]:
    eng = m.make_engine(db)
    try:
        with Session(eng) as s:
            return {
                fd.floor: fd.finished_at.timestamp() for fd in s.execute(select(m.SlamFloorDone).where(m.SlamFloorDone.run_id == run_id)).scalars()
            }
    finally:
        eng.dispose()


def _running_batch(db: str) -> int | None:
    eng = m.make_engine(db)
    try:
        with Session(eng) as s:
            return s.execute(select(m.SlamRun.id).where(m.SlamRun.kind == "batch", m.SlamRun.status == "running")).scalars().first()
    finally:
        eng.dispose()


def _filled(tmp_path: Path, walks, two_floors: bool, n: int | None = None) -> str:
    db = str(tmp_path / "slam.db")
    st = Store(db)
    st.save_floor_plan(SITE, sample_plan(two_floors))
    store_walks(st, walks[:n], two_floors)
    st.close()
    return db


# ------------------------------------------------------------------------------------------ one run at a time
def test_one_batch_run_per_site_and_stale_leases_resume(tmp_path, walks):
    db = _filled(tmp_path, walks, True, n=4)
    st = Store(db)
    try:
        live = {"token": "a", "host": os.uname().nodename, "pid": os.getpid(), "heartbeat": time.time()}
        run, resumed, _ = st.slam.claim_batch(SITE, None, live, lease_is_stale)
        assert not resumed
        # a second process while the first lives: refused (the command line while the server solves)
        with pytest.raises(SlamBusy):
            st.slam.claim_batch(SITE, None, dict(live, token="b"), lease_is_stale)
        # the holder's process is gone (a killed run): resumed at once, the same run
        dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout.strip()
        assert st.slam.renew_lease(run, "a", time.time())
        with Session(st.engine) as s, s.begin():
            r = s.get(m.SlamRun, run)
            r.stats = dict(r.stats, lease=dict(live, pid=int(dead)))
        again, resumed, taken = st.slam.claim_batch(SITE, None, dict(live, token="c"), lease_is_stale)
        assert (again, resumed, taken["pid"]) == (run, True, int(dead))
        assert not st.slam.renew_lease(run, "a", time.time())  # the old holder lost it
        # a holder elsewhere whose heartbeat stopped longer than the lease ago: resumed too
        with Session(st.engine) as s, s.begin():
            r = s.get(m.SlamRun, run)
            r.stats = dict(r.stats, lease={"token": "d", "host": "elsewhere", "pid": 1, "heartbeat": time.time() - 120})
        assert st.slam.claim_batch(SITE, None, dict(live, token="e"), lease_is_stale)[:2] == (run, True)
        # a stale run of other floors is superseded (ended failed), a new run begins
        st.slam.release_lease(run, "e")
        other, resumed, _ = st.slam.claim_batch(SITE, ["F1"], dict(live, token="f"), lease_is_stale)
        assert other != run and not resumed
        assert st.slam.runs(SITE)[1].status == "failed" and "superseded" in st.slam.runs(SITE)[1].error
    finally:
        st.close()


# ------------------------------------------------------------------------------------------ the command line
def test_slam_rebuild_cli_is_atomic_and_resumes_after_a_kill(tmp_path, walks):
    db = _filled(tmp_path, walks, True)
    # bad input: one line, exit 2 (the three commands side by side: each is mostly its start-up)
    bad = [
        (["--db", str(tmp_path / "none.db")], "no such database"),
        (["--db", db, "--site", "nowhere"], "no ended walks"),
        (["--db", db, "--site", SITE, "--floor", "F9"], "no walks on floor"),
    ]
    procs = [subprocess.Popen([*CLI, "slam", "rebuild", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for argv, _ in bad]
    try:
        for p, (_, what) in zip(procs, bad, strict=True):
            _, err = p.communicate(timeout=120)
            assert p.returncode == 2 and what in err and len(err.strip().splitlines()) == 1, err
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    assert not (tmp_path / "none.db").exists()

    r = subprocess.run([*CLI, "slam", "rebuild", "--db", db, "--serial"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1])["executor"]["kind"] == "serial"
    first = json.loads(r.stdout.strip().splitlines()[-1])["sites"][0]
    assert first["map_version"] == 1 and first["floors"] == ["F1", "F2"] and not first["resumed"]
    assert "[slam rebuild]" in r.stderr and "floors" in r.stderr
    st = Store(db)
    before_tracks = st.slam.tracks(SITE)
    before_map = st.load_map(SITE)
    st.close()
    assert before_map[0] == 1 and len(before_tracks) >= first["walks_corrected"] > 0

    # a second run killed after its first floor: readers still see version 1 and its tracks. One Dask
    # worker: the floors' tasks run one after the other, F1 first (F1 and F2 share no walk: two groups)
    p = subprocess.Popen(
        [*CLI, "slam", "rebuild", "--db", db, "--site", SITE, "--workers", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    workers: list = []
    try:
        _wait(lambda: (rid := _running_batch(db)) is not None and _floors_done(db, rid), 240, "the first floor's checkpoint")
        workers = psutil.Process(p.pid).children(recursive=True)
        assert workers, "no Dask worker process under slam rebuild"
        p.send_signal(signal.SIGKILL)
        p.wait(30)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert "tasks on a local Dask cluster of 1 worker processes" in p.stderr.read()  # the default: a local cluster
    # the worker processes exit with the killed command (Dask's parent-alive pipe): none left running
    _, alive = psutil.wait_procs(workers, timeout=15)
    assert not alive, f"Dask worker processes outlived the killed command: {alive}"
    run = _running_batch(db)
    done = _floors_done(db, run)
    assert list(done) == ["F1"]
    st = Store(db)
    mid_tracks, mid_map = st.slam.tracks(SITE), st.load_map(SITE)
    st.close()
    assert mid_map == before_map
    assert set(mid_tracks) == set(before_tracks)
    for wid, tr in before_tracks.items():
        np.testing.assert_array_equal(mid_tracks[wid].pos_enu, tr.pos_enu)

    # run again, serially: resumes the killed run after F1 (not solved again), completes it atomically
    r = subprocess.run([*CLI, "slam", "rebuild", "--db", db, "--site", SITE, "--serial"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    again = json.loads(r.stdout.strip().splitlines()[-1])["sites"][0]
    assert (again["run"], again["resumed"], again["floors_skipped"], again["map_version"]) == (run, True, ["F1"], 2)
    assert "resumed run" in r.stdout
    assert _floors_done(db, run)["F1"] == done["F1"]  # the checkpoint of F1 is the killed run's own
    st = Store(db)
    try:
        assert st.slam.unfinished_runs(SITE) == []
        assert st.slam.runs(SITE, kind="batch")[0].status == "complete"
        assert st.slam.summary(SITE)["map_version"] == 2
    finally:
        st.close()


# ------------------------------------------------------------------------------------------ late surveys
def test_a_survey_ended_during_a_run_is_in_its_crowd_map(tmp_path, walks):
    """A survey that ends while a batch run solves is not in the run's graph; the run's crowd map still
    carries its labels (from its marks), so a crowd map never replaces a survey map with fewer survey
    labels (the demo's outlier: a client fused 27 m off, served such a map)."""
    from hybridloc.radio.radiomap import RadioMap

    db = _filled(tmp_path, walks, False, n=10)  # walks 0, 3, 6, 9 are surveys
    late = walks[12]
    assert late.marks

    still = walks[15]  # a survey still walking when the run finishes: no end-of-walk marker yet
    assert still.marks

    def hook(floor: str) -> None:
        st = Store(db)
        try:
            store_walks(st, [late], prefix="late")
            store_walks(st, [still], prefix="open", ended=False)
        finally:
            st.close()

    out = run_batch(db, SITE, floor_hook=hook)
    st = Store(db)
    try:
        (lw,) = st.walks(SITE, device="late00")
        (ow,) = st.walks(SITE, device="open00")
        assert ow.end == WalkEnd.OPEN
        assert lw.walk_id not in st.slam.walk_states(SITE)  # not solved by the run that began before it
        with Session(st.engine) as s:
            prov = s.execute(select(m.RadioMapVersion.provenance).where(m.RadioMapVersion.version == out.map_version)).scalar_one()
        assert lw.walk_id in prov["survey_walks"] and lw.walk_id in prov["walks"]
        assert ow.walk_id in prov["survey_walks"]
        (tmp_path / "v.npz").write_bytes(st.load_map(SITE)[1])
        rmap = RadioMap.load(tmp_path / "v.npz")
        mine = [r for r in rmap.references if r.source == str(lw.walk_id)]
        assert mine
        # its labels lie on its marks' path: within the survey labelling's reach of a mark
        mk = np.array([[k.x, k.y] for k in late.marks])
        d = np.min(np.linalg.norm(np.array([r.pos_enu for r in mine])[:, None, :] - mk[None], axis=2), axis=1)
        gap = np.max(np.linalg.norm(np.diff(mk, axis=0), axis=1))
        assert np.all(d <= gap)
    finally:
        st.close()


# ------------------------------------------------------------------------------------------ quarantine
def test_a_walk_with_impossible_steps_is_quarantined_and_the_map_stays(tmp_path, walks):
    from hybridloc.clients.uplink import Uplink
    from hybridloc.server.service import Server

    db = _filled(tmp_path, walks, False)
    v1 = run_batch(db, SITE)
    assert v1.map_version == 1
    before = len(v1.quarantined)  # real walks the batch itself put aside (left the walkable area)
    ep = f"unixsock-stream/{tmp_path}/q.sock"
    srv = Server(ep, db, slam_sites=[SITE], slam_options=SlamOptions(poll_s=0.1, batch_every_walks=0, batch_interval_s=0)).start()
    lis = _Listen(ep)
    try:
        srv.load_map(SITE)
        # 4.5 m steps (under the wire's 5 m limit, so they are stored, hybridloc.wire.limits), the survey
        # marks kept: a walk six times its size leaves the building
        w = stretched(walks[0], 4.5 / float(np.median([s.length for s in walks[0].steps])))
        with zenoh.open(client_config(ep)) as s:
            up = Uplink(s, SITE, "giant", tmp_path / "spool")
            assert up.wait_connected(10)
            assert up.wait_acked(_send_walk(up, w), 20)
            up.close()
        st = srv.store
        gid = st.walks(SITE, device="giant")[0].walk_id
        _wait(lambda: gid in st.slam.walk_states(SITE), 240, "the giant walk's SLAM state")
        state = st.slam.walk_states(SITE)[gid]
        assert state.status == QUARANTINED and state.reason
        # the child writes the walk's state, then the worker counts its answer: the count follows shortly
        _wait(lambda: srv.slam_workers[SITE].counts.get("walks_quarantined", 0) == 1, 30, "the worker's quarantine count")
        from hybridloc.clients.status import query_status

        status = query_status(ep, timeout=10)
        slam = status["slam"]
        assert slam[SITE]["walks_quarantined"] == before + 1 and slam[SITE]["worker"]["counts"]["walks_quarantined"] == 1
        # the map in service did not move, and no track of the quarantined walk went to the device
        assert st.load_map(SITE)[0] == 1 and srv.locators[SITE][0] == 1
        assert lis.of("/giant/track") == []
        # a batch run leaves it out: the next map is built without it
        srv.request_batch(SITE)
        _wait(lambda: srv.locators[SITE][0] == 2, 240, "map version 2")
        with Session(st.engine) as ss:
            prov = ss.execute(select(m.RadioMapVersion.provenance).where(m.RadioMapVersion.version == 2)).scalar_one()
        assert gid not in prov["walks"] and len(prov["walks"]) > 0
        assert st.slam.walk_states(SITE)[gid].status == QUARANTINED
    finally:
        lis.close()
        srv.stop()


# ------------------------------------------------------------------------------------------ faults
def test_a_slow_failing_or_crashing_solve_never_delays_ingest(tmp_path, caplog):
    from hybridloc.clients.uplink import Uplink
    from hybridloc.server.service import Server

    hooks = tmp_path / "hooks"
    hooks.mkdir()
    for dev, what in (("slowphone", "block"), ("badphone", "raise"), ("crashphone", "crash")):
        (hooks / f"{dev}.{what}").write_text("")
    db = str(tmp_path / "f.db")
    opts = SlamOptions(poll_s=0.1, max_attempts=2, batch_every_walks=0, batch_interval_s=0, child_hook=HOOK, child_hook_arg=str(hooks))
    ep = f"unixsock-stream/{tmp_path}/f.sock"
    caplog.set_level(logging.ERROR, logger="hybridloc.server.slam")
    srv = Server(ep, db, slam_sites=[SITE], slam_options=opts).start()
    try:
        with zenoh.open(client_config(ep)) as s:
            ups = {d: Uplink(s, SITE, d, tmp_path / "spool" / d) for d in ("slowphone", "badphone", "crashphone", "steady")}
            assert ups["steady"].wait_connected(10)
            seq = ups["slowphone"].send(steps=straight_steps(20, 1000.0), end_of_walk=True)
            assert ups["slowphone"].wait_acked(seq, 10)
            # the child is inside the slow phone's solve (blocked until released) ...
            _wait(lambda: (hooks / "slowphone.entered").exists(), 120, "the slow solve to start")
            # ... and 200 batches of another device are acknowledged meanwhile
            for k in range(200):
                ups["steady"].send(steps=straight_steps(5, 10.0 * k))
            assert ups["steady"].wait_acked(200, 30)
            assert not (hooks / "slowphone.release").exists()
            slow_id = srv.store.walks(SITE, device="slowphone")[0].walk_id
            assert slow_id not in srv.store.slam.walk_states(SITE)  # still being solved
            (hooks / "slowphone.release").write_text("")
            _wait(lambda: slow_id in srv.store.slam.walk_states(SITE), 60, "the slow walk's state")
            # a solve that raises and one that kills the child: each tried max_attempts times, then failed
            for dev in ("badphone", "crashphone"):
                seq = ups[dev].send(steps=straight_steps(20, 2000.0), end_of_walk=True)
                assert ups[dev].wait_acked(seq, 10)
            ids = {dev: srv.store.walks(SITE, device=dev)[0].walk_id for dev in ("badphone", "crashphone")}
            k0 = ups["steady"].next_seq
            while any(srv.store.slam.walk_states(SITE).get(i) is None for i in ids.values()):
                ups["steady"].send(steps=straight_steps(5, 3000.0 + ups["steady"].next_seq))  # ingest goes on throughout
                time.sleep(0.05)
                assert ups["steady"].next_seq - k0 < 5000, "the failing walks never got a state"
            assert ups["steady"].wait_acked(ups["steady"].next_seq - 1, 30)
            for u in ups.values():
                u.close()
        states = srv.store.slam.walk_states(SITE)
        assert states[ids["badphone"]].status == FAILED and states[ids["crashphone"]].status == FAILED
        w = srv.slam_workers[SITE]
        # the worker marks a walk failed, then counts it: the count follows shortly
        _wait(lambda: w.counts["walks_failed"] == 2, 30, "the worker's failure count")
        assert w.counts["walks_failed"] == 2 and w.counts["walk_errors"] == 4 and w.counts["child_crashes"] == 2
        assert srv.worker_error is None and srv.counts["batches-persisted"] == srv.store.status()["batches"]
        logged = [r.getMessage() for r in caplog.records]
        for i in ids.values():
            assert any(f"walk {i} failed" in msg for msg in logged), logged
        assert any("test hook: the solve of badphone fails" in msg for msg in logged)
        assert any("child process died" in str(r.exc_info[1]) for r in caplog.records if r.exc_info)
    finally:
        srv.stop()


# ------------------------------------------------------------------------------------------ the live server
def test_live_crowd_slam_server(tmp_path, capsys):
    from hybridloc.cli import main as cli_main
    from hybridloc.clients.agent import Agent, PoseWriter, replay_phone
    from hybridloc.clients.status import query_status
    from hybridloc.clients.uplink import Uplink
    from hybridloc.demo import bundled_split
    from hybridloc.io.msft import read_ilc_trace
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.server.rebuild import rebuild
    from hybridloc.server.service import Server

    surveys, phones, _ = bundled_split()
    surveys = surveys[::3]  # 11 of the 31 survey walks make the survey map
    db = str(tmp_path / "live.db")
    assert cli_main(["floorplan", "import", str(ILC_SITE1_F1), "--site", SITE, "--db", db]) == 0
    ep = f"tcp/127.0.0.1:{free_port()}"
    opts = SlamOptions(idle_timeout_s=2.0, poll_s=0.1, batch_every_walks=0, batch_interval_s=0, live_every_s=3.0)
    srv = Server(ep, db, slam_sites=[SITE], slam_options=opts).start()
    lis = _Listen(ep)
    st = srv.store

    applied: dict[str, int] = {}

    def replay(path, kind: str, speed: float) -> str:
        tr = read_ilc_trace(path)
        dev = f"{kind}-{Path(path).name[:12]}"
        with zenoh.open(client_config(ep)) as s:
            ag = Agent(s, SITE, dev, tmp_path / "spool" / dev, PoseWriter(None), tr.device_model)
            assert ag.uplink.wait_connected(10)
            replay_phone(ag, tr, speed, survey=kind == "survey", lockstep=kind == "phone")
            res = ag.close(wait=30)
        assert res.acked == res.batches
        applied[dev] = res.tracks_applied
        return dev

    try:
        with cf.ThreadPoolExecutor(4) as ex:
            survey_devs = list(ex.map(lambda p: replay(p, "survey", 0.0), surveys))
        survey_ids = [w.walk_id for d in survey_devs for w in st.walks(SITE, device=d)]
        _wait(lambda: set(survey_ids) <= set(st.slam.walk_states(SITE)), 300, "the survey walks' SLAM states")
        # the survey radio map, stored by someone else (map rebuild): the worker serves and announces it
        v, n_lab, _ = rebuild(st, SITE, tmp_path / "rebuild-cache")
        assert v == 1
        _wait(lambda: srv.locators.get(SITE, (None,))[0] == 1, 30, "the survey map in service")
        # the phones (81-114 s walks), in lock-step at 6x: each walk is open for 14-19 s or more, several
        # provisional corrections at one per 3 s of wall time (live corrections), then ended
        with cf.ThreadPoolExecutor(4) as ex:
            phone_devs = list(ex.map(lambda p: replay(p, "phone", 6.0), phones))
        # a device that stops without an end-of-walk marker: its walk ends after the idle timeout
        with zenoh.open(client_config(ep)) as s:
            up = Uplink(s, SITE, "idler", tmp_path / "spool" / "idler")
            assert up.wait_connected(10)
            assert up.wait_acked(up.send(steps=straight_steps(30, 500.0)), 10)
            up.close()
        idle_id = st.walks(SITE, device="idler")[0].walk_id
        phone_ids = {d: st.walks(SITE, device=d)[0].walk_id for d in phone_devs}
        _wait(lambda: set(phone_ids.values()) | {idle_id} <= set(st.slam.walk_states(SITE)), 300, "the phone walks' states")
        assert st.walks(SITE, device="idler")[0].end.value == "idle"
        # every finished walk has its state; the surveys are corrected through their marks
        ended = [w.walk_id for w in st.walks(SITE, ended_only=True)]
        states = st.slam.walk_states(SITE)
        assert set(ended) <= set(states)
        assert all(states[i].status == CORRECTED and states[i].anchored == "marks" for i in survey_ids)
        # every walk with a track sent it to its device, the stored track itself
        tracks = st.slam.tracks(SITE)
        for dev, wid in phone_ids.items():
            if wid not in tracks:
                continue
            got = [TRACK.decode(b) for b in lis.of(f"/{dev}/track")]
            final = [t for t in got if t.walk_id == wid and t.run == states[wid].run_id]
            assert final, f"{dev} received no track of walk {wid}"
            np.testing.assert_allclose(final[-1].track.pos_enu, tracks[wid].pos_enu, atol=1e-9)
        # live: provisional tracks of the open walk (runs of their own, older than the walk's final run)
        # reached phones while they walked, and their agents re-anchored on them
        assert srv.slam_workers[SITE].counts["live_tracks_published"] >= 1
        early = [
            t for d, wid in phone_ids.items() for t in map(TRACK.decode, lis.of(f"/{d}/track")) if t.walk_id == wid and t.run < states[wid].run_id
        ]
        assert early and sum(applied[d] for d in phone_devs) >= 1
        # a batch re-solve on demand: progress, a new map version announced, the locator moves
        srv.request_batch(SITE)
        _wait(lambda: srv.locators[SITE][0] == 2, 300, "map version 2 in service")
        _wait(lambda: any(MAP_VERSION.decode(b).version == 2 for b in lis.of("/map/version")), 10, "the map version 2 announcement")
        mv = [MAP_VERSION.decode(b) for b in lis.of("/map/version")]
        assert [x.version for x in mv] == [1, 2] and mv[0].source == "survey" and mv[1].source == "slam" and mv[1].walks > len(survey_ids) // 2
        prog = [PROGRESS.decode(b) for b in lis.of("/progress")]
        assert any(p.stage == "floors" and p.floor == "F1" and p.done == 1 and p.total == 1 for p in prog)
        status = query_status(ep, timeout=10)
        slam = status["slam"][SITE]
        assert slam["map_version"] == 2 and slam["walks_pending"] == 0 and slam["worker"]["counts"]["batch_runs"] == 1
        assert slam["walks_corrected"] >= len(survey_ids)
        capsys.readouterr()
        assert cli_main(["status", "--endpoint", ep]) == 0
        printed = capsys.readouterr().out
        assert f"slam {SITE}: walks corrected {slam['walks_corrected']}," in printed and "map v2 (slam)" in printed
        assert "loops accepted" in printed and "coverage" in printed and "worker: added" in printed
    finally:
        lis.close()
        srv.stop()


# ------------------------------------------------------------------------------------------ SIGKILL
def test_server_killed_during_a_batch_run_resumes_and_loses_nothing(tmp_path, walks):
    from hybridloc.clients.uplink import Uplink

    db = _filled(tmp_path, walks, True, n=33)
    run_batch(db, SITE)  # the site solved once: map version 1, every walk held
    ep = f"tcp/127.0.0.1:{free_port()}"
    # one process for the batch: the kill must fall between its floors' checkpoints (with the floors side by
    # side, F2 is solved beside F1 and checkpointed right after it; test_slam_fork.py covers that path)
    argv = [*CLI, "serve", "--endpoint", ep, "--db", db, "--site", SITE, "--slam-batch-every", "2", "--slam-interval", "0", "--slam-processes", "1"]
    out: list[str] = []

    def serve():
        p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        while True:
            line = p.stdout.readline()
            assert line, "".join(out)
            out.append(line)
            if "listening" in line:
                break
        threading.Thread(target=lambda: out.extend(p.stdout), daemon=True).start()  # keep the pipe drained
        return p

    srv = serve()
    lis = _Listen(ep, peer=True)
    acked: dict[str, int] = {}
    stop = threading.Event()
    sent = {"n": 0}

    def steady():
        """A device sending a batch every 20 ms from before the kill to after the restart."""
        with zenoh.open(_conf(ep, peer=True)) as s:
            up = Uplink(s, SITE, "steady", tmp_path / "spool" / "steady", resend_after=0.5)
            k = 0
            while not stop.is_set():
                up.send(steps=straight_steps(3, 5.0 * k))
                k += 1
                up.resend_if_stalled()
                acked["steady"] = max(acked.get("steady", 0), up.acked)
                time.sleep(0.02)
            t_end = time.monotonic() + 60
            while up.acked < up.next_seq - 1 and time.monotonic() < t_end:
                up.resend_if_stalled()
                time.sleep(0.05)
            acked["steady"] = up.acked
            sent["n"] = up.next_seq - 1
            up.close()

    t = threading.Thread(target=steady)
    t.start()
    try:
        # two new walks (the last sample walks): the batch run is due after them
        with zenoh.open(client_config(ep)) as s:
            for i, w in ((33, walks[33]), (34, walks[34])):
                up = Uplink(s, SITE, f"new{i}", tmp_path / "spool" / f"new{i}")
                assert up.wait_connected(10)
                assert up.wait_acked(_send_walk(up, w), 20)
                up.close()
        # SIGKILL as soon as the first floor is checkpointed (its progress message), F2 being solved
        _wait(lambda: any(PROGRESS.decode(b).stage == "floors" and PROGRESS.decode(b).done == 1 for b in lis.of("/progress")), 300, "floor F1 done")
        srv.send_signal(signal.SIGKILL)
        srv.wait(30)
        run = _running_batch(db)
        done = _floors_done(db, run)
        assert list(done) == ["F1"]
        n_acked_before = acked.get("steady", 0)
        time.sleep(1.0)  # the steady device keeps sending into the void (spooled)
        srv = serve()
        _wait(lambda: _running_batch(db) is None, 300, "the resumed run to complete")
        stop.set()
        t.join(90)
        st = Store(db, migrate=False)
        try:
            runs = st.slam.runs(SITE, kind="batch")
            assert runs[0].run_id == run and runs[0].status == "complete" and runs[0].stats.get("resumes") == 1
            assert _floors_done(db, run)["F1"] == done["F1"]  # F1 not solved again
            assert st.slam.summary(SITE)["map_version"] == 2
            # nothing acknowledged is lost: every batch the device heard acknowledged is stored
            with Session(st.engine) as s:
                stored = s.execute(select(m.Device.last_seq).where(m.Device.id == "steady")).scalar_one()
                n_rows = len(s.execute(select(m.Batch.seq).where(m.Batch.device_id == "steady")).scalars().all())
        finally:
            st.close()
        assert n_acked_before > 0 and acked["steady"] == sent["n"] == stored == n_rows, "".join(out)
    finally:
        stop.set()
        t.join(90)
        lis.close()
        if srv.poll() is None:
            srv.send_signal(signal.SIGTERM)
            try:
                srv.wait(30)
            except subprocess.TimeoutExpired:
                srv.kill()
                srv.wait()


# ------------------------------------------------------------------------------------------ grown map
def test_the_served_map_grows_at_every_added_walk(tmp_path, walks, capsys):
    """``SlamOptions.grow_map``: a map version from a batch over 27 walks, then 8 more walks stored and
    added one by one by the worker. Each added crowd walk with an absolute track is served on top of
    the version - its WiFi scans at the stored track's positions, so a scan of it is located onto its
    own label (distance 0 outweighs every other neighbour) - survey walks and relative ones are not;
    the locate workers answer alike; a batch's version takes over the walks it holds."""
    from hybridloc.radio.radiomap import RadioMap
    from hybridloc.server.locate_pool import LocatePool, make_locator
    from hybridloc.server.service import Server
    from hybridloc.slam.online import labels_from_tracks

    db = _filled(tmp_path, walks, False, n=27)
    assert run_batch(db, SITE).map_version == 1
    st = Store(db)
    late = walks[27:35]  # 27 and 30 keep their survey marks
    store_walks(st, late, prefix="late")
    late_ids = [st.walks(SITE, device=f"late{i:02d}")[0].walk_id for i in range(len(late))]
    st.close()
    ep = f"unixsock-stream/{tmp_path}/g.sock"
    opts = SlamOptions(poll_s=0.1, batch_every_walks=0, batch_interval_s=0, live_every_s=0, grow_map=True)
    srv = Server(ep, db, slam_sites=[SITE], slam_options=opts).start()
    pool = LocatePool(1)
    try:
        srv.load_map(SITE)
        st = srv.store
        _wait(lambda: set(late_ids) <= set(st.slam.walk_states(SITE)), 240, "the late walks' SLAM states")
        _wait(lambda: srv.slam_workers[SITE].counts.get("walks_added", 0) == len(late), 30, "the worker's count of added walks")
        states = st.slam.walk_states(SITE)
        crowd = {wid for wid, w in zip(late_ids, late) if not w.marks and states[wid].status == CORRECTED and states[wid].anchored != "relative"}
        assert crowd, "no late crowd walk was placed on the map: nothing to serve"
        base, grown = srv._grown[SITE].base, srv._grown[SITE].labels
        assert {ls.source for ls in grown} == {str(w) for w in crowd}
        assert srv.counts["map-walks-grown"] == len(crowd) == srv.slam_workers[SITE].counts["map_walks_grown"]
        from hybridloc.cli import main as cli_main

        capsys.readouterr()
        assert cli_main(["status", "--endpoint", ep]) == 0
        assert f"grown into the served map {len(crowd)}" in capsys.readouterr().out
        # the labels are the stored tracks' (what a batch's map would take from them)
        walks_of = [st.read_walk(w) for w in sorted(crowd)]
        expect = [ls for ls in labels_from_tracks(walks_of, st.slam.tracks(SITE, walk_ids=crowd)) if ls.scan.technology.value == "wifi"]
        key = lambda ls: (ls.source, ls.scan.t)  # noqa: E731
        got = sorted(grown, key=key)
        expect.sort(key=key)
        assert [key(a) for a in got] == [key(b) for b in expect]
        np.testing.assert_allclose([a.pos_enu for a in got], [b.pos_enu for b in expect], atol=1e-9)
        version, loc, blob = srv.locators[SITE]
        assert version == 1 and len(loc.knn.refs) == len(base.knn.refs) + len(grown)
        # a scan of an added walk finds itself: located onto its own label; the version alone cannot
        probe = got[:: max(1, len(got) // 5)]
        fixes = srv.answer_many(SITE, [ls.scan for ls in probe])
        for ls, fx in zip(probe, fixes):
            assert fx.fix is not None and np.linalg.norm(fx.fix.pos_enu - ls.pos_enu) < 1e-3
        alone = make_locator(RadioMap.load(io.BytesIO(blob)), "knn")
        assert max(np.linalg.norm(r.fix.pos_enu - ls.pos_enu) for ls, r in zip(probe, alone.locate_many([ls.scan for ls in probe]))) > 0.1
        # the locate workers answer the same from the version and the labels grown on it
        pool.add_map(SITE, 1, blob)
        pool.add_labels(SITE, 1, grown)
        from_pool = pool.answer(SITE, [ls.scan for ls in probe])
        assert from_pool is not None and len(from_pool) == len(fixes)
        np.testing.assert_array_equal([a.pos_enu for _, a in from_pool], [fx.fix.pos_enu for fx in fixes])
        # a walk's labels served again replace its own; the version's own walks are not taken
        one = [ls for ls in grown if ls.source == got[0].source]
        assert srv.add_labels(SITE, one) == 1 and len(srv._grown[SITE].labels) == len(grown)
        held1 = next(iter(srv._grown[SITE].held))
        assert srv.add_labels(SITE, [dataclasses.replace(one[0], source=held1)]) == 0
        np.testing.assert_array_equal(
            srv.locators[SITE][1].knn.pos, loc.knn.pos[: len(base.knn.refs)].tolist() + [ls.pos_enu for ls in srv._grown[SITE].labels]
        )
        # a batch's version holds the added walks: their labels leave the grown set, and so do those of
        # walks the batch made relative or put aside
        srv.request_batch(SITE)
        _wait(lambda: srv.locators[SITE][0] == 2, 240, "map version 2")
        v2 = RadioMap.load(io.BytesIO(srv.locators[SITE][2]))
        held = {r.source for r in v2.references}
        states = st.slam.walk_states(SITE)
        placed = {str(w) for w in crowd if states[w].status == CORRECTED and states[w].anchored != "relative"}
        left = srv._grown[SITE].labels
        assert {ls.source for ls in left} == (placed - held)
        assert len(srv.locators[SITE][1].knn.refs) == len(v2.references) + len(left)
        # a version read before the newer one came (another thread's load, installing late) never
        # replaces the newer one in service
        srv.store.load_map = lambda site: (1, blob)  # what that thread read
        try:
            assert srv.load_map(SITE) == 2 and srv.locators[SITE][0] == 2
        finally:
            del srv.store.load_map
    finally:
        pool.close()
        srv.stop()
    # a restarted server serves the labels of the walks its version does not hold, from the database
    st = Store(db)
    ws = st.slam.walk_states(SITE)
    with Session(st.engine) as ss:
        ss.execute(m.RadioMapVersion.__table__.delete().where(m.RadioMapVersion.version == 2))
        ss.commit()
    st.close()
    placed = {str(w) for w in crowd if ws[w].status == CORRECTED and ws[w].anchored != "relative"}
    again = Server(f"unixsock-stream/{tmp_path}/g2.sock", db, slam_sites=[SITE], slam_options=dataclasses.replace(opts, poll_s=30.0))
    try:
        assert again.load_map(SITE) == 1
        assert {ls.source for ls in again._grown[SITE].labels} == placed
        assert len(again.locators[SITE][1].knn.refs) == len(again._grown[SITE].base.knn.refs) + len(again._grown[SITE].labels)
    finally:
        again.stop()
    pool = LocatePool(1)
    srv = Server(f"unixsock-stream/{tmp_path}/g3.sock", db)  # the option off: nothing grown
    try:
        assert srv.load_map(SITE) == 1 and srv._grown[SITE].labels == [] and srv.counts["map-walks-grown"] == 0
    finally:
        pool.close()
        srv.stop()

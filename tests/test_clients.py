"""Local fusion and the client agents against a real server on loopback."""

import math

import numpy as np
import zenoh

from hybridloc.fusion import LocalFusion
from hybridloc.types import AbsoluteFix, StepEvent

from .helpers import wait_until as _wait_for


def _walk(n, heading, length=0.7, t0=0.0):
    return [StepEvent(t0 + 0.5 * i, length, heading, 0.05, math.radians(2), 0.0, math.radians(1)) for i in range(n)]


def test_fusion_learns_heading_bias_and_step_scale_from_fixes():
    """Steps report heading 0 and 0.7 m; the truth walks at +10 deg with 0.8 m steps; fixes every 10 steps."""
    rng = np.random.default_rng(0)
    f = LocalFusion(init=(0.0, 0.0, 0.5))
    true = np.zeros(2)
    bias, scale = math.radians(10), 0.8 / 0.7
    for k in range(40):
        for st in _walk(10, 0.0, t0=5.0 * k):
            f.predict(st)
            true += 0.8 * np.array([math.cos(bias), math.sin(bias)])
        ok, _ = f.correct(AbsoluteFix(5.0 * k + 5, true + rng.normal(0, 1.0, 2), np.eye(2) * 1.0, "wifi", "F1", 0.99))
    # consistent (within 3 sigma of its own covariance) and informative (sigma well below the prior)
    sb, ss = math.sqrt(f.P[2, 2]), math.sqrt(f.P[3, 3])
    assert abs(f.x[2] - bias) < 3 * sb and sb < math.radians(6)
    assert abs(f.x[3] - scale) < 3 * ss and ss < 0.05
    assert np.linalg.norm(f.x[:2] - true) < 2.0
    assert np.allclose(f.P, f.P.T) and np.linalg.eigvalsh(f.P).min() > 0


def test_fusion_rejects_outliers_outside_the_95_region_and_reinitialises_when_lost():
    f = LocalFusion(init=(0.0, 0.0, 0.5))
    for st in _walk(10, 0.0):
        f.predict(st)
    ok, _ = f.correct(AbsoluteFix(5.0, [40.0, 0.0], np.eye(2), "gps", "F1"))  # multipath: 33 m off
    assert not ok and f.n_rejected == 1
    for i in range(5):  # the world keeps saying we are elsewhere: the filter gives in and restarts there
        ok, e = f.correct(AbsoluteFix(6.0 + i, [100.0, 50.0], np.eye(2), "wifi", "F2", 0.95))
    assert ok and np.linalg.norm(f.x[:2] - [100, 50]) < 1e-6 and f.floor == "F2"


def test_phone_agent_end_to_end_with_server_down_then_up(tmp_path):
    from hybridloc.clients.agent import Agent, PoseWriter, replay_phone
    from hybridloc.io.msft import find_ilc_traces, read_ilc_trace
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.server.service import Server
    from hybridloc.wire.zconfig import client_config

    ep = f"unixsock-stream/{tmp_path}/s.sock"
    traces = find_ilc_traces(ILC_SITE1_F1)
    tr = read_ilc_trace(traces[0])
    # the server is not up yet: the agent dead-reckons and spools (a peer keeps retrying to connect)
    conf = client_config(ep)
    conf.insert_json5("mode", '"peer"')
    with zenoh.open(conf) as s:
        ag = Agent(s, "site1", "phoneA", tmp_path / "spool", PoseWriter(tmp_path / "pose.csv"), tr.device_model, init=(0.0, 0.0, 1.0))
        replay_phone(ag, tr, speed=0.0)
        assert ag.uplink.acked == 0 and ag.uplink.pending > 0
        n_sent = ag.uplink.next_seq - 1
        srv = Server(ep, str(tmp_path / "db.sqlite")).start()
        try:
            res = ag.close(wait=30)  # catches up: resends the spool once the server is there
        finally:
            srv.stop()
    assert res.acked == n_sent and res.steps > 20
    lines = (tmp_path / "pose.csv").read_text().splitlines()
    assert lines[0] == "t,x,y,floor,sigma_x,sigma_y,kind" and len(lines) > res.steps


def test_uplink_resend_skips_a_batch_acknowledged_while_resending(tmp_path):
    """An acknowledgement can land between listing the spool and reading a file (it deletes the file):
    the resend must skip it, not crash the agent (seen with 77 clients at 20x in ``eval fusion``)."""
    from hybridloc.clients.uplink import Uplink
    from hybridloc.wire.zconfig import client_config

    conf = client_config(f"unixsock-stream/{tmp_path}/none.sock")
    conf.insert_json5("mode", '"peer"')  # nobody listens: every batch stays pending
    with zenoh.open(conf) as s:
        up = Uplink(s, "site1", "phoneR", tmp_path / "spool", resend_after=0.0)
        for _ in range(3):
            up.send(steps=_walk(2, 0.0))
        sent = []

        def put_then_ack_next(payload):  # the server acknowledges batch 2 while batch 1 is resent
            sent.append(payload)
            (up.spool / f"{2:012d}.json").unlink(missing_ok=True)

        up._put = put_then_ack_next
        assert up.resend_if_stalled() == 2 and len(sent) == 2
        up.close()


def test_lockstep_agent_gets_an_answer_per_scan_and_run_fusion_replays_it_exactly(tmp_path):
    """Every scan sent gets an answer (a fix, or "no fix" with a reason for a scan of unknown
    transmitters); the fixes and the step counts at which they arrived, fed to the same filter by
    ``run_fusion``, reproduce the live pose rows exactly."""
    from hybridloc.clients.agent import Agent, PoseWriter
    from hybridloc.fusion import run_fusion
    from hybridloc.radio.radiomap import BuildParams, build_radio_map
    from hybridloc.radio.survey import LabelledScan
    from hybridloc.server.service import Server
    from hybridloc.types import RfScan
    from hybridloc.wire.zconfig import client_config, free_port

    rng = np.random.default_rng(0)
    aps = {"a1": (0, 0), "a2": (30, 0), "a3": (0, 20), "a4": (30, 20)}

    def reading(p):
        return {k: -40 - 30 * np.log10(max(1.0, np.hypot(p[0] - q[0], p[1] - q[1]))) + rng.normal(0, 1.5) for k, q in aps.items()}

    refs = [LabelledScan(RfScan(float(i), "wifi", reading(p)), p, 0.5, "F1") for i, p in enumerate(rng.uniform(0, [30, 20], (800, 2)))]
    build_radio_map(refs, site="site1", params=BuildParams()).save(tmp_path / "m.npz")
    ep = f"tcp/127.0.0.1:{free_port()}"
    srv = Server(ep, str(tmp_path / "db.sqlite")).start()
    try:
        srv.load_map("site1", (tmp_path / "m.npz").read_bytes())
        with zenoh.open(client_config(ep)) as s:
            ag = Agent(s, "site1", "phoneL", tmp_path / "spool", PoseWriter(None), init=(2.0, 10.0, 1.0))
            assert ag.uplink.wait_connected()
            steps = _walk(60, 0.0, t0=0.0)  # 0.7 m every 0.5 s along +x from (2, 10)
            for i, st in enumerate(steps):
                ag.add_step(st)
                assert ag.estimate.t == st.t and ag.estimate.cov.shape == (2, 2)
                if i % 4 == 3:  # a scan every 2 s; one of unknown transmitters only
                    rssi = {"zz:zz": -60.0} if i == 31 else reading((2.0 + 0.7 * (i + 1), 10.0))
                    ag.add_scan(RfScan(st.t, "wifi", rssi))
                    ag.flush(st.t)
                    assert ag.wait_answers(timeout=10.0)
            r = ag.close(wait=10)
    finally:
        srv.stop()
    assert ag.n_asked == 15 and ag.n_answers == 15 and r.fixes_received == 14  # one "no fix" answer
    assert srv.counts["no-fix-pushed"] == 1
    replay = run_fusion(LocalFusion(init=(2.0, 10.0, 1.0)), r.step_events, [f for _, f in r.fix_log], [a for a, _ in r.fix_log])
    live = [(row[0], row[1], row[2]) for row in r.poses]
    assert len(replay) == len(live)
    assert np.allclose([(e.t, e.pos[0], e.pos[1]) for e in replay], live, atol=1e-9)


def test_cli_phone_client_with_the_particle_filter_stays_on_the_floor_plan(tmp_path):
    """``hybridloc serve --map`` + ``hybridloc client phone --filter particle --lockstep`` on the bundled
    sample: fixes arrive for the scans, and every live position of the particle filter lies on the
    floor plan (particles outside it or across its walls die). ``--filter kourogi`` runs alike."""
    import csv
    import json
    import subprocess
    import sys

    import shapely

    from hybridloc.io.msft import read_ilc_site, read_ilc_trace
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.wire.zconfig import free_port

    traces = sorted((ILC_SITE1_F1 / "F1" / "path_data_files").glob("*.txt.gz"))
    run = lambda *a: subprocess.run([sys.executable, "-m", "hybridloc.cli", *a], capture_output=True, text=True, timeout=300)  # noqa: E731
    m = tmp_path / "f1.npz"
    r = run("map", "build", "--format", "msft", *map(str, traces[:12]), "--out", str(m))
    assert r.returncode == 0, r.stderr
    site = read_ilc_trace(traces[13]).site
    ep = f"tcp/127.0.0.1:{free_port()}"
    srv = subprocess.Popen(
        [sys.executable, "-m", "hybridloc.cli", "serve", "--endpoint", ep, "--db", str(tmp_path / "db.sqlite"), "--map", f"{site}={m}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert "listening" in srv.stdout.readline()
        pose = tmp_path / "pose.csv"
        r = run(
            "client",
            "phone",
            "--endpoint",
            ep,
            "--site",
            site,
            "--replay",
            str(traces[13]),
            "--speed",
            "0",
            "--lockstep",
            "--filter",
            "particle",
            "--floorplan",
            str(ILC_SITE1_F1),
            "--spool",
            str(tmp_path / "spool"),
            "--pose-out",
            str(pose),
        )
        assert r.returncode == 0, r.stderr
        # the paper's own filter through the same client path (another device, same walk)
        pose_k = tmp_path / "pose-kourogi.csv"
        rk = run(
            "client",
            "phone",
            "--endpoint",
            ep,
            "--site",
            site,
            "--replay",
            str(traces[13]),
            "--speed",
            "0",
            "--lockstep",
            "--filter",
            "kourogi",
            "--device",
            "phone-kourogi",
            "--spool",
            str(tmp_path / "spool-k"),
            "--pose-out",
            str(pose_k),
        )
        assert rk.returncode == 0, rk.stderr
        rows_k = list(csv.DictReader(open(pose_k)))
        assert rows_k and all(np.isfinite([float(w["x"]), float(w["y"]), float(w["sigma_x"])]).all() for w in rows_k)
        # a device's step-length calibration: a survey teaches it from its marks, a phone from the
        # step scale its Kalman filter learned from the fixes (when they pinned it)
        cal = tmp_path / "dev.json"
        rs = run(
            "client",
            "survey",
            "--endpoint",
            ep,
            "--site",
            site,
            "--replay",
            str(traces[14]),
            "--speed",
            "0",
            "--device",
            "survey-cal",
            "--spool",
            str(tmp_path / "spool-s"),
            "--calibration",
            str(cal),
            "--update-calibration",
        )
        assert rs.returncode == 0, rs.stderr
        d = json.loads(cal.read_text())
        assert d["n_segments"] >= 1 and 0.5 <= d["coef"][0] <= 0.9, rs.stdout
        rp = run(
            "client",
            "phone",
            "--endpoint",
            ep,
            "--site",
            site,
            "--replay",
            str(traces[13]),
            "--speed",
            "0",
            "--lockstep",
            "--device",
            "phone-cal",
            "--spool",
            str(tmp_path / "spool-c"),
            "--calibration",
            str(cal),
            "--update-calibration",
        )
        assert rp.returncode == 0, rp.stderr
        assert "calibration" in rp.stdout and json.loads(cal.read_text())["n_segments"] >= d["n_segments"]
    finally:
        srv.terminate()
        srv.wait(30)
    fixes = int(r.stdout.split(" fixes received")[0].rsplit(" ", 1)[1])
    assert fixes > 0, r.stdout
    rows = list(csv.DictReader(open(pose)))
    assert rows and {"t", "x", "y", "floor", "sigma_x", "sigma_y"} <= set(rows[0])
    # on the footprint: the particles keep to the walkable area (outline minus shops), but the reported
    # mean of a cloud split between two corridors, or in a bend, may lie in a shop between them
    walk = read_ilc_site(ILC_SITE1_F1).floor("F1").outline.buffer(0.5)
    xy = np.array([[float(w["x"]), float(w["y"])] for w in rows])
    assert shapely.contains_xy(walk, xy[:, 0], xy[:, 1]).mean() > 0.95


def test_cli_phone_client_live_from_a_pipe(tmp_path):
    """``client phone --live -``: IMU samples and WiFi scans arrive as lines on stdin (what a sensor
    bridge writes); malformed lines are counted and skipped, the client walks, uploads and gets fixes."""
    import subprocess
    import sys

    from hybridloc.io.msft import read_ilc_trace
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.wire.zconfig import free_port

    traces = sorted((ILC_SITE1_F1 / "F1" / "path_data_files").glob("*.txt.gz"))
    run = lambda *a, **k: subprocess.run([sys.executable, "-m", "hybridloc.cli", *a], capture_output=True, text=True, timeout=300, **k)  # noqa: E731
    m = tmp_path / "f1.npz"
    assert run("map", "build", "--format", "msft", *map(str, traces[:12]), "--out", str(m)).returncode == 0
    tr = read_ilc_trace(traces[13])
    imu = tr.imu
    lines = ["t,ax,ay,az,gx,gy,gz,mx,my,mz"]
    scans = iter(sorted(tr.wifi_scans, key=lambda s: s.t))
    nxt = next(scans, None)
    for i in range(len(imu)):
        while nxt is not None and nxt.t <= imu.t[i]:
            lines.append(f"wifi,{nxt.t:.3f}," + ";".join(f"{k}={v:.0f}" for k, v in nxt.rssi_dbm.items()))
            nxt = next(scans, None)
        row = [imu.t[i], *imu.accel_body[i], *imu.gyro_body[i], *imu.mag_body[i]]
        lines.append(",".join(f"{v:.6g}" if k else f"{v:.3f}" for k, v in enumerate(row)))
        if i == 500:
            lines += ["garbage", "1.0,2.0", "wifi,nan,aa=1"]  # three malformed records
    site = tr.site
    ep = f"tcp/127.0.0.1:{free_port()}"
    srv = subprocess.Popen(
        [sys.executable, "-m", "hybridloc.cli", "serve", "--endpoint", ep, "--db", str(tmp_path / "db.sqlite"), "--map", f"{site}={m}"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert "listening" in srv.stdout.readline()
        r = run(
            "client",
            "phone",
            "--endpoint",
            ep,
            "--site",
            site,
            "--live",
            "-",
            "--rate",
            f"{imu.rate_hz:.3f}",
            "--lockstep",
            "--spool",
            str(tmp_path / "spool"),
            "--pose-out",
            str(tmp_path / "pose.csv"),
            input="\n".join(lines) + "\n",
        )
    finally:
        srv.terminate()
        srv.wait(30)
    assert r.returncode == 0, r.stderr
    assert "3 malformed lines skipped" in r.stdout, r.stdout
    steps = int(r.stdout.split(" steps,")[0].rsplit(" ", 1)[1])
    fixes = int(r.stdout.split(" fixes received")[0].rsplit(" ", 1)[1])
    assert steps > 20 and fixes > 0, r.stdout
    # a stream in g is refused with a message naming the unit
    g_lines = [",".join(f"{v:.6g}" for v in [imu.t[i], *(imu.accel_body[i] / 9.80665), *imu.gyro_body[i]]) for i in range(300)]
    r = run(
        "client",
        "phone",
        "--endpoint",
        ep,
        "--site",
        site,
        "--live",
        "-",
        "--rate",
        "50",
        "--spool",
        str(tmp_path / "spool2"),
        input="\n".join(g_lines) + "\n",
    )
    assert r.returncode != 0 and "in g" in r.stderr


def test_phone_client_carried_turned_estimates_its_walking_offset(tmp_path):
    """The client's PDR settings reach its PDR: the bundled walk replayed with the phone turned by
    180 deg (a pocket, upside down) and --estimate-offset walks the same way as the phone held
    normally (within 20 deg, the estimator's spread on real walks); without it, backwards."""
    import dataclasses

    from hybridloc.clients.agent import Agent, PoseWriter, replay_phone
    from hybridloc.io.msft import find_ilc_traces, read_ilc_trace
    from hybridloc.pdr import PhonePdrConfig
    from hybridloc.pdr.evaluate import turn_in_hand
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.units import wrap_angle
    from hybridloc.wire.zconfig import client_config

    tr = max((read_ilc_trace(p) for p in find_ilc_traces(ILC_SITE1_F1)), key=lambda t: t.imu.t[-1] - t.imu.t[0])
    turned = dataclasses.replace(tr, imu=turn_in_hand(tr.imu, math.pi))
    conf = client_config(f"unixsock-stream/{tmp_path}/none.sock")
    conf.insert_json5("mode", '"peer"')  # no server: the agent dead-reckons and spools
    heading = {}
    with zenoh.open(conf) as s:
        for name, trace, cfg in (
            ("held", tr, PhonePdrConfig(estimate_offset=True)),
            ("turned", turned, PhonePdrConfig(estimate_offset=True)),
            ("turned, no estimate", turned, None),
        ):
            ag = Agent(s, "site1", f"p-{len(heading)}", tmp_path / f"spool{len(heading)}", PoseWriter(None), tr.device_model, init=(0.0, 0.0, 1.0))
            pdr = replay_phone(ag, trace, speed=0.0, pdr_config=cfg)
            ag.close(wait=0.1)
            h = np.array([st.heading for st in pdr.steps[len(pdr.steps) // 2 :]])
            heading[name] = float(np.angle(np.exp(1j * h).mean()))
    assert abs(wrap_angle(heading["turned"] - heading["held"])) < math.radians(20)
    assert abs(wrap_angle(heading["turned, no estimate"] - heading["held"])) > math.radians(120)


def test_end_of_walk_marker_closes_the_walk_on_the_server(tmp_path):
    """The agent marks the last batch of a walk (end_walk, as every replay and live driver does at the
    end of its input); the server stores the walk as ended by its marker at once, not after the idle gap.
    A walk whose client sends no marker (an older client) stays open."""
    from hybridloc.clients.agent import Agent, PoseWriter
    from hybridloc.server.service import Server
    from hybridloc.server.store import Store
    from hybridloc.types import WalkEnd
    from hybridloc.wire.zconfig import client_config, free_port

    ep = f"tcp/127.0.0.1:{free_port()}"
    db = str(tmp_path / "db.sqlite")
    srv = Server(ep, db).start()
    try:
        with zenoh.open(client_config(ep)) as s:
            for device, end in (("marked", True), ("older", False)):
                ag = Agent(s, "site1", device, tmp_path / f"spool-{device}", PoseWriter(None))
                assert ag.uplink.wait_connected()
                steps = _walk(10, 0.0, t0=100.0)
                for st in steps:
                    ag.add_step(st)
                    ag.tick(st.t)
                if end:
                    ag.end_walk(steps[-1].t)
                else:
                    ag.flush(steps[-1].t)
                assert ag.uplink.wait_acked(timeout=10.0)
                ag.close(wait=10)
    finally:
        srv.stop()
    store = Store(db)
    try:
        ends = {w.device: w.end for w in store.walks("site1")}
    finally:
        store.close()
    assert ends == {"marked": WalkEnd.MARKER, "older": WalkEnd.OPEN}


def _corrected(walk_id, t, pos_last, anchored="map", bias=0.0, scale=1.0):
    """A corrected track at times t (the last point at pos_last), its earlier points along +x."""
    from hybridloc.types import CorrectedTrack

    t = np.asarray(t, float)
    pos = np.column_stack([np.linspace(0.0, pos_last[0], len(t)), np.full(len(t), pos_last[1])])
    cov = np.tile(np.eye(2) * 0.25, (len(t), 1, 1))
    cov[-1] = np.diag([0.04, 0.09])
    return CorrectedTrack(walk_id, t, pos, cov, ("F1",) * len(t), ("step",) * len(t), anchored, scale, bias)


def test_agent_reanchors_on_its_walks_corrected_track_and_ignores_the_rest(tmp_path):
    """A router session (the project's server_config) puts tracks on the agent's ``track`` key while steps
    are fed by hand: the first track of this walk re-anchors the filter (the pose moves to the corrected
    position at the track's last time plus the steps since, turned by its heading bias and scaled; the
    Kalman filter does that exactly), the filter takes its bias and scale; a track of an earlier walk,
    of another walk, of an older run, a relative one and malformed bytes are counted and change nothing."""
    from hybridloc.clients.agent import Agent, PoseWriter
    from hybridloc.wire import codecs as C
    from hybridloc.wire import protocol as P
    from hybridloc.wire.messages import Track
    from hybridloc.wire.zconfig import client_config, free_port, server_config

    ep = f"tcp/127.0.0.1:{free_port()}"
    site, dev = "site1", "phoneT"
    with zenoh.open(server_config(ep)) as router, zenoh.open(client_config(ep)) as s:
        ag = Agent(s, site, dev, tmp_path / "spool", PoseWriter(None), init=(0.0, 0.0, 0.5), floor="F1")
        pub = router.declare_publisher(P.key_track(site, dev))
        assert _wait_for(lambda: pub.matching_status.matching)
        sent = 0

        def put(payload, applied=None):
            nonlocal sent
            pub.put(payload)
            sent += 1
            assert _wait_for(lambda: (ag.drain_fixes(), ag.tracks_received == sent)[1])

        def track(walk_id, run, t, pos_last, **kw):
            return C.TRACK.encode(Track(site, dev, walk_id, 1, run, _corrected(walk_id, t, pos_last, **kw)))

        put(track(6, 1, [0.0, 1.0], (5.0, 5.0)))  # before any step: an earlier walk's track
        steps = _walk(30, 0.0)  # t = 0 .. 14.5, 0.7 m along +x
        for st in steps:
            ag.add_step(st)
        before = np.array([ag.estimate.x, ag.estimate.y])
        put(b"{not json")
        put(C.TRACK.encode(Track(site, "phoneU", 7, 1, 3, _corrected(7, [0.0, 10.0], (50.0, 20.0)))))  # another device's payload on this key
        put(track(7, 1, [0.0, 10.0], (50.0, 20.0), anchored="relative"))  # a shape, not a position
        assert np.allclose([ag.estimate.x, ag.estimate.y], before) and ag.walk_id is None
        bias, scale = 0.2, 1.1
        put(track(7, 3, np.arange(21) * 0.5, (50.0, 20.0), bias=bias, scale=scale))  # this walk, up to t = 10 s
        since = [st for st in steps if st.t > 10.0]
        want = np.array([50.0, 20.0]) + sum(scale * st.length * np.array([math.cos(st.heading + bias), math.sin(st.heading + bias)]) for st in since)
        assert len(since) == 9 and ag.walk_id == 7 and ag.tracks_applied == 1
        assert np.allclose([ag.estimate.x, ag.estimate.y], want, atol=1e-9), (ag.estimate, want)
        assert ag.fusion.x[2] == bias and ag.fusion.x[3] == scale
        # the pose carries the filter's covariance: the track's at t, grown by the nine steps since
        assert np.allclose(ag.estimate.cov, ag.fusion.P[:2, :2]) and np.linalg.eigvalsh(ag.estimate.cov - np.diag([0.04, 0.09])).min() > 0
        for walk_id, run in ((8, 4), (7, 2), (7, 3)):  # another walk; an older run; the same run again
            put(track(walk_id, run, np.arange(21) * 0.5, (0.0, 0.0)))
        assert np.allclose([ag.estimate.x, ag.estimate.y], want, atol=1e-9)
        more = _walk(5, 0.0, t0=15.0)
        for st in more:
            ag.add_step(st)
        put(track(7, 5, np.arange(33) * 0.5, (60.0, 25.0), bias=0.0, scale=1.0))  # a newer run, up to t = 16 s
        want2 = np.array([60.0, 25.0]) + sum(st.length * np.array([1.0, 0.0]) for st in more if st.t > 16.0)
        assert np.allclose([ag.estimate.x, ag.estimate.y], want2, atol=1e-9)
        pub.undeclare()
        r = ag.close(wait=0.1)
    assert (r.tracks_received, r.tracks_applied, r.tracks_rejected, r.tracks_ignored) == (9, 2, 2, 5)
    assert r.track_ignored == {"before-start": 1, "relative": 1, "other-walk": 1, "old-run": 2} and r.walk_id == 7
    assert dict(ag.track_rejected) == {"malformed-json": 1, "key-mismatch": 1}
    assert [row[6] for row in r.poses].count("reanchor") == 2


def test_agent_fetches_each_new_map_version_once_into_its_particle_filter(tmp_path):
    """The server announces map versions on ``map/version``; the agent (a particle filter with the
    :func:`walk_prior_refresh` hook) fetches the map from the real server's ``map`` queryable for each
    new version, once, on its own thread: a repeated or older announcement and malformed bytes fetch
    nothing, and the filter's walk prior is the new map's."""
    from hybridloc.clients.agent import Agent, PoseWriter, walk_prior_refresh
    from hybridloc.fusion import ParticleConfig, ParticleFusion
    from hybridloc.radio.radiomap import BuildParams, build_radio_map
    from hybridloc.radio.survey import LabelledScan
    from hybridloc.server.service import Server
    from hybridloc.types import RfScan
    from hybridloc.wire import codecs as C
    from hybridloc.wire import protocol as P
    from hybridloc.wire.messages import MapVersion
    from hybridloc.wire.zconfig import client_config, free_port

    rng = np.random.default_rng(0)
    aps = {"a1": (0, 0), "a2": (30, 0), "a3": (0, 20)}
    refs = [
        LabelledScan(
            RfScan(float(i), "wifi", {k: -40 - 30 * np.log10(max(1.0, np.hypot(p[0] - q[0], p[1] - q[1]))) for k, q in aps.items()}), p, 0.5, "F1"
        )
        for i, p in enumerate(rng.uniform(0, [30, 20], (200, 2)))
    ]
    build_radio_map(refs, site="site1", params=BuildParams()).save(tmp_path / "m.npz")
    blob = (tmp_path / "m.npz").read_bytes()
    ep = f"tcp/127.0.0.1:{free_port()}"
    srv = Server(ep, str(tmp_path / "db.sqlite")).start()
    try:
        assert srv.load_map("site1", blob) == 1
        with zenoh.open(client_config(ep)) as s:
            pf = ParticleFusion(None, ParticleConfig(n_particles=100), init=(5.0, 5.0, 1.0), floor="F1")
            first_prior = pf.prior
            refresh = walk_prior_refresh(pf)
            seen = []

            def hook(payload, info):
                seen.append(info.version)
                refresh(payload, info)

            ag = Agent(s, "site1", "phoneM", tmp_path / "spool", PoseWriter(None), fusion=pf, map_refresh=hook)
            pub = srv.session.declare_publisher(P.key_map_version("site1"))
            assert _wait_for(lambda: pub.matching_status.matching)
            rejected = 0

            def announce(version):
                pub.put(C.MAP_VERSION.encode(MapVersion("site1", version, "survey", 1.7e9, 3, None)))

            def settle():  # malformed bytes after the announcements: once counted, the announcements before are handled
                nonlocal rejected
                pub.put(b"[]")
                rejected += 1
                assert _wait_for(lambda: (ag.drain_fixes(), ag.map_versions_rejected == rejected)[1])

            announce(1)
            assert _wait_for(lambda: (ag.drain_fixes(), seen == [1])[1]), seen
            assert pf.prior is not first_prior and ag.map_version == 1
            prior_1 = pf.prior
            announce(1)  # again: nothing to fetch
            settle()
            assert srv.load_map("site1", blob) == 2
            announce(2)
            assert _wait_for(lambda: (ag.drain_fixes(), seen == [1, 2])[1]), seen
            assert pf.prior is not prior_1
            announce(1)  # older than held
            settle()
            pub.undeclare()
            r = ag.close(wait=0.1)
    finally:
        srv.stop()
    assert seen == [1, 2] and r.maps_fetched == 2 and r.map_version == 2 and ag.map_fetch_failed == 0

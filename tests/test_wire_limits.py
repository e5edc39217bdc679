"""Physical limits on a batch's items (hybridloc.wire.limits): each reason refuses exactly the item that
breaks it and counts it; the batch and its other items go through; a real server stores the rest, acks
the batch and counts the refusals once; hybridloc's own clients never hit a limit on real recordings."""

import glob
import json
import math
from collections import Counter
from pathlib import Path

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings

from hybridloc.clients.uplink import Uplink
from hybridloc.server.service import Server
from hybridloc.types import RfScan, StepEvent, SurveyMark, Technology
from hybridloc.wire import codecs as C
from hybridloc.wire import limits as L
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import Batch
from hybridloc.wire.zconfig import client_config

from .helpers import wait_until as _wait
from .test_wire_codecs import wild_batches

SITE, DEV = "site1", "dev01"
T0 = 1.7e9
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def _step(t, length=0.7, **kw):
    return StepEvent(t, length, kw.pop("heading", 0.3), 0.05, kw.pop("sigma_heading", 0.1), **kw)


def _scan(t, n=3, **kw):
    return RfScan(t, Technology.WIFI, {f"ap{i}": -60.0 for i in range(n)}, **kw)


def _good():
    """Two seconds of a walk: four steps, two scans, a mark."""
    steps = [_step(T0 + 0.5 * i) for i in range(4)]
    return steps, [_scan(T0 + 0.2), _scan(T0 + 1.2)], [SurveyMark(T0 + 1.0, 10.0, 20.0, "F1")]


def _decode(steps, scans, marks) -> Batch:
    return C.BATCH.decode(C.BATCH.encode(Batch(SITE, DEV, 1, "", steps, scans, marks)))


# one bad item added to a good batch, per reason: (reason, where it goes, the item)
BAD = [
    ("step-too-long", "steps", _step(T0 + 2.0, length=50.0)),  # the load test's 50 m step
    ("step-too-fast", "steps", _step(T0 + 1.5 + 0.02)),  # 0.02 s after the previous step
    ("step-too-fast", "steps", _step(T0 + 1.5 + 0.1, length=2.0)),  # 20 m/s
    ("climb-too-high", "steps", _step(T0 + 2.0, height_change=3.5, sigma_height_change=0.1)),
    ("climb-too-high", "steps", _step(T0 + 2.0, floor_change=500)),
    ("wrong-units", "steps", _step((T0 + 2.0) * 1e3)),  # milliseconds
    ("wrong-units", "steps", _step(T0 + 2.0, sigma_heading=10.0)),  # a sigma in degrees
    ("scan-too-large", "scans", _scan(T0 + 1.5, n=10_000)),  # the load test's 10,000 transmitters
    ("wrong-units", "scans", _scan(T0 + 1.5, frequency_hz={"ap0": 2412.0})),  # MHz
    ("wrong-units", "marks", SurveyMark(T0 + 1.5, 10.0, 2.0e6, "F1")),  # millimetres
    ("time-out-of-order", "steps", _step(T0 + 0.7)),  # between the 2nd and 3rd, sent last
    ("time-out-of-order", "scans", _scan(T0 + 0.1)),
    ("batch-span", "steps", _step(T0 + 3600.0)),  # an hour after the rest
    ("batch-span", "marks", SurveyMark(T0 - 1000.0, 1.0, 2.0, "F1")),
]


@pytest.mark.parametrize("reason,where,item", BAD, ids=[f"{r}-{w}-{i}" for i, (r, w, _) in enumerate(BAD)])
def test_each_limit_refuses_its_item_and_keeps_the_rest(reason, where, item):
    steps, scans, marks = _good()
    lists = {"steps": steps, "scans": scans, "marks": marks}
    lists[where] = [*lists[where], item]
    b = _decode(lists["steps"], lists["scans"], lists["marks"])
    assert dict(b.refused) == {reason: 1}
    good = _decode(*_good())
    assert good.refused == () and C.BATCH.encode(b) == C.BATCH.encode(good)  # the same items, byte for byte


@pytest.mark.parametrize(
    "field,value,reason", [("heading_change", 7.0, "turn-too-fast"), ("heading_change", -400.0, "turn-too-fast"), ("heading", 90.0, "wrong-units")]
)
def test_angles_are_judged_as_sent(field, value, reason):
    """The records wrap a heading and a heading change into (-pi, pi]: a turn of 7 rad in one step or a
    heading in degrees would pass as a plausible angle, so the limits read the values as sent (a heading
    change in degrees is a turn no step makes either)."""
    steps, scans, marks = _good()
    msg = json.loads(C.BATCH.encode(Batch(SITE, DEV, 1, "", [*steps, _step(T0 + 2.0, heading_change=0.1, sigma_heading_change=0.05)], scans, marks)))
    msg["steps"][-1][field] = value
    b = C.BATCH.decode(json.dumps(msg).encode())
    assert dict(b.refused) == {reason: 1} and len(b.steps) == len(steps)


def test_stale_readings_are_dropped_from_their_scan():
    steps, _, marks = _good()
    ages = {"ap0": 2.0, "ap1": L.MAX_READING_AGE_S + 1.0, "ap2": -1.0}
    sc = _scan(T0 + 0.5, age_s=ages, frequency_hz={"ap0": 2.412e9, "ap1": 5.18e9})
    all_stale = _scan(T0 + 0.8, n=2, age_s={"ap0": 1e4, "ap1": 1e4})
    b = _decode(steps, [sc, all_stale], marks)
    assert dict(b.refused) == {"reading-too-old": 4}
    (kept,) = b.scans
    assert dict(kept.rssi_dbm) == {"ap0": -60.0} and dict(kept.age_s) == {"ap0": 2.0} and dict(kept.frequency_hz) == {"ap0": 2.412e9}


def test_the_largest_window_is_kept():
    """Items on either side of a 300 s window: the larger group stays, the smaller is refused."""
    early = [_step(T0 + 0.5 * i) for i in range(3)]
    late = [_step(T0 + 400.0 + 0.5 * i) for i in range(5)]
    b = _decode(early + late, [], [])
    assert dict(b.refused) == {"batch-span": 3} and [s.t for s in b.steps] == [s.t for s in late]


def test_limits_sit_above_a_walker():
    """The limits keep every step a fast walker or a runner makes: a 2 m running step every 0.25 s
    (8 m/s, 4 steps/s), a 180 deg turn on one step, two stair risers (0.36 m) per step."""
    steps = [_step(T0 + 0.25 * i, length=2.0, heading_change=math.pi if i == 3 else 0.1, sigma_heading_change=0.05) for i in range(8)]
    steps.append(_step(T0 + 2.5, height_change=0.36, sigma_height_change=0.05, floor_change=1))
    b = _decode(steps, [_scan(T0 + 1.0, n=558, age_s={"ap0": 139.0})], [])
    assert b.refused == () and len(b.steps) == 9 and len(b.scans) == 1


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
@given(wild_batches())
def test_any_batch_keeps_only_items_within_the_limits_and_counts_the_rest(b):
    back = C.BATCH.decode(C.BATCH.encode(b))
    refused = Counter(dict(back.refused))
    assert set(refused) <= set(L.REASONS)
    for s in back.steps:
        assert s.length <= L.MAX_STEP_LENGTH_M and abs(s.heading) <= L.MAX_ANGLE_RAD and abs(s.t) < L.MAX_ABS_TIME_S
        assert s.heading_change is None or abs(s.heading_change) <= L.MAX_HEADING_CHANGE_RAD
    for a, c in zip(back.steps, back.steps[1:]):
        assert c.t - a.t >= L.MIN_STEP_INTERVAL_S and c.length <= L.MAX_STEP_SPEED_M_S * (c.t - a.t)
    for lst in (back.steps, back.scans, back.marks):
        assert all(x.t <= y.t for x, y in zip(lst, lst[1:]))
    times = [x.t for lst in (back.steps, back.scans, back.marks) for x in lst]
    assert not times or max(times) - min(times) <= L.MAX_BATCH_SPAN_S
    for sc in back.scans:
        assert 0 < len(sc.rssi_dbm) <= L.MAX_SCAN_READINGS and all(0.0 <= a <= L.MAX_READING_AGE_S for a in sc.age_s.values())
    # every item sent is kept or counted (a scan all of whose readings were stale: its readings counted)
    sent = len(b.steps) + len(b.scans) + len(b.marks)
    kept = len(back.steps) + len(back.scans) + len(back.marks)
    counted = sum(n for r, n in refused.items() if r != "reading-too-old")
    assert sent - kept >= counted and (sent - kept == counted or refused["reading-too-old"] > 0)


def test_server_stores_the_rest_acks_and_counts_each_refusal_once(tmp_path):
    """The load test's three bad inputs (a 50 m step, step times out of order in one batch, a scan of
    10,000 transmitters) through a real server: the batch is acknowledged, its good items stored, each
    refusal counted once by reason (a resend of the same batch is a duplicate and counts nothing more)."""
    ep = f"unixsock-stream/{tmp_path}/srv.sock"
    srv = Server(ep, str(tmp_path / "srv.db")).start()
    try:
        with zenoh.open(client_config(ep)) as s:
            up = Uplink(s, SITE, DEV, tmp_path / "spool", resend_after=0.5)
            try:
                assert up.wait_connected()
                steps = [_step(T0 + 0.5 * i) for i in range(6)]
                steps.insert(3, _step(T0 + 0.6))  # back in time
                steps.append(_step(T0 + 3.5, length=50.0))
                up.send(steps=steps, scans=[_scan(T0 + 1.0, n=10_000), _scan(T0 + 2.0)])
                assert up.wait_acked(timeout=10) and not list((tmp_path / "spool").glob("0*.json"))
                raw = C.BATCH.encode(Batch(SITE, DEV, 1, "", steps, [_scan(T0 + 1.0, n=10_000), _scan(T0 + 2.0)], ()))
                s.put(P.key_batch(SITE, DEV), raw)  # the same batch again
                assert _wait(lambda: srv.counts["rejected:duplicate"] >= 1)
                st = srv.store.status()
            finally:
                up.close()
    finally:
        srv.stop()
    assert st["steps"] == 6 and st["scans"] == 1
    rej = st["rejections"]
    assert (rej.get("time-out-of-order"), rej.get("step-too-long"), rej.get("scan-too-large"), rej.get("duplicate")) == (1, 1, 1, 1)
    assert srv.counts["rejected:step-too-long"] == 1 and srv.counts["rejected:scan-too-large"] == 1


def _phone_steps(path):
    from hybridloc.io.msft import read_ilc_trace
    from hybridloc.pdr.phone import PhonePdr

    tr = read_ilc_trace(path)
    if tr.imu is None or len(tr.imu.t) < 2:
        return [], tr.scans
    pdr = PhonePdr(tr.imu.rate_hz)
    imu, steps = tr.imu, []
    mag = imu.mag_body
    for k in range(len(imu.t)):
        steps += pdr.update(float(imu.t[k]), imu.accel_body[k].tolist(), imu.gyro_body[k].tolist(), None if mag is None else mag[k].tolist())
    return steps, tr.scans


def _refusals_in_batches(steps, scans, period=1.0) -> Counter:
    """What the limits refuse when the walk is sent in batches of ``period`` seconds, as the agent does."""
    items = sorted([(s.t, 0, s) for s in steps] + [(s.t, 1, s) for s in scans], key=lambda x: (x[0], x[1]))
    out: Counter = Counter()
    i = 0
    while i < len(items):
        t_end = items[i][0] + period
        group = []
        while i < len(items) and items[i][0] < t_end:
            group.append(items[i])
            i += 1
        _, _, _, refused = L.screen([x for _, k, x in group if k == 0], [x for _, k, x in group if k == 1], [])
        out.update(refused)
    return out


def test_own_clients_never_hit_a_limit_on_real_recordings():
    """The phone PDR on site1 walks (one in ten of every floor) and the foot INS on every PyShoe trial:
    not one step, stride, scan or reading refused."""
    walks = sorted(glob.glob(str(SHARED / "msft-ilc" / "site1" / "*" / "path_data_files" / "*")))
    trials = sorted(glob.glob(str(SHARED / "pyshoe-vicon" / "*.mat")))
    if not walks or not trials:
        pytest.skip(f"{SHARED} holds no site1 walks or PyShoe trials (../shared is absent)")
    from hybridloc.ins.foot import run_foot_ins, strides
    from hybridloc.io.imu_files import read_pyshoe_mat

    refused: Counter = Counter()
    n_steps = n_scans = 0
    for path in walks[::10]:
        steps, scans = _phone_steps(path)
        refused.update(_refusals_in_batches(steps, scans))
        n_steps, n_scans = n_steps + len(steps), n_scans + len(scans)
    for path in trials:
        st = strides(run_foot_ins(read_pyshoe_mat(path).imu))
        refused.update(_refusals_in_batches(st, []))
        n_steps += len(st)
    assert n_steps > 1000 and n_scans > 100
    assert refused == Counter(), (dict(refused), n_steps, n_scans)


def test_reasons_are_documented():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text()
    assert [r for r in L.REASONS if f"`{r}`" not in doc] == []

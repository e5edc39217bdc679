"""The store's walks and its read API, on real SQLite files (and once through a real Zenoh ingest).

Batches are built from their wire JSON (``hybridloc.batch/1``) and decoded as the server decodes them,
so the tests hold whatever record classes the decoder returns.
"""

import datetime as dt
import json
import math
import time

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from hybridloc.server import db as m
from hybridloc.server.service import Server
from hybridloc.server.store import WALK_IDLE_GAP_S, Store
from hybridloc.types import StepEvent, SurveyMark, WalkEnd
from hybridloc.wire import protocol as P
from hybridloc.wire.codecs import BATCH, step_to_dict
from hybridloc.wire.zconfig import client_config

SITE = "site1"


def _payload(device, seq, steps=(), scans=(), marks=(), model="", site=SITE) -> bytes:
    msg = {
        "schema": P.BATCH_SCHEMA,
        "site": site,
        "device": device,
        "seq": seq,
        "device_model": model,
        "sent_at": 0.0,
        "steps": [step_to_dict(s) for s in steps],
        "scans": list(scans),
        "marks": [{"t": k.t, "x": k.x, "y": k.y, "floor": k.floor} for k in marks],
    }
    return json.dumps(msg, allow_nan=False).encode()


def _batch(device, seq, steps=(), scans=(), marks=(), model="", site=SITE):
    return BATCH.decode(_payload(device, seq, steps, scans, marks, model, site))


def _full_step(t, k=0):
    """A step with every StepEvent field away from its default (what a foot INS with a barometer sends)."""
    return StepEvent(
        t,
        0.71 + 0.01 * k,
        -3.0 + 0.37 * k,
        0.043,
        0.087,
        0.013 * (k - 3),
        0.0052,
        0.17 * (-1) ** k,
        0.021,
        (k % 3) - 1,
        "mag-disturbed" if k % 2 else "gap",
    )


def _scan(t, k=0):
    return {
        "t": t,
        "tech": "wifi",
        "rssi": {"aa:bb": -51.0 - k, "cc:dd": -77.5},
        "freq": {"aa:bb": 2.412e9, "cc:dd": 5.18e9},
        "age": {"aa:bb": 0.25 * k, "cc:dd": 1.5},
    }


def _steps(t0, n, dt_s=0.5):
    return [_full_step(t0 + i * dt_s, i) for i in range(n)]


@pytest.fixture
def store(db_url):
    st = Store(db_url)  # on SQLite and on PostgreSQL
    yield st
    st.close()


def test_every_step_scan_and_mark_field_survives_ingest_to_read_walk(store):
    steps = _steps(1000.0, 12)
    scans = [_scan(1000.2 + 1.1 * k, k) for k in range(5)]
    marks = [SurveyMark(1000.0, 3.5, -2.25, "F1"), SurveyMark(1005.75, 9.0, 1.5, "F1")]
    # steps, scans and marks in separate batches whose times interleave, as a client sends them
    acked, rejected, written = store.persist(
        [_batch("dev1", 1, steps=steps[6:], model="Pixel 4"), _batch("dev1", 2, scans=scans, marks=marks), _batch("dev1", 3, steps=steps[:6])]
    )
    assert acked == {"dev1": 3} and not rejected and written == 3
    [info] = store.walks(SITE)
    w = store.read_walk(info.walk_id)
    assert w.steps == tuple(steps)  # StepEvent equality: every field, exactly
    assert [(s.t, s.technology.value, dict(s.rssi_dbm), dict(s.frequency_hz), dict(s.age_s)) for s in w.scans] == [
        (s["t"], s["tech"], s["rssi"], s["freq"], s["age"]) for s in scans
    ]
    assert all(s.device_model == "Pixel 4" for s in w.scans)
    assert w.marks == tuple(marks)
    assert (w.site, w.device, w.walk_id, w.device_model, w.floors, w.end) == (SITE, "dev1", info.walk_id, "Pixel 4", ("F1",), WalkEnd.OPEN)
    assert (w.t_start, w.t_end) == (1000.0, max(steps[-1].t, scans[-1]["t"], marks[-1].t))
    assert (info.n_batches, info.n_steps, info.n_scans, info.n_marks) == (3, 12, 5, 2)


def test_two_bursts_separated_by_more_than_the_idle_gap_are_two_walks(store):
    first = _steps(0.0, 10)  # 0 .. 4.5 s
    t_gap = first[-1].t + WALK_IDLE_GAP_S  # exactly the gap: still the same walk (the rule is "more than")
    second = _steps(t_gap + WALK_IDLE_GAP_S + 1.0, 4)
    store.persist([_batch("dev1", 1, steps=first), _batch("dev1", 2, scans=[_scan(t_gap)]), _batch("dev1", 3, steps=second)])
    store.persist([_batch("dev2", 1, steps=_steps(2.0, 3))])
    walks = store.walks(SITE, device="dev1")
    assert [(w.t_start, w.t_end, w.end, w.n_batches) for w in walks] == [(0.0, t_gap, WalkEnd.IDLE, 2), (second[0].t, second[-1].t, WalkEnd.OPEN, 1)]
    assert [w.walk_id for w in store.walks(SITE, device="dev1", ended_only=True)] == [walks[0].walk_id]
    assert [w.walk_id for w in store.walks(SITE, since=t_gap + 1.0)] == [walks[1].walk_id]
    assert [w.device for w in store.walks(SITE)] == ["dev1", "dev2", "dev1"]  # by start time
    assert store.walks("elsewhere") == []
    assert store.read_walk(walks[1].walk_id).steps == tuple(second)
    assert len(store.read_walk(walks[0].walk_id).scans) == 1


def test_a_device_clock_going_back_by_more_than_the_gap_opens_a_walk(store):
    store.persist([_batch("dev1", 1, steps=_steps(5000.0, 4)), _batch("dev1", 2, steps=_steps(5000.0 - 2 * WALK_IDLE_GAP_S, 4))])
    assert [w.end for w in store.walks(SITE)] == [WalkEnd.OPEN, WalkEnd.IDLE]  # by start time: the later-sent walk starts earlier


def test_a_resent_batch_is_never_doubled(store):
    b1, b2 = _batch("dev1", 1, steps=_steps(0.0, 5)), _batch("dev1", 2, steps=_steps(2.5, 5), scans=[_scan(3.0)])
    store.persist([b1, b2])
    acked, rejected, written = store.persist([b2, b1, b2])
    assert acked == {"dev1": 2} and rejected == {("dev1", "duplicate"): 3} and written == 0
    [info] = store.walks(SITE)
    w = store.read_walk(info.walk_id)
    assert (info.n_batches, len(w.steps), len(w.scans)) == (2, 10, 1)


def test_out_of_order_batches_wait_for_their_turn(store):
    steps = _steps(10.0, 9)
    b1, b2, b3 = (_batch("dev1", i + 1, steps=steps[3 * i : 3 * i + 3]) for i in range(3))
    acked, rejected, _ = store.persist([b1, b3])
    assert acked == {"dev1": 1} and rejected == {("dev1", "out-of-order"): 1}
    store.persist([b2, b3])
    [info] = store.walks(SITE)
    assert store.read_walk(info.walk_id).steps == tuple(steps) and info.n_batches == 3


def test_the_end_of_walk_marker_closes_the_walk(store):
    store.persist([_batch("dev1", 1, steps=_steps(0.0, 4)), _batch("dev1", 2, steps=_steps(2.0, 4))], end_of_walk={("dev1", 2)})
    store.persist([_batch("dev1", 3, steps=_steps(5.0, 4))])  # seconds later, yet a new walk
    store.persist([_batch("dev1", 4)])  # a batch of nothing joins the open walk
    walks = store.walks(SITE)
    assert [(w.end, w.n_batches, w.t_start) for w in walks] == [(WalkEnd.MARKER, 2, 0.0), (WalkEnd.OPEN, 2, 5.0)]
    store.persist([_batch("dev1", 5)], end_of_walk={("dev1", 5)})
    store.persist([_batch("dev1", 6)])  # nothing, and no open walk: it belongs to none
    assert [w.end for w in store.walks(SITE)] == [WalkEnd.MARKER, WalkEnd.MARKER]
    assert store.status()["batches"] == 6 and sum(w.n_batches for w in store.walks(SITE)) == 5


def test_walk_floors_from_marks_and_fixes_in_order_of_first_appearance(store):
    from hybridloc.types import AbsoluteFix

    marks = [SurveyMark(1.0, 0.0, 0.0, "F1"), SurveyMark(2.0, 1.0, 0.0, "F1"), SurveyMark(9.0, 1.0, 1.0, "F2")]
    store.persist([_batch("dev1", 1, steps=_steps(0.0, 20), marks=marks), _batch("dev2", 1, steps=_steps(0.0, 4))])
    store.add_fixes(
        [
            ("dev1", AbsoluteFix(5.0, [1.0, 2.0], [[4.0, 0.0], [0.0, 4.0]], "wifi", floor="B1")),
            ("dev2", AbsoluteFix(1.0, [1.0, 2.0], [[4.0, 0.0], [0.0, 4.0]], "wifi", floor="F1")),
            ("dev2", AbsoluteFix(99.0, [1.0, 2.0], [[4.0, 0.0], [0.0, 4.0]], "wifi", floor="F7")),
        ]
    )  # after every walk: none
    by_dev = {w.device: w for w in store.walks(SITE)}
    assert by_dev["dev1"].floors == ("F1", "B1", "F2") and by_dev["dev2"].floors == ("F1",)
    assert [w.device for w in store.walks(SITE, floor="F1")] == ["dev1", "dev2"]
    assert [w.device for w in store.walks(SITE, floor="F2")] == ["dev1"]
    assert store.walks(SITE, floor="F7") == []
    assert store.read_walk(by_dev["dev1"].walk_id).floors == ("F1", "B1", "F2")
    # one group naming floors the walk has, earlier, twice: each floor's first time is its earliest
    fix = lambda t, f: ("dev1", AbsoluteFix(t, [1.0, 2.0], [[4.0, 0.0], [0.0, 4.0]], "wifi", floor=f))  # noqa: E731
    store.add_fixes([fix(4.0, "B1"), fix(3.5, "F2"), fix(3.0, "F2"), fix(12.0, "F1")])
    assert store.read_walk(by_dev["dev1"].walk_id).floors == ("F1", "F2", "B1")


def test_idle_walks_close_on_the_server_clock(store):
    store.persist([_batch("dev1", 1, steps=_steps(0.0, 4))])
    assert store.close_idle_walks() == 0
    assert store.close_idle_walks(now=m.utcnow() + dt.timedelta(seconds=WALK_IDLE_GAP_S + 1.0)) == 1
    assert [w.end for w in store.walks(SITE)] == [WalkEnd.IDLE]
    with pytest.raises(KeyError):
        store.read_walk(12345)


def test_read_walk_selects_records_through_indexes(store):
    if store.engine.dialect.name != "sqlite":
        pytest.skip("EXPLAIN QUERY PLAN is SQLite's")
    from sqlalchemy import select

    for model, index in ((m.Step, "ix_step_batch_id"), (m.Scan, "ix_scan_device_t"), (m.SurveyMark, "ix_survey_mark_device_t")):
        q = (
            select(model)
            .join(m.Batch, m.Batch.id == model.batch_id)
            .where(model.device_id == "d", model.t >= 0.0, model.t <= 1.0, m.Batch.walk_id == 1)
            .order_by(model.t, model.id)
        )
        with store.engine.connect() as c:
            plan = " | ".join(
                r[-1] for r in c.exec_driver_sql("EXPLAIN QUERY PLAN " + str(q.compile(store.engine, compile_kwargs={"literal_binds": True})))
            )
        # steps come through the walk's batches (migration 0004), then sorted by time; the others in index order
        assert f"USING INDEX {index}" in plan and ("TEMP B-TREE" not in plan or model is m.Step), plan
        if model is m.Step:
            assert "ix_batch_walk_id" in plan and "SCAN step" not in plan, plan


def test_walk_read_after_a_real_zenoh_ingest(tmp_path, db_url):
    ep = f"unixsock-stream/{tmp_path}/srv.sock"
    steps = _steps(1.7e9, 30)
    scans = [_scan(1.7e9 + 2.0 * k, k) for k in range(6)]
    srv = Server(ep, db_url).start()
    try:
        with zenoh.open(client_config(ep)) as s:
            pub = s.declare_publisher(P.key_batch(SITE, "devz"), congestion_control=zenoh.CongestionControl.BLOCK)
            pub.put(_payload("devz", 1, steps=steps[:15], scans=scans[:3], model="SM-G960F"))
            pub.put(_payload("devz", 2, steps=steps[15:], scans=scans[3:]))
            pub.put(_payload("devz", 1, steps=steps[:15], scans=scans[:3], model="SM-G960F"))  # resent
            t_end = time.monotonic() + 10.0
            while srv.counts["batches-persisted"] < 2 or srv.counts["rejected:duplicate"] < 1:
                assert time.monotonic() < t_end, dict(srv.counts)
                time.sleep(0.02)
            pub.undeclare()
        [info] = srv.store.walks(SITE, device="devz")
        w = srv.store.read_walk(info.walk_id)
    finally:
        srv.stop()
    assert w.steps == tuple(steps)
    assert [(s.t, dict(s.rssi_dbm), dict(s.frequency_hz), dict(s.age_s), s.device_model) for s in w.scans] == [
        (s["t"], s["rssi"], s["freq"], s["age"], "SM-G960F") for s in scans
    ]
    assert w.device_model == "SM-G960F" and w.end == WalkEnd.OPEN and math.isclose(w.duration, steps[-1].t - steps[0].t)


def test_the_driver_level_step_insert_names_every_step_column():
    """Store._insert_records writes steps through the driver with its own column list: it must be the
    step table's columns (all but the id), in order, or a migration adding one would go unwritten."""
    from hybridloc.server import db as m
    from hybridloc.server.store import _STEP_COLUMNS, _step_insert_sql

    assert list(_STEP_COLUMNS) == [c.name for c in m.Step.__table__.columns if c.name != "id"]
    assert _step_insert_sql("qmark").count("?") == len(_STEP_COLUMNS) and _step_insert_sql("pyformat").count("%s") == len(_STEP_COLUMNS)


@settings(max_examples=500, deadline=None)
@given(
    st.dictionaries(
        st.sampled_from(["rssi", "freq", "age"]),
        st.dictionaries(
            st.text(min_size=1, max_size=64), st.one_of(st.floats(allow_nan=False, allow_infinity=False), st.integers(-(2**53), 2**53)), max_size=30
        ),
    )
)
def test_readings_json_reads_back_as_json_dumps_does(readings):
    """The scan table's readings text (msgspec) reads back to what ``json.dumps``'s text (SQLAlchemy's
    JSON type, the text stored before) reads back to, float for float."""
    from server.store import readings_json

    got, was = json.loads(readings_json(readings)), json.loads(json.dumps(readings))
    assert repr(got) == repr(was) == repr(readings)


def test_readings_msgspec_cannot_write_are_written_as_before():
    """NaN (msgspec: null) and a lone surrogate (msgspec: refused) are written by json.dumps, as before."""
    from server.store import readings_json

    for readings in ({"rssi": {"a": -50.0}, "age": {"a": math.nan}}, {"rssi": {"\ud800": -50.0}}):
        assert readings_json(readings) == json.dumps(readings)
    assert readings_json({"rssi": {"nullable": -50.0}}) == json.dumps({"rssi": {"nullable": -50.0}})

"""Migrations on a filled database: a real SQLite file and a real PostgreSQL database (the ``db_url``
fixture runs each test on both) filled through the real 0001 schema, upgraded to 0002 (walks),
downgraded to 0001 with every 0001 row intact, and upgraded again (real Alembic); every revision,
the SLAM one included."""

import datetime as dt
import json

import numpy as np
from sqlalchemy import MetaData, insert, inspect, select

from hybridloc.server import db as m
from hybridloc.server.migrate import current_revision, downgrade, upgrade
from hybridloc.server.store import WALK_IDLE_GAP_S, Store
from hybridloc.types import StepEvent, WalkEnd
from hybridloc.wire import protocol as P
from hybridloc.wire.codecs import BATCH, step_to_dict

T0 = 1.6e9
NOW = dt.datetime(2024, 5, 1, 12, 0, tzinfo=dt.UTC)
HEAD = "0004_step_batch_index"
STEP_0001 = ["id", "batch_id", "device_id", "t", "length", "heading", "sigma_length", "sigma_heading", "heading_change", "floor_change"]


def _fill_0001(eng) -> dict[str, list[tuple]]:
    """Rows written through the tables 0001 created (reflected: today's models have more columns)."""
    md = MetaData()
    md.reflect(eng)
    t = md.tables

    def step(bid, dev, tt):
        return {
            "batch_id": bid,
            "device_id": dev,
            "t": tt,
            "length": 0.7,
            "heading": 0.3,
            "sigma_length": 0.05,
            "sigma_heading": 0.1,
            "heading_change": 0.01,
            "floor_change": 0,
        }

    def scan(bid, dev, tt):
        return {
            "batch_id": bid,
            "device_id": dev,
            "t": tt,
            "technology": "wifi",
            "readings": {"rssi": {"aa": -60.0}, "freq": {"aa": 2.412e9}, "age": {"aa": 0.5}},
        }

    with eng.begin() as c:
        c.execute(insert(t["site"]), [{"id": "s1", "name": "s1"}])
        c.execute(
            insert(t["device"]),
            [
                {"id": "dA", "site_id": "s1", "model": "Pixel", "last_seq": 5},
                {"id": "dB", "site_id": "s1", "model": "", "last_seq": 1},
                {"id": "dC", "site_id": "s1", "model": "", "last_seq": 0},
            ],
        )
        # (id, device, seq, steps, scans, marks), the counts matching the rows written below
        batches = [
            (1, "dA", 1, 11, 0, 0),
            (2, "dA", 2, 0, 8, 0),
            (3, "dA", 3, 0, 0, 0),
            (4, "dA", 4, 11, 0, 2),
            (5, "dA", 5, 0, 2, 0),
            (6, "dB", 1, 1, 0, 0),
        ]
        c.execute(
            insert(t["batch"]),
            [{"id": i, "device_id": d, "seq": q, "received_at": NOW, "n_steps": ns, "n_scans": nc, "n_marks": nm} for i, d, q, ns, nc, nm in batches],
        )
        if eng.dialect.name == "postgresql":  # ids given by hand: move the sequence past them, as the app's inserts would have
            c.exec_driver_sql("SELECT setval(pg_get_serial_sequence('batch', 'id'), (SELECT max(id) FROM batch))")
        # dA: a walk 100-112 s (steps, then its scans, then an empty batch), silence, a walk 500-512 s
        c.execute(
            insert(t["step"]),
            [step(1, "dA", T0 + 100.0 + k) for k in range(11)] + [step(4, "dA", T0 + 500.0 + k) for k in range(11)] + [step(6, "dB", T0 + 7.0)],
        )
        c.execute(insert(t["scan"]), [scan(2, "dA", T0 + 105.0 + k) for k in range(8)] + [scan(5, "dA", T0 + 511.0), scan(5, "dA", T0 + 512.0)])
        c.execute(
            insert(t["survey_mark"]),
            [
                {"batch_id": 4, "device_id": "dA", "t": T0 + 502.0, "x": 1.0, "y": 2.0, "floor": "F1"},
                {"batch_id": 4, "device_id": "dA", "t": T0 + 508.0, "x": 3.0, "y": 2.0, "floor": "F2"},
            ],
        )
        c.execute(
            insert(t["fix"]),
            [
                {"device_id": "dA", "t": T0 + 505.0, "x": 0.0, "y": 0.0, "floor": "B1", "cov": [[1, 0], [0, 1]], "source": "wifi"},
                {"device_id": "dA", "t": T0 + 50.0, "x": 0.0, "y": 0.0, "floor": "F9", "cov": [[1, 0], [0, 1]], "source": "wifi"},
            ],
        )
    return _dump_0001(eng)


def _dump_0001(eng) -> dict[str, list[tuple]]:
    """Every row of the 0001 tables, 0001's columns only, in primary key order."""
    md = MetaData()
    md.reflect(eng)
    cols_0001 = {"step": STEP_0001, "batch": ["id", "device_id", "seq", "received_at", "n_steps", "n_scans", "n_marks"]}
    out = {}
    with eng.connect() as c:
        for name in ("site", "device", "batch", "step", "scan", "survey_mark", "fix"):
            tab = md.tables[name]
            cols = [tab.c[k] for k in cols_0001.get(name, tab.c.keys())]
            out[name] = [tuple(r) for r in c.execute(select(*cols).order_by(*tab.primary_key.columns))]
    return out


def _walks(st: Store):
    return [(w.device, w.t_start, w.t_end, w.end, w.floors, w.device_model, w.n_batches, w.n_steps, w.n_scans, w.n_marks) for w in st.walks("s1")]


def test_upgrade_downgrade_upgrade_on_a_filled_database(db_url):
    assert WALK_IDLE_GAP_S < 500.0 - 112.0  # the fill's two walks of dA are split by the gap
    db = db_url
    eng = m.make_engine(db)
    upgrade(eng, "0001_initial")
    assert current_revision(eng) == "0001_initial"
    before = _fill_0001(eng)

    upgrade(eng, "0002_walks")
    assert current_revision(eng) == "0002_walks"
    st = Store(db, migrate=False)
    walks = _walks(st)
    assert walks == [
        ("dB", T0 + 7.0, T0 + 7.0, WalkEnd.OPEN, (), "", 1, 1, 0, 0),
        ("dA", T0 + 100.0, T0 + 112.0, WalkEnd.IDLE, (), "Pixel", 3, 11, 8, 0),  # the empty batch 3 joined it
        ("dA", T0 + 500.0, T0 + 512.0, WalkEnd.OPEN, ("F1", "B1", "F2"), "Pixel", 2, 11, 2, 2),  # the fix at 505 s named B1; the one at 50 s no walk
    ]
    ids = {(w.device, w.t_start): w.walk_id for w in st.walks("s1")}
    first = st.read_walk(ids[("dA", T0 + 100.0)])
    assert [s.t for s in first.steps] == [T0 + 100.0 + k for k in range(11)] and len(first.scans) == 8 and first.marks == ()
    # rows stored before 0002 read back with the new fields at their defaults
    assert first.steps[0] == StepEvent(T0 + 100.0, 0.7, 0.3, 0.05, 0.1, 0.01, None, 0.0, 0.0, 0, "")
    assert dict(first.scans[0].age_s) == {"aa": 0.5} and dict(first.scans[0].frequency_hz) == {"aa": 2.412e9}
    second = st.read_walk(ids[("dA", T0 + 500.0)])
    assert len(second.steps) == 11 and len(second.scans) == 2 and [k.floor for k in second.marks] == ["F1", "F2"]
    with st.engine.connect() as c:
        assert [r[0] for r in c.execute(select(m.Batch.walk_id).order_by(m.Batch.id))] == [ids[("dA", T0 + 100.0)]] * 3 + [
            ids[("dA", T0 + 500.0)]
        ] * 2 + [ids[("dB", T0 + 7.0)]]
    st.close()

    downgrade(eng, "0001_initial")
    assert current_revision(eng) == "0001_initial"
    insp = inspect(eng)
    assert not {"walk", "walk_floor"} & set(insp.get_table_names())
    assert "walk_id" not in {c["name"] for c in insp.get_columns("batch")}
    assert [c["name"] for c in insp.get_columns("step")] == STEP_0001
    assert "ix_survey_mark_device_t" not in {i["name"] for i in insp.get_indexes("survey_mark")}
    assert _dump_0001(eng) == before  # every 0001 row, unchanged

    upgrade(eng)
    st = Store(db)
    assert _walks(st) == walks  # the same walks again
    st.close()
    eng.dispose()


def test_a_migrated_open_walk_takes_the_next_batch(db_url):
    db = db_url
    eng = m.make_engine(db)
    upgrade(eng, "0001_initial")
    _fill_0001(eng)
    eng.dispose()
    st = Store(db)  # upgrades to head
    msg = {
        "schema": P.BATCH_SCHEMA,
        "site": "s1",
        "device": "dA",
        "seq": 6,
        "device_model": "",
        "sent_at": 0.0,
        "steps": [step_to_dict(StepEvent(T0 + 515.0, 0.7, 0.0, 0.05, 0.1))],
    }
    assert st.persist([BATCH.decode(json.dumps(msg).encode())])[0] == {"dA": 6}
    last = st.walks("s1", device="dA")[-1]
    assert (last.t_start, last.t_end, last.n_batches, last.n_steps, last.end) == (T0 + 500.0, T0 + 515.0, 3, 12, WalkEnd.OPEN)
    st.close()


def test_downgrade_to_base_and_back_on_an_empty_database(db_url):
    eng = m.make_engine(db_url)
    upgrade(eng)
    downgrade(eng, "base")
    assert current_revision(eng) is None and inspect(eng).get_table_names() == ["alembic_version"]
    upgrade(eng)
    assert current_revision(eng) == HEAD
    eng.dispose()


def test_0003_slam_up_down_up_keeps_maps(db_url):
    """0003 (crowd SLAM tables, map provenance) on a filled 0002 database: a map stored before reads as an
    "import"; SLAM rows written at head; downgrade to 0002 drops them and keeps every 0002 row."""
    from hybridloc.server.slam_store import CORRECTED, WalkResult
    from hybridloc.types import CorrectedTrack

    db = db_url
    eng = m.make_engine(db)
    upgrade(eng, "0001_initial")
    _fill_0001(eng)
    upgrade(eng, "0002_walks")
    md = MetaData()
    md.reflect(eng)
    with eng.begin() as c:
        c.execute(insert(md.tables["radio_map"]), [{"site_id": "s1", "version": 1, "created_at": NOW, "n_scans": 3, "data": b"npz"}])
    before = _dump_0001(eng)
    upgrade(eng)
    assert current_revision(eng) == HEAD
    st = Store(db)
    with st.engine.connect() as c:
        assert [tuple(r) for r in c.execute(select(m.RadioMapVersion.version, m.RadioMapVersion.source, m.RadioMapVersion.run_id))] == [
            (1, "import", None)
        ]
    wid = st.walks("s1")[0].walk_id
    tr = CorrectedTrack(wid, [T0 + 7.0], [[1.0, 2.0]], [np.eye(2)], ("F1",), ("step",), "map", 1.0, 0.0)
    run = st.slam.begin_run("s1")
    st.slam.write_floor(run, "F1", [WalkResult(wid, CORRECTED, tr)])
    assert st.slam.finish_run(run, b"npz2", provenance={"walks": [wid]}) == 2
    st.close()
    downgrade(eng, "0002_walks")
    insp = inspect(eng)
    assert not {"slam_run", "slam_floor_done", "walk_slam", "track_point", "loop_closure"} & set(insp.get_table_names())
    assert "source" not in {c["name"] for c in insp.get_columns("radio_map")}
    assert _dump_0001(eng) == before
    upgrade(eng)
    assert current_revision(eng) == HEAD
    eng.dispose()


def test_0004_step_batch_index_up_down_up(db_url):
    """0004 (steps indexed by batch, not by device and time) on a filled 0003 database: the indexes change,
    no row does, every walk reads back the same; downgrade to 0003 restores ix_step_device_t."""
    db = db_url
    eng = m.make_engine(db)
    upgrade(eng, "0001_initial")
    _fill_0001(eng)
    upgrade(eng, "0003_slam")

    def read(st: Store) -> list:
        out = []
        for w in st.walks("s1"):
            wk = st.read_walk(w.walk_id)
            scans = [(x.t, x.technology, dict(x.rssi_dbm), dict(x.frequency_hz), dict(x.age_s)) for x in wk.scans]
            out.append((w, wk.steps, scans, wk.marks, wk.floors, wk.end))
        return out

    st = Store(db, migrate=False)
    walks = read(st)
    st.close()
    assert sum(len(w[1]) for w in walks) == 23
    before = _dump_0001(eng)

    def step_indexes() -> set[str]:
        return {i["name"] for i in inspect(eng).get_indexes("step")}

    assert "ix_step_device_t" in step_indexes() and "ix_step_batch_id" not in step_indexes()
    upgrade(eng, "0004_step_batch_index")
    assert current_revision(eng) == HEAD
    assert "ix_step_batch_id" in step_indexes() and "ix_step_device_t" not in step_indexes()
    assert _dump_0001(eng) == before
    st = Store(db)
    assert read(st) == walks
    st.close()
    downgrade(eng, "0003_slam")
    assert "ix_step_device_t" in step_indexes() and "ix_step_batch_id" not in step_indexes()
    assert _dump_0001(eng) == before
    upgrade(eng)
    assert current_revision(eng) == HEAD and "ix_step_batch_id" in step_indexes()
    eng.dispose()

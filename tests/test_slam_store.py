"""The crowd SLAM's storage on a real SQLite file with the real migrations: incremental walks, a batch run
written floor by floor, killed midway and resumed, completed atomically (readers see the old tracks until
then), the loop audit and the per-site summary."""

import numpy as np
import pytest

from hybridloc.server.slam_store import CORRECTED, QUARANTINED, RELATIVE, WalkResult
from hybridloc.server.store import Store
from hybridloc.slam.pipeline import LoopRecord
from hybridloc.types import CorrectedTrack, RfScan, StepEvent, SurveyMark, Technology
from hybridloc.wire.messages import Batch

T0 = 1.6e9


def _fill(st: Store, n_walks: int = 3, marks_on: int = 0) -> list[int]:
    """n_walks ended walks of site s1 (one device each), 10 steps and 2 scans; walk ``marks_on`` has marks."""
    bs = []
    for k in range(n_walks):
        t = T0 + 1000.0 * k
        steps = [StepEvent(t + i, 0.7, 0.0, 0.05, 0.1) for i in range(10)]
        scans = [RfScan(t + 2.0, Technology.WIFI, {"aa": -60.0}), RfScan(t + 7.0, Technology.WIFI, {"aa": -70.0})]
        marks = [SurveyMark(t, 0.0, 0.0, "F1"), SurveyMark(t + 9, 6.3, 0.0, "F1")] if k == marks_on else [SurveyMark(t, 0.0, 0.0, "F1")][:0]
        bs.append(Batch("s1", f"d{k}", 1, "", steps, scans, marks, end_of_walk=True))
    st.persist(bs)
    ws = st.walks("s1")
    # the crowd walks name their floor through a fix (what the server does when it answers a scan)
    from hybridloc.types import AbsoluteFix

    st.add_fixes([(w.device, AbsoluteFix(w.t_start + 2.0, np.zeros(2), np.eye(2), "wifi", "F1")) for w in ws])
    return [w.walk_id for w in st.walks("s1")]


def _track(wid: int, t0: float, dx: float = 0.0, anchored: str = "loops") -> CorrectedTrack:
    t = np.concatenate([t0 + np.arange(10.0), [t0 + 2.0, t0 + 7.0]])
    order = np.argsort(t, kind="stable")
    kinds = np.array(["step"] * 10 + ["scan"] * 2)[order]
    pos = np.column_stack([0.7 * (t[order] - t0) + dx, np.zeros(12)])
    return CorrectedTrack(wid, t[order], pos, np.tile(np.eye(2) * 4.0, (12, 1, 1)), ("F1",) * 12, tuple(kinds), anchored, 1.02, 0.05)


def _loop(a: int, b: int, accepted: bool) -> LoopRecord:
    return LoopRecord(str(a), T0, str(b), T0 + 1000, 0.8, 0.9 if accepted else 0.1, accepted, "F1", 0.7, "" if accepted else "robust-weight")


@pytest.fixture
def st(db_url):
    s = Store(db_url)  # on SQLite and on PostgreSQL
    yield s
    s.close()


def test_walks_added_one_by_one(st):
    w = _fill(st)
    assert st.slam.pending_walks("s1") == w
    st.slam.save_walk("s1", WalkResult(w[0], CORRECTED, _track(w[0], T0, anchored="marks")), [])
    st.slam.save_walk("s1", WalkResult(w[1], CORRECTED, _track(w[1], T0 + 1000)), [_loop(w[1], w[0], True), _loop(w[1], w[0], False)])
    st.slam.save_walk("s1", WalkResult(w[2], QUARANTINED, _track(w[2], T0 + 2000), "off-walkable: 60 %"), [])
    assert st.slam.pending_walks("s1") == []
    tr = st.slam.tracks("s1")
    assert set(tr) == set(w)
    got = tr[w[1]]
    want = _track(w[1], T0 + 1000)
    np.testing.assert_array_equal(got.t, want.t)
    np.testing.assert_array_equal(got.pos_enu, want.pos_enu)
    np.testing.assert_array_equal(got.cov, want.cov)
    assert got.kind == want.kind and got.anchored == "loops" and got.scale == 1.02 and got.heading_bias == 0.05
    sm = st.slam.summary("s1")
    assert (sm["walks_corrected"], sm["walks_quarantined"], sm["walks_pending"]) == (2, 1, 0)
    assert (sm["loops_accepted"], sm["loops_rejected"]) == (1, 1)
    # coverage: the scans of the walks without marks (w1, w2) that have an absolute track: w1 only
    assert sm["coverage"] == pytest.approx(0.5)
    # a batch run does not take the quarantined walk
    assert st.slam.solvable_walks("s1") == w[:2]


def test_batch_run_is_atomic_resumable_and_replaces_tracks(st):
    w = _fill(st)
    for wid, k in zip(w, range(3)):
        st.slam.save_walk("s1", WalkResult(wid, CORRECTED, _track(wid, T0 + 1000 * k)), [])
    old = st.slam.tracks("s1")
    run = st.slam.begin_run("s1", ["F1", "F2"])
    st.slam.write_floor(
        run, "F1", [WalkResult(wid, CORRECTED, _track(wid, T0 + 1000 * k, dx=5.0)) for wid, k in zip(w[:2], range(2))], [_loop(w[0], w[1], True)]
    )
    # killed here: readers still see the old tracks, the run is unfinished with F1 done
    mid = st.slam.tracks("s1")
    for wid in w:
        np.testing.assert_array_equal(mid[wid].pos_enu, old[wid].pos_enu)
    assert st.slam.loops("s1") == []
    un = st.slam.unfinished_runs("s1")
    assert [r.run_id for r in un] == [run] and un[0].floors_done == ("F1",)
    with pytest.raises(ValueError):
        st.slam.write_floor(run, "F1", [])
    st.slam.write_floor(run, "F2", [WalkResult(w[2], RELATIVE, _track(w[2], T0 + 2000, dx=5.0, anchored="relative"))])
    v = st.slam.finish_run(run, b"mapbytes", n_scans=4, provenance={"walks": w, "survey_walks": [w[0]]})
    assert v == 1 and st.load_map("s1") == (1, b"mapbytes")
    new = st.slam.tracks("s1")
    for wid in w:
        np.testing.assert_allclose(new[wid].pos_enu, old[wid].pos_enu + [5.0, 0.0])
    assert st.slam.walk_states("s1")[w[2]].status == RELATIVE
    assert st.slam.unfinished_runs("s1") == []
    assert len(st.slam.loops("s1")) == 1
    # the superseded points are gone: one point set per walk
    from sqlalchemy import func, select
    from sqlalchemy.orm import Session

    from hybridloc.server import db as m

    with Session(st.engine) as s:
        assert s.execute(select(func.count()).select_from(m.TrackPoint)).scalar_one() == 3 * 12
        rm = s.execute(select(m.RadioMapVersion)).scalar_one()
        assert rm.source == "slam" and rm.run_id == run and rm.provenance["survey_walks"] == [w[0]]
    with pytest.raises(ValueError):
        st.slam.finish_run(run)
    # the summary's counts (counted in the database) are those of the audit's rows: the batch run's
    # loop, then a walk added after it (its loops count; the walks' loops before the batch do not)
    assert st.slam.loop_counts("s1") == (1, 0)
    st.slam.save_walk("s1", WalkResult(w[1], CORRECTED, _track(w[1], T0 + 1000)), [_loop(w[1], w[0], False)])
    rows = st.slam.loops("s1")
    assert st.slam.loop_counts("s1") == (sum(r.accepted for r in rows), sum(not r.accepted for r in rows)) == (1, 1)
    assert st.slam.processed_walks("s1") == set(w)


def test_failed_run_leaves_nothing(st):
    w = _fill(st, 1)
    run = st.slam.begin_run("s1")
    st.slam.write_floor(run, "F1", [WalkResult(w[0], CORRECTED, _track(w[0], T0))])
    st.slam.fail_run(run, "solver diverged")
    assert st.slam.tracks("s1") == {} and st.slam.unfinished_runs("s1") == []
    assert st.slam.runs("s1")[0].status == "failed" and st.slam.runs("s1")[0].error == "solver diverged"
    with pytest.raises(ValueError):
        WalkResult(w[0], "fine")


def test_slam_show_from_the_database(st, tmp_path, capsys):
    """``slam show --db URL --site S``: the stored tracks, their dead reckoning and the loop audit drawn
    over the plan stored by ``floorplan import``; bad input one line, exit 2."""
    from hybridloc.cli import main
    from hybridloc.samples import ILC_SITE1_F1

    w = _fill(st)
    st.slam.save_walk("s1", WalkResult(w[0], CORRECTED, _track(w[0], T0, anchored="marks")), [])
    st.slam.save_walk("s1", WalkResult(w[1], CORRECTED, _track(w[1], T0 + 1000)), [_loop(w[1], w[0], True)])
    db = st.engine.url.render_as_string(hide_password=False)  # a sqlite:/// or postgresql:// URL
    assert main(["floorplan", "import", str(ILC_SITE1_F1), "--site", "s1", "--db", db]) == 0
    png = tmp_path / "show.png"
    assert main(["slam", "show", "--db", db, "--site", "s1", "--floor", "F1", "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000
    assert "2 walks, 1 accepted and 0 rejected loops" in capsys.readouterr().out
    assert main(["slam", "show", "--db", db, "--site", "s1", "--floor", "F9", "--out", str(png)]) == 2
    assert main(["slam", "show", "--db", db, "--site", "nowhere", "--floor", "F1", "--out", str(png)]) == 2
    assert main(["slam", "show", "--db", db, "--floor", "F1", "--out", str(png)]) == 2


def test_map_versions_from_concurrent_writers_never_collide(db_url):
    """A batch run of the SLAM worker and a ``map rebuild`` both take "newest version + 1": on one
    database (SQLite's write lock, PostgreSQL's row lock of db.lock_site) from two connections at once,
    every map is stored, under distinct versions 1..n."""
    import threading

    stores = [Store(db_url) for _ in range(2)]
    errors: list[BaseException] = []
    got: list[int] = []
    lock = threading.Lock()
    barrier = threading.Barrier(2)

    def writer(st: Store, k: int) -> None:
        try:
            barrier.wait()
            for i in range(15):
                if k == 0:
                    v = st.save_map("s1", b"survey %d" % i, 1, source="survey")
                else:
                    run = st.slam.begin_run("s1")
                    v = st.slam.finish_run(run, map_data=b"slam %d" % i, n_scans=1)
                with lock:
                    got.append(int(v))
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(st, k)) for k, st in enumerate(stores)]
    for th in threads:
        th.start()
    for th in threads:
        th.join(120)
    for st in stores:
        st.close()
    assert not errors, errors
    assert sorted(got) == list(range(1, 31))


def test_one_map_version_is_read_by_its_number(st):
    _fill(st, 1)
    v1 = st.save_map("s1", b"survey", 1, source="survey")
    v2 = st.save_map("s1", b"slam", 2, source="slam")
    assert (v1, v2) == (1, 2)
    assert st.map_version("s1", 1) == b"survey" and st.map_version("s1", 2) == b"slam"
    assert st.map_version("s1", 3) is None and st.map_version("other-site", 1) is None


def test_a_walk_across_floors_keeps_every_floors_points(st):
    """A walk solved on two floors of one batch run has a checkpoint entry on each (each with that floor's
    points only): the run keeps both pieces, their count, the corrected state of the floor where it was
    placed, whatever the order of the floors, and the scale of the longer piece."""
    w = _fill(st, 2)
    a = _track(w[0], T0, anchored="loops")
    upper = CorrectedTrack(w[0], a.t[:5] + 20.0, a.pos_enu[:5], a.cov[:5], ("F2",) * 5, a.kind[:5], "relative", 0.9, -0.2)
    run = st.slam.begin_run("s1", ["F1", "F2", "F3"])
    # F1: placed; F2: a short relative piece; F3: nothing to place there (no points)
    st.slam.write_floor(run, "F1", [WalkResult(w[0], CORRECTED, a), WalkResult(w[1], CORRECTED, _track(w[1], T0 + 1000))])
    st.slam.write_floor(run, "F2", [WalkResult(w[0], RELATIVE, upper)])
    st.slam.write_floor(run, "F3", [WalkResult(w[0], RELATIVE, None, "no track")])
    st.slam.finish_run(run)
    got = st.slam.tracks("s1")[w[0]]
    assert len(got) == len(a) + len(upper) and set(got.floor) == {"F1", "F2"}
    state = st.slam.walk_states("s1")[w[0]]
    assert (state.status, state.n_points) == (CORRECTED, len(a) + len(upper))
    assert got.anchored == "loops" and got.scale == a.scale and got.heading_bias == a.heading_bias


@pytest.mark.parametrize(
    ("solved", "added", "every", "share", "due"),
    [
        (0, 24, 25, 0.25, False),  # no batch yet: the count alone
        (0, 25, 25, 0.25, True),
        (80, 25, 25, 0.25, True),  # below every / share = 100 walks solved: the count alone
        (200, 25, 25, 0.25, False),  # a site of 200 walks waits for a quarter of it
        (200, 49, 25, 0.25, False),
        (200, 50, 25, 0.25, True),
        (200, 25, 25, 0.0, True),  # share 0: every 25 walks, as before
        (200, 60, 0, 0.25, False),  # not by count at all
    ],
)
def test_batch_schedule_by_count_and_share(db_url, solved, added, every, share, due):
    """A batch re-solve is due after max(batch_every_walks, batch_share x the walks the last batch solved)
    walks added since it (the interval and a request aside): batches at geometrically spaced site sizes."""
    from sqlalchemy.orm import Session

    from hybridloc.server import db as m
    from hybridloc.server.slam_worker import SlamOptions, SlamWorker

    st = Store(db_url)
    try:
        with Session(st.engine) as s, s.begin():
            s.add(m.Site(id="sched"))
            s.flush()
            if solved:
                s.add(
                    m.SlamRun(
                        site_id="sched",
                        kind="batch",
                        status="complete",
                        finished_at=m.utcnow(),
                        stats={"walks": {"corrected": solved - 3, "relative": 3}},
                    )
                )
                s.flush()
            for _ in range(added):
                s.add(m.SlamRun(site_id="sched", kind="walk", status="complete", finished_at=m.utcnow()))
        w = SlamWorker(db_url, "sched", lambda *_: None, SlamOptions(batch_every_walks=every, batch_share=share, batch_interval_s=0))
        try:
            assert w._since_last_batch()[0::2] == (added, solved)
            assert w._batch_due() is due
        finally:
            w.store.close()
    finally:
        st.close()


def test_a_heartbeat_never_puts_back_the_stats_of_a_finished_run(st, monkeypatch):
    """The lease's heartbeat reads a run's stats, the run finishes (writing its own stats), then the
    heartbeat writes: its write must not land on the finished run (it put the lease-only stats back over
    the finished run's, seen in an eval crowd run: the worker's batch schedule then read 0 walks solved)."""
    import hybridloc.server.slam_store as ss

    lease = {"token": "t", "host": "h", "pid": 1, "heartbeat": 0.0}
    run, _, _ = st.slam.claim_batch("race", None, lease, lambda held: False)
    fired = []

    class Racing(ss.Session):
        def get(self, *a, **k):
            obj = super().get(*a, **k)
            if not fired:
                fired.append(True)
                st.slam.finish_run(run, None, stats={"walks": {"corrected": 7}})  # another session, between read and write
            return obj

    monkeypatch.setattr(ss, "Session", Racing)
    assert st.slam.renew_lease(run, "t", 1.0) is False
    monkeypatch.undo()
    (info,) = [r for r in st.slam.runs("race") if r.run_id == run]
    assert info.status == "complete" and info.stats["walks"] == {"corrected": 7}

"""Crowd SLAM live (hybridloc.slam.online) on real recordings: the bundled sample of site1 F1 (35 walks)
and, where present, ../shared/data/msft-ilc/site1 (a second floor).

The sample's walks get walk ids 100.. in file order; a seeded third keep their waypoints as survey marks
(they also label the survey map the server would serve), the others lose them before anything reads them
(their waypoints stay in the test, for nothing but a sanity bound)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hybridloc.io.msft import find_ilc_traces, read_ilc_site
from hybridloc.radio.radiomap import build_radio_map
from hybridloc.radio.survey import label_scans
from hybridloc.samples import ILC_SITE1_F1
from hybridloc.slam.online import (
    MAX_OUTSIDE_SHARE,
    MAX_STEP_M,
    CrowdSlam,
    build_crowd_maps,
    check_track,
    label_time,
    labels_from_marks,
    labels_from_tracks,
)
from hybridloc.slam.pipeline import MARKS, RELATIVE, SlamConfig, run_slam
from hybridloc.slam.walkgraph import walks_from_files
from hybridloc.types import CorrectedTrack, Waypoints

#: a survey mark's sd (SlamConfig.mark_sigma_m: a person marks a point to about half a metre)
MARK_SD_M = SlamConfig().mark_sigma_m


@pytest.fixture(scope="module")
def sample():
    """(walks, plan, survey map): the bundled sample as the server would hold it."""
    paths = find_ilc_traces(ILC_SITE1_F1)
    loaded = walks_from_files(paths, marks=True, workers=2)
    rng = np.random.default_rng(21)
    marked = set(rng.choice(len(loaded), size=len(loaded) // 3, replace=False).tolist())
    walks = [dataclasses.replace(w, walk_id=100 + i, marks=w.marks if i in marked else ()) for i, (w, _) in enumerate(loaded)]
    plan = read_ilc_site(ILC_SITE1_F1)
    return walks, plan, _survey_map(walks, plan)


def _survey_map(walks, plan):
    """The survey map of the marked walks (as server/rebuild labels them: PDR bridged between marks)."""
    refs = []
    for w in walks:
        if w.marks:
            wp = Waypoints(np.array([m.t for m in w.marks]), np.array([[m.x, m.y] for m in w.marks]), w.marks[0].floor)
            wifi = [s for s in w.scans if s.technology.value == "wifi"]
            refs += label_scans(wifi, list(w.steps), wp, w.t_start, source=f"survey-{w.walk_id}")
    return build_radio_map(refs, site="site1", plan=plan)


def _held_state(cs: CrowdSlam) -> dict:
    """Every held piece's solution (copies), to check that nothing moved."""
    out = {}
    for f in cs._floors.values():
        for key, h in f.held.items():
            out[(f.name, key)] = None if h.pos is None else (h.pos.copy(), h.cov.copy(), h.status)
    return out


def _same_state(a: dict, b: dict) -> bool:
    if set(a) != set(b):
        return False
    for k, v in a.items():
        w = b[k]
        if (v is None) != (w is None):
            return False
        if v is not None and not (np.array_equal(v[0], w[0]) and np.array_equal(v[1], w[1], equal_nan=True) and v[2] == w[2]):
            return False
    return True


@pytest.fixture(scope="module")
def replay(sample):
    """Every walk of the sample added one by one (seeded order) with the survey map served, the held
    state checked around each add; then the floor re-solved in batch."""
    walks, plan, smap = sample
    cs = CrowdSlam("site1", plan)
    cs.set_map(smap)
    order = np.random.default_rng(5).permutation(len(walks))
    outcomes, moved = {}, []
    for k in order:
        before_state, before_tracks = _held_state(cs), dict(cs.tracks)
        o = cs.add_walk(walks[k])
        outcomes[o.walk_id] = o
        after = _held_state(cs)
        after_old = {key: v for key, v in after.items() if key[1][0] != o.walk_id}
        if not _same_state(before_state, after_old) or any(cs.tracks[w] is not t for w, t in before_tracks.items()):
            moved.append(o.walk_id)
    inc_tracks = dict(cs.tracks)
    inc_labels, inc_coverage = cs.labels(), cs.coverage()
    batch = cs.rebuild_floor("F1")
    return cs, outcomes, moved, inc_tracks, inc_labels, inc_coverage, batch


# ------------------------------------------------------------------------------------------ incremental
def test_add_walk_tracks_every_step_and_scan(sample, replay):
    walks, _, _ = sample
    cs, outcomes, moved, inc_tracks, *_ = replay
    by_id = {w.walk_id: w for w in walks}
    assert set(outcomes) == set(by_id)
    # quarantine is the exception: a walk the map's fixes stretch into a wrong corridor at an impossible
    # step scale is caught (it is not held, its track is returned for inspection)
    bad = {wid: o.quarantined for wid, o in outcomes.items() if o.quarantined}
    assert len(bad) <= len(walks) // 10, bad
    assert all(r.startswith(("diverged: ", "off-walkable: ")) for r in bad.values())
    assert set(bad) == set(cs.quarantined) and not set(bad) & set(cs.walks)
    for wid, o in outcomes.items():
        w, tr = by_id[wid], o.track
        assert tr is not None and tr.walk_id == wid
        assert len(tr) == len(w.steps) + len(w.scans)
        assert tr.kind.count("step") == len(w.steps) and tr.kind.count("scan") == len(w.scans)
        assert np.all(np.diff(tr.t) >= 0) and set(tr.floor) == {"F1"}
        steps_t = np.array([t for t, k in zip(tr.t, tr.kind) if k == "step"])
        np.testing.assert_array_equal(steps_t, sorted(s.t for s in w.steps))
        scans_t = sorted(t for t, k in zip(tr.t, tr.kind) if k == "scan")
        np.testing.assert_allclose(scans_t, sorted(label_time(s) for s in w.scans))
        if tr.anchored == RELATIVE:
            assert np.all(np.isnan(tr.cov))
        else:
            assert np.all(np.isfinite(tr.cov)) and np.all(np.linalg.eigvalsh(tr.cov) > 0)
        assert all(str(wid) in (lp.walk_a, lp.walk_b) and 0.0 <= lp.weight <= 1.0 for lp in o.loops)
        assert all(lp.reason for lp in o.loops if not lp.accepted)
        assert o.seconds > 0
    assert sum(lp.accepted for o in outcomes.values() for lp in o.loops) > 0
    # the walks without marks found their place: by the survey map's fixes or loops to placed walks
    assert {tr.anchored for wid, tr in inc_tracks.items() if tr is not None and not by_id[wid].marks} & {"map", "loops"}
    assert set(inc_tracks) == set(by_id) - set(bad)


def test_add_walk_never_moves_the_held_walks(replay):
    _, _, moved, *_ = replay
    assert moved == []


def test_marked_walks_are_anchored_by_their_marks(sample, replay):
    """A walk with survey marks is tied to them: at each mark its corrected track is within about the
    marks' own sd (0.5 m). The odometry between marks, with its scale and heading bias free, absorbs
    the PDR's drift; what is left at a mark is shared between the mark and the PDR's white error: the
    median over a walk's marks is bounded by 2 sd."""
    walks, _, _ = sample
    _, outcomes, *_ = replay
    marked = [w for w in walks if w.marks]
    assert marked
    for w in marked:
        tr = outcomes[w.walk_id].track
        assert tr.anchored == MARKS
        at = [tr.at(m.t) for m in w.marks]
        d = [np.linalg.norm(p[0] - (m.x, m.y)) for p, m in zip(at, w.marks) if p is not None]
        assert len(d) >= len(w.marks) - 2  # a mark outside the steps' span has no track point around it
        assert np.median(d) < 2 * MARK_SD_M, (w.walk_id, np.round(d, 2))


def test_incremental_is_close_to_batch(sample, replay):
    """The same walks solved one by one (each against the others held) and all together (re-solved
    jointly, EM with the crowd map). Both estimate the same positions from the same data, so their
    difference is within their combined sd s = sqrt(s_inc^2 + s_batch^2) per axis: its norm is at most
    Rayleigh-like, median 1.18 s, 99 % below 3.03 s (less: the two share their data). Marked walks are
    held by the same 0.5 m marks in both: within one mark sd."""
    walks, _, _ = sample
    cs, _, _, inc_tracks, _, _, batch = replay
    by_id = {w.walk_id: w for w in walks}
    ratios = []
    for wid, a in inc_tracks.items():
        b = cs.tracks.get(wid)
        if a is None or b is None or a.anchored == RELATIVE or b.anchored == RELATIVE:
            continue
        d = np.linalg.norm(a.pos_enu - b.pos_enu, axis=1)
        if by_id[wid].marks:
            assert np.median(d) < MARK_SD_M, wid
            continue
        s = np.sqrt(0.5 * (np.trace(a.cov, axis1=1, axis2=2) + np.trace(b.cov, axis1=1, axis2=2)))
        ratios.append(float(np.median(d / s)))
    assert len(ratios) >= 5
    assert np.median(ratios) <= 1.18 and max(ratios) <= 3.03, np.round(sorted(ratios), 2)
    assert batch.stats["walks"] == len(cs.walks) + batch.stats["quarantined"]


def test_batch_anchors_more_and_keeps_its_audit(sample, replay):
    walks, _, _ = sample
    cs, outcomes, _, _, _, inc_coverage, batch = replay
    held_before = {wid for wid, o in outcomes.items() if not o.quarantined}
    assert batch.floor == "F1" and set(batch.walks) == held_before
    assert sum(batch.stats["anchored"].values()) == len(held_before) - batch.stats["quarantined"]
    assert batch.stats["readded"] <= len(held_before) and batch.stats["quarantined"] == sum(1 for o in batch.walks.values() if o.quarantined)
    assert batch.stats["loops_candidates"] == len(batch.loops) and batch.stats["loops_accepted"] == sum(lp.accepted for lp in batch.loops)
    for wid, o in batch.walks.items():
        assert all(str(wid) in (lp.walk_a, lp.walk_b) for lp in o.loops)
        assert (o.track is cs.tracks[wid]) if not o.quarantined else (wid in cs.quarantined and wid not in cs.walks)
    # the joint solve and EM place at least as many crowd scans as the walks one by one did
    assert cs.coverage() >= inc_coverage


# ------------------------------------------------------------------------------------------ batch = run_slam
def test_rebuild_floor_is_run_slam_for_one_floor(sample):
    """On a site of one floor, rebuild_floor over held walks is run_slam: the same corrected tracks, the
    same anchoring and loop audit, the same labels (positions; the sds of between-node BLE scans are at
    least run_slam's: the track's covariance adds the Brownian bridge of the dead reckoning)."""
    walks, plan, smap = sample
    sub = walks[:12]
    res = run_slam(sub, plan, smap)
    cs = CrowdSlam("site1", plan)
    cs.set_map(smap)
    for w in sub:
        cs.hold(w, None)
    out = cs.rebuild_floor("F1")
    fs = res.floors["F1"]
    for k, pc in enumerate(fs.pieces):
        wid = sub[pc.walk].walk_id
        tr = cs.tracks[wid]
        assert tr.anchored == fs.status[k]
        got = np.array([tr.at(t)[0] for t in pc.step_t[1:]])
        np.testing.assert_allclose(got, fs.track(k, pc.step_t[1:]), atol=1e-9)
    key = lambda lp: (lp.walk_a, lp.t_a, lp.walk_b, lp.t_b, lp.kind)  # noqa: E731
    ref = {key(lp): lp for lp in res.loops}
    assert set(ref) == {key(lp) for lp in out.loops}
    for lp in out.loops:
        r = ref[key(lp)]
        assert (lp.accepted, lp.reason) == (r.accepted, r.reason) and lp.weight == pytest.approx(r.weight, abs=1e-12)
    a = {id(ls.scan): ls for ls in res.labels}
    b = {id(ls.scan): ls for ls in cs.labels()}
    assert set(a) == set(b)
    for i, la in a.items():
        lb = b[i]
        np.testing.assert_allclose(lb.pos_enu, la.pos_enu, atol=1e-9)
        assert lb.source == la.source and lb.floor == la.floor
        if la.scan.technology.value == "wifi":
            assert lb.sigma == pytest.approx(la.sigma, rel=1e-9)
        else:
            assert lb.sigma >= la.sigma - 1e-12


# ------------------------------------------------------------------------------------------ quarantine
def test_a_corrupted_walk_is_quarantined_and_changes_nothing(sample):
    """Walks made to diverge (10 m steps; survey marks 300 m off the plan; a step of 1e30 m that breaks
    the arithmetic) are quarantined with their reason, counted and not held; the held solution is exactly
    what it was, and a sane walk still adds after them."""
    walks, plan, smap = sample
    cs = CrowdSlam("site1", plan)
    cs.set_map(smap)
    for w in walks[:15]:
        assert cs.add_walk(w).quarantined == ""
    state, tracks, labels = _held_state(cs), dict(cs.tracks), len(cs.labels())
    plain = next(w for w in walks[15:] if not w.marks)
    marked = next(w for w in walks[15:] if w.marks)
    long_steps = dataclasses.replace(plain, walk_id=900, steps=tuple(dataclasses.replace(s, length=10.0) for s in plain.steps))
    off_plan = dataclasses.replace(marked, walk_id=901, marks=tuple(dataclasses.replace(m, x=m.x + 300.0) for m in marked.marks))
    broken = list(marked.steps)
    broken[3] = dataclasses.replace(broken[3], length=1e30)
    overflow = dataclasses.replace(marked, walk_id=902, steps=tuple(broken))
    reasons = {}
    for bad in (long_steps, off_plan, overflow):
        o = cs.add_walk(bad)
        reasons[o.walk_id] = o.quarantined
        assert o.walk_id not in cs.walks and cs.quarantined[o.walk_id] == o.quarantined
    assert reasons[900].startswith("diverged:")
    assert reasons[901].startswith(("diverged:", "off-walkable:"))
    assert reasons[902].startswith("error: ")
    assert _same_state(state, _held_state(cs)) and all(cs.tracks[w] is t for w, t in tracks.items()) and len(cs.labels()) == labels
    assert cs.add_walk(plain).quarantined == ""


def test_check_track_verdicts(replay):
    """check_track on real corrected tracks: fine as they are; off-walkable when moved off the plan
    (relative ones are shapes only, never checked against the plan); diverged with one step too long
    or an impossible scale."""
    cs, *_ = replay
    plan = cs.plan
    tracks = [t for t in cs.tracks.values() if t is not None]
    absolute = next(t for t in tracks if t.anchored != RELATIVE)
    fields = {"F1": cs._floors["F1"].field}
    for t in tracks:
        assert check_track(t, plan, fields) == ""
        assert check_track(t, plan) == ""  # shapely's distance instead of the field
    moved = dataclasses.replace(absolute, pos_enu=absolute.pos_enu + [300.0, 0.0])
    assert check_track(moved, plan, fields) == "off-walkable: 100 % of the track outside the walkable area"
    assert check_track(dataclasses.replace(moved, anchored=RELATIVE, cov=np.full_like(moved.cov, np.nan)), plan, fields) == ""
    # a share just over the bound: its first points moved far out
    n = len(absolute)
    k = int(math.ceil((MAX_OUTSIDE_SHARE + 0.05) * n))
    part = absolute.pos_enu.copy()
    part[:k] += [300.0, 0.0]
    assert check_track(dataclasses.replace(absolute, pos_enu=part), plan, fields, max_step_m=1e9).startswith("off-walkable:")
    steps = [i for i, kd in enumerate(absolute.kind) if kd == "step"]
    jump = absolute.pos_enu.copy()
    jump[steps[len(steps) // 2] :] += [0.0, MAX_STEP_M + 1.0]
    assert check_track(dataclasses.replace(absolute, pos_enu=jump), None).startswith("diverged: a corrected step")
    assert check_track(dataclasses.replace(absolute, scale=0.3), None).startswith("diverged: step-length scale")
    assert check_track(dataclasses.replace(absolute, cov=absolute.cov * 1e6), None).startswith("diverged: position sd")


# ------------------------------------------------------------------------------------------ products
def test_labels_coverage_and_crowd_maps(sample, replay):
    walks, plan, _ = sample
    cs, *_ = replay
    labels = cs.labels()
    held = [w for w in walks if w.walk_id in cs.walks]
    absolute = {wid for wid, t in cs.tracks.items() if t is not None and t.anchored != RELATIVE}
    assert labels and {int(ls.source) for ls in labels} == absolute
    assert all(ls.sigma > 0 and math.isfinite(ls.sigma) and ls.floor == "F1" and len(ls.scan) for ls in labels)
    # the labels are the tracks' scan points
    again = labels_from_tracks(held, {wid: t for wid, t in cs.tracks.items() if t is not None})
    assert [(id(a.scan), a.source) for a in again] == [(id(b.scan), b.source) for b in labels]
    assert all(np.array_equal(a.pos_enu, b.pos_enu) and a.sigma == b.sigma for a, b in zip(again, labels))
    # coverage: labelled scans of unmarked walks over all their scans with readings
    crowd = [w for w in walks if not w.marks and (w.walk_id in cs.walks or w.walk_id in cs.quarantined)]  # quarantined ones count
    n_all = sum(1 for w in crowd for s in w.scans if len(s))
    n_lab = sum(1 for ls in labels if not cs.walks[int(ls.source)].marks)
    assert cs.coverage() == pytest.approx(n_lab / n_all)
    assert cs.coverage(["F1"]) == cs.coverage() and math.isnan(cs.coverage(["F9"])) and cs.labels(["F9"]) == []
    maps = build_crowd_maps(labels, "site1", plan)
    assert "wifi" in maps
    for tech, rm in maps.items():
        assert rm.technology == tech and "F1" in rm.floors
        assert len(rm.references) == sum(1 for ls in labels if ls.scan.technology.value == tech)


def test_surveys_without_an_absolute_track_are_labelled_by_their_marks(sample, replay):
    """A survey ended after a batch began has no track in it: the crowd map labels its scans from its marks,
    exactly as the survey map does (PDR bridged between marks); a survey with an absolute track is
    labelled from the track only, a relative or missing track falls back to the marks."""
    walks, _, _ = sample
    cs, *_ = replay
    surveys = [w for w in walks if w.marks]
    crowd_walk = next(w for w in walks if not w.marks)
    tracks = {wid: t for wid, t in cs.tracks.items() if t is not None}
    absolute = {wid for wid, t in tracks.items() if t.anchored != RELATIVE}
    assert {w.walk_id for w in surveys} <= absolute  # every survey of the replay is mark-anchored
    assert labels_from_marks(walks, tracks) == []  # nothing to add: every survey has its track
    late, relative = surveys[0], surveys[1]
    without = {wid: t for wid, t in tracks.items() if wid != late.walk_id}
    without[relative.walk_id] = dataclasses.replace(tracks[relative.walk_id], anchored=RELATIVE)
    got = labels_from_marks(walks, without)
    assert {ls.source for ls in got} == {str(late.walk_id), str(relative.walk_id)}
    for w in (late, relative):
        wp = Waypoints(np.array([m.t for m in w.marks]), np.array([[m.x, m.y] for m in w.marks]), w.marks[0].floor)
        want = label_scans([s for s in w.scans if len(s)], list(w.steps), wp, w.t_start, source=str(w.walk_id))
        mine = [ls for ls in got if ls.source == str(w.walk_id)]
        assert want and len(mine) == len(want)
        assert all(a.scan is b.scan and np.array_equal(a.pos_enu, b.pos_enu) and a.floor == b.floor == "F1" for a, b in zip(mine, want))
    # a phone walk (no marks) without a track is not labelled, whatever its track
    assert labels_from_marks([crowd_walk], {}) == []


def test_a_batch_on_a_crowd_map_keeps_the_survey_labels(sample, replay):
    """On a crowd map (what a restarted server or ``slam rebuild`` serves: every label sourced by its
    walk id) a batch is not fixed to its crowd walks' own labels, fed back, but keeps the survey walks'
    labels, which come from their marks: its crowd walks still get fixes on the floor it solves (before,
    every label of the floor was left out, and a one-floor site's batch got no fix at all)."""
    _, plan, smap = sample
    cs, *_ = replay
    crowd = build_crowd_maps(cs.labels(), "site1", plan)["wifi"]
    ids = set(cs.walks)
    left_out = cs._fed_back(ids)
    assert left_out == {str(w) for w in ids if not cs.walks[w].marks}
    kept = {r.source for r in crowd.references if r.source not in left_out}
    assert kept and kept <= {str(w) for w in ids if cs.walks[w].marks}
    fl = cs._floor("F1")
    keys = sorted(k for k, h in fl.held.items() if not cs.walks[k[0]].marks)
    pieces = [fl.held[k].piece for k in keys]
    try:
        cs.set_map(crowd)
        fixes = cs._map_fixes(pieces, exclude=left_out)
        everyone = cs._map_fixes(pieces, exclude={str(w) for w in ids})  # the old rule
    finally:
        cs.set_map(smap)
    assert sum(map(len, fixes.values())) > 0 and not everyone


def test_hold_round_trip(sample, replay):
    """A server restart: the stored walks and tracks held again give the same labels and coverage, and a
    walk added afterwards is solved as it would have been without the restart (the neighbours' loop and
    beacon nodes are scan points of their stored tracks: the same positions)."""
    walks, plan, smap = sample
    cs, *_ = replay
    again = CrowdSlam("site1", plan)
    again.set_map(smap)
    for wid, w in cs.walks.items():
        again.hold(w, cs.tracks[wid])
    by_id = {w.walk_id: w for w in walks}
    for wid, why in cs.quarantined.items():
        again.hold(by_id[wid], None, quarantined=why)
    assert again.quarantined == cs.quarantined and set(again.walks) == set(cs.walks)
    assert again.floors() == cs.floors() == ["F1"]
    a, b = cs.labels(), again.labels()
    assert [(id(x.scan), x.source, x.sigma) for x in a] == [(id(x.scan), x.source, x.sigma) for x in b]
    assert all(np.array_equal(x.pos_enu, y.pos_enu) for x, y in zip(a, b))
    assert again.coverage() == cs.coverage()
    # the same walk re-added to both
    w = next(w for w in walks if not w.marks and cs.tracks[w.walk_id].anchored in ("map", "loops"))
    for s in (cs, again):
        s.remove_walk(w.walk_id)
    o1, o2 = cs.add_walk(w), again.add_walk(w)
    assert o1.quarantined == o2.quarantined == ""
    assert o1.track.anchored == o2.track.anchored
    assert {(lp.walk_a, lp.t_a, lp.t_b) for lp in o1.loops if lp.accepted} == {(lp.walk_a, lp.t_a, lp.t_b) for lp in o2.loops if lp.accepted}
    # the held nodes differ only by the covariance read from the nearest track point: centimetres
    assert np.max(np.linalg.norm(o1.track.pos_enu - o2.track.pos_enu, axis=1)) < 0.05


def test_remove_walk_forgets_it_and_moves_nothing(sample, replay):
    walks, plan, smap = sample
    cs = CrowdSlam("site1", plan)
    cs.set_map(smap)
    for w in walks[:8]:
        cs.add_walk(w)
    gone = walks[3].walk_id
    state = _held_state(cs)
    cs.remove_walk(gone)
    assert gone not in cs.walks and gone not in cs.tracks and all(ls.source != str(gone) for ls in cs.labels())
    left = {k: v for k, v in state.items() if k[1][0] != gone}
    assert _same_state(left, _held_state(cs))
    assert all(str(gone) not in (lp.walk_a, lp.walk_b) for f in cs._floors.values() for lp in f.loops)


def test_incremental_loops_match_detect_new(sample):
    """LoopDetector.detect_incremental gives the same mutual candidates and accepted loops as detect_new
    (the brute-force reverse pass), scoring only the old scans a new scan lists."""
    from hybridloc.slam.frontend import LoopDetector
    from hybridloc.slam.online import _walk_scans
    from hybridloc.slam.walkgraph import walk_pieces

    walks, _, _ = sample
    ws = [x for i, w in enumerate(walks) for pc in walk_pieces(w, i) if (x := _walk_scans(pc, i)) is not None]
    det = LoopDetector()
    det.fit(ws)
    linked = sorted({lp.walk_b for lp in det.detect(ws) if lp.accepted})  # walks with accepted loops
    assert linked
    accepted = 0
    for n in [0, len(ws) - 1] + linked[:: max(1, len(linked) // 4)]:
        new, old = [ws[n]], ws[:n] + ws[n + 1 :]
        full = det.detect_new(new, old)
        fast = det.detect_incremental(new, old)
        # the candidates that passed the similarity floor and were mutual: all the model gate and PCM see
        mutual = lambda loops: {  # noqa: E731
            (lp.walk_a, lp.node_a, lp.walk_b, lp.node_b, lp.similarity, lp.accepted, lp.reason)
            for lp in loops
            if lp.reason not in ("below-s-min", "not-mutual")
        }
        assert mutual(fast) == mutual(full)
        assert {(lp.walk_a, lp.node_a, lp.walk_b, lp.node_b) for lp in fast} <= {(lp.walk_a, lp.node_a, lp.walk_b, lp.node_b) for lp in full}
        accepted += sum(lp.accepted for lp in full)
    assert accepted > 0


# ------------------------------------------------------------------------------------------ several floors
def test_a_second_floor_and_a_walk_across_floors(sample, ilc_site1):
    """With site1's F2 walks beside the sample's F1: floors are solved apart (rebuilding F2 leaves every
    F1 track as it was), labels and coverage select by floor, and a walk that takes the stairs (an F1
    walk continued by an F2 walk, the floor change on its first F2 step) gives one track whose points
    carry their floor."""
    walks, _, _ = sample
    plan = read_ilc_site(ilc_site1)
    f2_paths = sorted((ilc_site1 / "F2" / "path_data_files").glob("*.txt*"))[:8]
    f2 = [
        dataclasses.replace(w, walk_id=500 + i, marks=w.marks if i < 3 else ())
        for i, (w, _) in enumerate(walks_from_files(f2_paths, marks=True, workers=2))
    ]
    cs = CrowdSlam("site1", plan)
    for w in walks[:10] + f2:
        assert cs.add_walk(w).quarantined == ""
    assert cs.floors() == ["F1", "F2"]
    f1_tracks = {wid: t for wid, t in cs.tracks.items() if wid < 500}
    out = cs.rebuild_floor("F2")
    assert set(out.walks) == {w.walk_id for w in f2}
    assert all(cs.tracks[wid] is t for wid, t in f1_tracks.items())
    assert {ls.floor for ls in cs.labels(["F2"])} <= {"F2"} and {int(ls.source) for ls in cs.labels(["F1"])} <= set(f1_tracks)
    # the stairs walk
    a, b = walks[12], f2[5]
    shift = a.t_end + 30.0 - b.t_start
    b_steps = [dataclasses.replace(s, t=s.t + shift) for s in b.steps]
    b_steps[0] = dataclasses.replace(b_steps[0], floor_change=1)
    b_scans = [dataclasses.replace(s, t=s.t + shift) for s in b.scans]
    both = dataclasses.replace(
        a, walk_id=777, t_end=b.t_end + shift, floors=("F1", "F2"), steps=a.steps + tuple(b_steps), scans=a.scans + tuple(b_scans), marks=()
    )
    o = cs.add_walk(both)
    assert o.quarantined == "" and o.track is not None
    assert len(o.track) == len(both.steps) + len(both.scans)
    fl = np.array(o.track.floor)
    t_change = b_steps[0].t
    assert set(fl[o.track.t < t_change - 1.0]) == {"F1"} and set(fl[o.track.t > t_change + 1.0]) == {"F2"}
    assert {lp.floor for lp in o.loops} <= {"F1", "F2"}
    assert isinstance(o.track, CorrectedTrack)


def test_batch_quarantines_a_corrupted_walk_and_solves_the_rest(sample):
    """A corrupted walk (10 m steps) reaching a batch re-solve (held without a track, as after a restart):
    the joint solve cannot fit it, it fails on its own too, so it is quarantined; every other walk gets
    its batch solution and none of them is quarantined."""
    walks, plan, smap = sample
    cs = CrowdSlam("site1", plan)
    cs.set_map(smap)
    for w in walks[:12]:
        cs.hold(w, None)
    plain = next(w for w in walks[12:] if not w.marks)
    bad = dataclasses.replace(plain, walk_id=950, steps=tuple(dataclasses.replace(s, length=10.0) for s in plain.steps))
    cs.hold(bad, None)
    stages = []
    out = cs.rebuild_floor("F1", progress=lambda stage, floor, done, total: stages.append((stage, floor)))
    assert out.walks[950].quarantined.startswith("diverged:") and 950 in cs.quarantined and 950 not in cs.walks
    assert [wid for wid, o in out.walks.items() if o.quarantined] == [950]
    assert all(cs.tracks[w.walk_id] is out.walks[w.walk_id].track is not None for w in walks[:12])
    assert out.stats["quarantined"] == 1 and sum(out.stats["anchored"].values()) == 12
    assert stages[0] == ("loops", "F1") and stages[-1] == ("done", "F1")
    # its candidates are in its outcome (the audit of what it tried), not in the floor's current audit
    assert all("950" not in (lp.walk_a, lp.walk_b) for lp in out.loops)


def test_a_walk_is_held_on_the_floor_its_fingerprints_name(sample):
    """A crowd walk's floor is a claim: a single-floor walk without marks that names a floor its scans
    do not match is held on the floor the served map's fixes name (>= SlamConfig.floor_vote_min_fixes
    gated fixes, a floor_vote_share majority), or the vote map's when one is set; a surveyed walk, a walk
    with too few scans, a site with no map, or the vote switched off keep the claim; a stored absolute
    track keeps the walk where the solve put it."""
    walks, plan, smap = sample
    cfg = SlamConfig(floor_vote=True)  # the default (SlamConfig.floor_vote), written out
    wifi = lambda w: [s for s in w.scans if s.technology.value == "wifi"]  # noqa: E731
    # a walk whose places the map covers (a surveyed walk's scans, its marks dropped: the bundled sample's
    # map is too sparse for most other walks' scans to pass the mapped-distance gate)
    covered = next(w for w in walks if w.marks and len(wifi(w)) >= 3 * cfg.floor_vote_min_fixes)
    claim = dataclasses.replace(covered, walk_id=900, floors=("F9",), marks=())
    cs = CrowdSlam("site1", plan, cfg)
    cs.set_map(smap)
    o = cs.add_walk(claim)
    assert o.quarantined == "" and o.track is not None
    assert set(o.track.floor) == {"F1"} and cs.floor_moves[900] == ("F9", "F1")
    # a surveyed walk keeps the floor it names, whatever its scans say
    marks_f9 = tuple(dataclasses.replace(m, floor="F9") for m in covered.marks)
    surveyed = cs._walk_pieces(dataclasses.replace(covered, walk_id=901, floors=("F9",), marks=marks_f9))[0]
    assert (surveyed.mark >= 0).any() and surveyed.floor == "F9"
    # too few scans to vote: the claim stands
    few = dataclasses.replace(claim, walk_id=902, scans=tuple(wifi(claim)[: cfg.floor_vote_min_fixes - 1]))
    assert cs._walk_pieces(few)[0].floor == "F9" and 902 not in cs.floor_moves
    # no map, or the vote off: the claim stands
    bare = CrowdSlam("site1", plan, cfg)
    assert bare._walk_pieces(claim)[0].floor == "F9"
    off = CrowdSlam("site1", plan, dataclasses.replace(cfg, floor_vote=False))
    off.set_map(smap)
    assert off._walk_pieces(claim)[0].floor == "F9"
    assert CrowdSlam("site1", plan).cfg.floor_vote  # the default: on
    # the vote reads the vote map when one is set (the SLAM child's newest crowd map), not the served one
    voted = CrowdSlam("site1", plan, cfg)
    voted.set_vote_map(smap)
    assert voted._walk_pieces(claim)[0].floor == "F1" and voted._map is None
    voted.set_vote_map(None)  # none: back to the served map, here none
    assert voted._walk_pieces(claim)[0].floor == "F9"
    # what the Dask path groups floors by
    assert cs.held_floors(claim) == ["F1"] and off.held_floors(claim) == ["F9"] and off.revote_floors() == []
    # a restart: the stored absolute track holds the walk on its floor, map or not
    bare.hold(claim, o.track)
    assert bare._pieces[900][0].floor == "F1" and bare.floor_moves[900] == ("F9", "F1")
    # forgetting the walk forgets its move
    bare.remove_walk(900)
    assert 900 not in bare.floor_moves
    # held before a map could place it, asked again once the map is served (what a batch starts with)
    bare.hold(claim, None)
    assert bare._pieces[900][0].floor == "F9" and bare.revote_floors() == []
    bare.set_map(smap)
    assert bare.revote_floors() == [900] and bare._pieces[900][0].floor == "F1" and bare.floor_moves[900] == ("F9", "F1")
    assert bare.revote_floors() == []  # nothing left to move


def test_em_goes_on_while_a_round_anchors_more_pieces(sample, monkeypatch):
    """The EM stop (labels moved less than em_stop_m) measures only the pieces already anchored, so it
    does not end EM while a round still anchors more of them (SlamConfig.em_while_anchoring). With the
    stop made certain (em_stop_m huge), EM runs exactly until the first round that anchored no more,
    at most em_rounds; with the rule off, one round."""
    from hybridloc.slam import online

    walks, plan, smap = sample
    grew: list[bool] = []
    real = online.anchored_more

    def watched(old, new):
        grew.append(real(old, new))
        return grew[-1]

    monkeypatch.setattr(online, "anchored_more", watched)
    rounds = {}
    for rule in (True, False):
        grew.clear()
        cs = CrowdSlam("site1", plan, SlamConfig(em_stop_m=1e9, em_while_anchoring=rule))
        cs.set_map(smap)
        for w in walks:
            cs.hold(w, None)
        out = cs.rebuild_floor("F1")
        rounds[rule] = out.stats["em_rounds"]
        if rule:
            # every round but the last anchored more; the last anchored no more, or was the last allowed
            assert len(grew) == rounds[rule] >= 1 and all(grew[:-1]), (grew, rounds)
            assert not grew[-1] or rounds[rule] == SlamConfig().em_rounds
        else:
            assert grew == [] and rounds[rule] == 1

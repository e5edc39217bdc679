"""Radio maps, survey labelling, positioning, similarity: synthetic worlds with known truth + real data."""

import dataclasses
import gc
import json
import math

import numpy as np
import pytest

from hybridloc.errors import MissingData
from hybridloc.radio.locate import KnnLocator, ProbabilisticLocator
from hybridloc.radio.radiomap import BuildParams, RadioMap, build_radio_map
from hybridloc.radio.similarity import ProximityModel, cosine_shifted, jaccard
from hybridloc.radio.survey import LabelledScan, label_scans
from hybridloc.types import RfScan, StepEvent, Waypoints

APS = {"ap1": (0.0, 0.0), "ap2": (30.0, 0.0), "ap3": (0.0, 30.0), "ap4": (30.0, 30.0), "ap5": (15.0, 15.0)}


def rssi_at(xy, rng, noise=2.0):
    """Log-distance path loss: -40 dBm at 1 m, exponent 3 (typical indoor), Gaussian noise."""
    out = {}
    for k, p in APS.items():
        d = max(1.0, math.dist(xy, p))
        r = -40.0 - 30.0 * math.log10(d) + noise * rng.standard_normal()
        if r > -95:
            out[k] = r
    return out


def synth_survey(rng, n=1500, t0=0.0):
    pts = rng.uniform(0, 30, (n, 2))
    return [LabelledScan(RfScan(t0 + i, "wifi", rssi_at(p, rng), device_model="phoneA"), p, 0.5, "F1") for i, p in enumerate(pts)]


def test_survey_labelling_stretches_and_rotates_pdr_between_marks():
    # PDR walks East 10 steps of 0.7 m (7 m); the marks say the walk went 10 m North.
    steps = [StepEvent(t=1.0 + i, length=0.7, heading=0.0, sigma_length=0.05, sigma_heading=0.05) for i in range(10)]
    wp = Waypoints(np.array([0.5, 10.0]), np.array([[5.0, 5.0], [5.0, 15.0]]), "F2")
    scans = [RfScan(t, "wifi", {"a": -50.0}) for t in (0.2, 0.5, 5.5, 10.0, 12.0)]
    lab = label_scans(scans, steps, wp, t_start=0.0)
    assert [round(ls.scan.t, 1) for ls in lab] == [0.5, 5.5, 10.0]  # outside the marks: not labelled
    np.testing.assert_allclose(lab[0].pos_enu, [5.0, 5.0], atol=1e-9)
    np.testing.assert_allclose(lab[2].pos_enu, [5.0, 15.0], atol=1e-9)
    assert lab[1].pos_enu[0] == pytest.approx(5.0, abs=1e-9) and 5.0 < lab[1].pos_enu[1] < 15.0
    assert lab[0].sigma == pytest.approx(0.5) and lab[1].sigma > lab[0].sigma  # uncertainty peaks mid-way
    assert all(ls.floor == "F2" for ls in lab)


def test_survey_labelling_takes_each_marks_floor_and_skips_the_stairs():
    """A walk marked on F1, then F2 (the stairs between the 2nd and 3rd marks): scans take their
    segment's floor, and the scans between marks on two floors are left unlabelled."""
    steps = [StepEvent(t=1.0 + i, length=0.7, heading=0.0, sigma_length=0.05, sigma_heading=0.05) for i in range(30)]
    wp = Waypoints(np.array([0.5, 10.0, 20.0, 30.0]), np.array([[0.0, 0.0], [7.0, 0.0], [14.0, 0.0], [21.0, 0.0]]), "F1", ("F1", "F1", "F2", "F2"))
    scans = [RfScan(t, "wifi", {"a": -50.0}) for t in (5.0, 15.0, 25.0)]
    lab = label_scans(scans, steps, wp, t_start=0.0)
    assert [(ls.scan.t, ls.floor) for ls in lab] == [(5.0, "F1"), (25.0, "F2")]
    with pytest.raises(ValueError, match="one floor per mark"):
        Waypoints(np.array([0.0, 1.0]), np.zeros((2, 2)), "F1", ("F1",))
    assert Waypoints(np.array([0.0]), np.zeros((1, 2)), "F3").floor_of(0) == "F3"


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(11)
    refs = synth_survey(rng)
    rmap = build_radio_map(refs, site="synth", params=BuildParams(cell=1.5, min_samples=3))
    test_pts = rng.uniform(3, 27, (60, 2))
    tests = [RfScan(10_000.0 + i, "wifi", rssi_at(p, rng), device_model="phoneA") for i, p in enumerate(test_pts)]
    return refs, rmap, test_pts, tests


def test_probabilistic_and_knn_locate_synthetic_world(world):
    refs, rmap, pts, tests = world
    for name, results in (
        ("prob", [ProbabilisticLocator(rmap, tau=1.0).locate(s) for s in tests]),
        ("knn", KnnLocator(refs, k=5).locate_many(tests)),
    ):
        err = np.array([np.linalg.norm(r.fix.pos_enu - p) for r, p in zip(results, pts)])
        # 2 dB noise on a 30 dB/decade slope is ~15 % range error per AP; with 5 APs a few metres
        # at most in a 30 m room.
        assert np.median(err) < 3.0, (name, np.median(err))
        hits = np.mean([r.region.contains(p) for r, p in zip(results, pts)])
        assert hits >= 0.8, (name, hits)
        assert all(r.fix.floor == "F1" and 0 < r.fix.floor_prob <= 1 for r in results)


def _answers(results):
    return [
        (
            r.reason,
            r.n_known,
            r.floor_probs,
            None if r.fix is None else (r.fix.t, r.fix.pos_enu.tolist(), r.fix.cov.tolist(), r.fix.floor, r.fix.floor_prob),
        )
        for r in results
    ]


@pytest.mark.parametrize("metric,representation", [("sorensen", "auto"), ("euclidean", "raw")])
def test_knn_with_another_k_answers_as_a_locator_built_with_it(world, metric, representation):
    """with_k shares the references' fingerprint index (the SLAM's gate locator beside its fix locator)
    and answers exactly as a locator built afresh with that k, memo or not, without touching the first."""
    refs, _, _, tests = world
    for memo in (False, True):
        five = KnnLocator(refs, k=5, metric=metric, representation=representation, memo=memo and metric == "sorensen")
        before = five.nearest(tests)
        for k in (1, 12, len(refs) + 3):
            other = five.with_k(k)
            fresh = KnnLocator(refs, k=k, metric=metric, representation=representation)
            assert other.k == fresh.k
            for a, b in zip(other.nearest(tests), fresh.nearest(tests)):
                np.testing.assert_array_equal(a, b)
            assert _answers(other.locate_many(tests)) == _answers(fresh.locate_many(tests))
        for a, b in zip(five.nearest(tests), before):
            np.testing.assert_array_equal(a, b)


def test_knn_memo_relabel_and_fixes_without_regions_answer_as_a_fresh_search(world):
    """The memo of searches (by scan), a relabelled locator (same scans, labels moved) and answers
    without regions give exactly what a fresh locator's full answers give: a search row reads only its
    scan and the references' fingerprints."""
    refs, _, _, tests = world
    tests = tests + [RfScan(20_000.0, "wifi", {"unknown": -50.0})]
    plain = KnnLocator(refs, k=5)
    want = _answers(plain.locate_many(tests))
    memo = KnnLocator(refs, k=5, memo=True)
    for chunk in (1, 7, len(tests)):  # the first pass fills the memo, the others read it, in other groupings
        got = [r for i in range(0, len(tests), chunk) for r in memo.locate_many(tests[i : i + chunk])]
        assert _answers(got) == want
    bare = memo.locate_many(tests, regions=False)
    assert _answers(bare) == want and all(r.region is None for r in bare)
    np.testing.assert_array_equal(memo.nearest(tests)[1], plain.nearest(tests)[1])
    # labels moved 4 m east: the same neighbours, fixes 4 m east, from the shared index and memo
    moved = [dataclasses.replace(r, pos_enu=np.asarray(r.pos_enu) + [4.0, 0.0]) for r in refs]
    re = memo.relabel(moved)
    assert re is not None and re._memo is memo._memo
    fresh = KnnLocator(moved, k=5).locate_many(tests)
    assert _answers(re.locate_many(tests)) == _answers(fresh)
    for a, b in zip(re.locate_many(tests), plain.locate_many(tests)):
        if a.fix is not None:
            np.testing.assert_allclose(a.fix.pos_enu, np.asarray(b.fix.pos_enu) + [4.0, 0.0], atol=1e-9)
    # the memo holds no scan: an entry leaves with its scan
    extra = [dataclasses.replace(s) for s in tests[:5]]
    before = len(memo._memo)
    memo.nearest(extra)
    assert len(memo._memo) == before + 5
    del extra
    gc.collect()
    assert len(memo._memo) == before
    # other scans (one reference fewer, or another scan object) are not relabelled
    assert memo.relabel(moved[1:]) is None
    assert memo.relabel([dataclasses.replace(moved[0], scan=dataclasses.replace(moved[0].scan))] + moved[1:]) is None


def test_no_fix_answers(world):
    _, rmap, _, _ = world
    loc = ProbabilisticLocator(rmap)
    assert loc.locate(RfScan(1.0, "wifi", {"unknown": -50.0})).reason == "no known transmitter in the scan"
    r = loc.locate(RfScan(1.0, "wifi", {"ap1": -100.0, "ap2": -100.0}))
    assert r.fix is None and "floor" in r.reason
    r = loc.locate(RfScan(1.0, "wifi", {"ap1": -50.0}), site="another-site")
    assert r.fix is None and "site" in r.reason


def test_map_file_round_trip(world, tmp_path):
    _, rmap, _, tests = world
    p = tmp_path / "m.npz"
    rmap.save(p)
    back = RadioMap.load(p)
    assert back.transmitters == rmap.transmitters and back.site == "synth"
    np.testing.assert_array_equal(back.floors["F1"].mu, rmap.floors["F1"].mu)
    assert len(back.references) == len(rmap.references)
    a = ProbabilisticLocator(rmap).locate(tests[0]).fix.pos_enu
    b = ProbabilisticLocator(back).locate(tests[0]).fix.pos_enu
    np.testing.assert_allclose(a, b)
    # who labelled each reference survives the file (a SLAM batch leaves a walk's own labels out by it);
    # a file written before the key existed reads as unknown
    named = dataclasses.replace(rmap, references=[dataclasses.replace(r, source=f"walk-{i % 3}") for i, r in enumerate(rmap.references)])
    named.save(p)
    assert [r.source for r in RadioMap.load(p).references] == [r.source for r in named.references]
    with np.load(p) as z:
        np.savez(tmp_path / "old.npz", **{k: z[k] for k in z.files if k != "ref/source"})
    assert {r.source for r in RadioMap.load(tmp_path / "old.npz").references} == {""}
    (tmp_path / "bad.npz").write_bytes(b"not a map")
    with pytest.raises(ValueError, match=r"not a hybridloc radio map \(not a \.npz file\)"):  # not numpy's word on pickles
        RadioMap.load(tmp_path / "bad.npz")
    with pytest.raises(MissingData, match="no such radio map file"):
        RadioMap.load(tmp_path / "none.npz")
    with pytest.raises(MissingData, match="is a folder"):
        RadioMap.load(tmp_path)
    rmap.save(tmp_path / "new" / "folder" / "m.npz")  # its folder made, as the commands' --out folders are
    assert len(RadioMap.load(tmp_path / "new" / "folder" / "m.npz").references) == len(rmap.references)


def test_device_offset_is_estimated_and_removed():
    rng = np.random.default_rng(12)
    refs = synth_survey(rng, 1200)
    # a second phone model reads 6 dB low
    for ls in synth_survey(rng, 1200, t0=5000.0):
        s = ls.scan
        refs.append(LabelledScan(RfScan(s.t, "wifi", {k: v - 6.0 for k, v in s.rssi_dbm.items()}, device_model="phoneB"), ls.pos_enu, 0.5, "F1"))
    rmap = build_radio_map(refs)
    assert rmap.device_offsets["phoneB"] - rmap.device_offsets["phoneA"] == pytest.approx(-6.0, abs=1.0)


def test_aging_fades_a_moved_transmitter():
    rng = np.random.default_rng(13)
    old = synth_survey(rng, 800, t0=0.0)
    # 300 days later ap5 moved to (5, 25): new survey
    APS_new = dict(APS, ap5=(5.0, 25.0))
    new = []
    for i, p in enumerate(rng.uniform(0, 30, (800, 2))):
        r = {k: -40.0 - 30.0 * math.log10(max(1.0, math.dist(p, q))) + 2.0 * rng.standard_normal() for k, q in APS_new.items()}
        new.append(LabelledScan(RfScan(300 * 86400.0 + i, "wifi", {k: v for k, v in r.items() if v > -95}), p, 0.5, "F1"))
    rmap = build_radio_map(old + new, params=BuildParams(half_life_days=30.0))
    f = rmap.floors["F1"]
    c = int(np.flatnonzero(f.tx == rmap.tx_index["ap5"])[0])
    near_new = f.tree.query([5.0, 25.0])[1]
    near_old = f.tree.query([15.0, 15.0])[1]
    assert f.mu[near_new, c] > f.mu[near_old, c]  # the map follows the new position


def test_similarity_measures_and_learned_proximity():
    a = RfScan(0, "wifi", {"x": -50.0, "y": -70.0})
    assert cosine_shifted(a, a) == pytest.approx(1.0) and jaccard(a, a) == 1.0
    b = RfScan(0, "wifi", {"z": -60.0})
    assert cosine_shifted(a, b) == 0.0 and jaccard(a, b) == 0.0
    rng = np.random.default_rng(14)
    refs = synth_survey(rng, 600)
    model = ProximityModel.fit(refs, radius=5.0, n_pairs=4000, rng=np.random.default_rng(1))
    p_same = model.probability(RfScan(0, "wifi", rssi_at((10, 10), rng)), RfScan(1, "wifi", rssi_at((10.5, 10), rng)))
    p_far = model.probability(RfScan(0, "wifi", rssi_at((2, 2), rng)), RfScan(1, "wifi", rssi_at((28, 28), rng)))
    assert p_same > 2 * p_far
    # calibration: on fresh random pairs the mean predicted probability matches the observed rate
    fresh = synth_survey(np.random.default_rng(15), 400)
    pr, obs = [], []
    for i in range(0, 398, 2):
        a, b = fresh[i], fresh[i + 1]
        pr.append(model.probability(a.scan, b.scan))
        obs.append(np.linalg.norm(a.pos_enu - b.pos_enu) < 5.0)
    assert abs(np.mean(pr) - np.mean(obs)) < 0.1


def test_cli_build_locate_show_on_bundled_sample(tmp_path):
    import csv
    import subprocess
    import sys

    from hybridloc.samples import ILC_SITE1_F1

    traces = sorted((ILC_SITE1_F1 / "F1" / "path_data_files").glob("*.txt.gz"))
    run = lambda *a: subprocess.run([sys.executable, "-m", "hybridloc.cli", *a], capture_output=True, text=True, timeout=300)  # noqa: E731
    m = tmp_path / "f1.npz"
    r = run("map", "build", "--format", "msft", *map(str, traces[:12]), "--out", str(m))
    assert r.returncode == 0, r.stderr
    r = run("locate", "--map", str(m), "--format", "msft", str(traces[13]), "--out", str(tmp_path / "loc"))
    assert r.returncode == 0, r.stderr
    stem = traces[13].name.replace(".txt.gz", "")
    rows = list(csv.DictReader(open(tmp_path / "loc" / f"{stem}.csv")))
    assert rows and list(rows[0])[:7] == ["t", "x", "y", "floor", "sigma_x", "sigma_y", "floor_prob"]
    assert all(r["floor"] == "F1" for r in rows if r["x"])
    assert (tmp_path / "loc" / f"{stem}.geojson").is_file()
    r = run("map", "show", str(m), "--out", str(tmp_path / "m.png"))
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "m.png").read_bytes()[:4] == b"\x89PNG"
    r = run("map", "show", str(m), "--floorplan", str(ILC_SITE1_F1), "--out", str(tmp_path / "plan.png"))  # over the floor plan
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "plan.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.shared_data
def test_uji_knn_building_and_floor(shared_data):
    from hybridloc.radio.sources import labelled_from_inputs

    lab, _, _ = labelled_from_inputs("ujiindoorloc", [str(shared_data / "ujiindoorloc" / "trainingData.csv.gz")])
    rng = np.random.default_rng(3)
    idx = rng.permutation(len(lab))
    refs, test = [lab[i] for i in idx[:6000]], [lab[i] for i in idx[6000:6400]]
    out = KnnLocator(refs).locate_many([t.scan for t in test])
    building = np.mean([o.fix.floor.split("_")[0] == t.floor.split("_")[0] for o, t in zip(out, test)])
    assert building >= 0.99  # buildings are 100s of metres apart with their own access points


def _uji_user_split(shared_data, tmp_path):
    """A training file of every user but 11 (every 4th row) and a validation file of user 11's rows
    (every 10th), both in the original CSV layout."""
    import gzip

    with gzip.open(shared_data / "ujiindoorloc" / "trainingData.csv.gz", "rt") as f:
        header, *rows = f.read().splitlines()
    user = header.split(",").index("USERID")
    train, val = tmp_path / "trainingData.csv", tmp_path / "validationData.csv"
    train.write_text("\n".join([header] + [r for r in rows if r.split(",")[user] != "11"][::4]) + "\n")
    val.write_text("\n".join([header] + [r for r in rows if r.split(",")[user] == "11"][::10]) + "\n")
    return train, val


@pytest.mark.shared_data
def test_uji_standard_split_is_scored_when_a_validation_file_is_there(shared_data, tmp_path):
    """The standard protocol (all training rows as references, the validation file's rows as queries),
    here with a validation file made of one user's rows and a training file of the others', both in the
    original CSV layout: the joint vote and the plain 3-NN (:func:`evaluate_uji_split`) and the split
    votes (:func:`answer_uji_split`, with a fixed choice: the grouped search that picks it is the
    slow test below and ``eval fingerprint``)."""
    from hybridloc.radio.evaluate import answer_uji_split, evaluate_uji_split
    from hybridloc.radio.hierarchy import FloorVote, PositionVote, Representation, SplitChoice

    train, val = _uji_user_split(shared_data, tmp_path)
    v = evaluate_uji_split(str(train), str(val))
    assert v["ours"]["n"] > 300 and v["ours"]["building"] >= 0.99  # buildings are 100s of m apart, own APs
    rep = Representation("exponential", 24.0, True)
    a = answer_uji_split(str(train), str(val), SplitChoice(FloorVote(rep), PositionVote(rep), float("nan")))
    s = a["scores"].summary()
    assert a["n"] == v["ours"]["n"]
    assert s["building_hit_pct"] >= 99.0  # as above
    # a floor is 3-4 m high and 15 dB of wall: the vote is far above the 1-in-4 or 1-in-5 of a guess
    assert s["floor_hit_pct"] >= 60.0


@pytest.mark.shared_data
@pytest.mark.slow  # ~12 min on 2 cores: the whole UJIIndoorLoc evaluation; eval fingerprint runs the same code
@pytest.mark.timeout(1800)
def test_uji_standard_split_through_eval_fingerprint(shared_data, tmp_path):
    """The path that scores the real validationData.csv, once it is beside the training file, end to end
    through ``eval fingerprint`` (grouped by user, by phone, the split votes): its lines and keys."""
    import subprocess
    import sys

    train, _ = _uji_user_split(shared_data, tmp_path)
    r = subprocess.run(
        [sys.executable, "-m", "hybridloc.cli", "eval", "fingerprint", "--uji", str(train), "--ilc", ""], capture_output=True, text=True, timeout=1750
    )
    assert r.returncode == 0, r.stderr
    assert "standard split" in r.stdout and "ratio of mean error ours/plain" in r.stdout
    assert "floor vote and position vote chosen apart" in r.stdout and "with that choice: building hit" in r.stdout
    head = json.loads(r.stdout.strip().splitlines()[-1])
    keys = list(head)
    assert keys.index("uji_phone_cv_penalised_m") < keys.index("uji_lopo_split_floor_hit_pct") < keys.index("uji_split_votes_floor_hit_pct")
    assert head["uji_split_votes_building_hit_pct"] >= 99.0


def test_sorensen_neighbours_match_scipy_bray_curtis():
    """The sparse sum-of-minima form is the Bray-Curtis distance exactly (scipy's cdist as reference)."""
    from scipy import sparse
    from scipy.spatial.distance import cdist

    from hybridloc.radio.locate import sorensen_neighbours

    rng = np.random.default_rng(3)
    R = rng.random((400, 60)) * (rng.random((400, 60)) < 0.2)
    Q = rng.random((25, 60)) * (rng.random((25, 60)) < 0.3)
    Q[0] = 0.0  # a query that heard nothing known: distance 1 to everything
    D, I = sorensen_neighbours(sparse.csc_array(R), R.sum(axis=1), Q, 6)
    ref = cdist(Q[1:], R, "braycurtis")
    assert np.allclose(D[1:], np.sort(ref, axis=1)[:, :6], atol=1e-12)
    assert np.allclose(np.take_along_axis(ref, I[1:], axis=1), D[1:], atol=1e-12)
    assert np.allclose(D[0], 1.0)


def test_sorensen_neighbours_sum_minima_as_a_scatter_add_does():
    """The sums of minima come from a sparse product: bit for bit the scatter-add of the selected entries'
    minima (np.bincount, the form before it), on float32 fingerprints as the locator keeps them."""
    from scipy import sparse

    from hybridloc.radio.locate import sorensen_neighbours

    rng = np.random.default_rng(4)
    R = (rng.random((300, 80)) * (rng.random((300, 80)) < 0.3)).astype(np.float32)
    Q = (rng.random((20, 80)) * (rng.random((20, 80)) < 0.4)).astype(np.float32)
    Rc, R_sum = sparse.csc_array(R), R.sum(axis=1)
    D, I = sorensen_neighbours(Rc, R_sum, Q, 7)
    for q, d, i in zip(Q, D, I, strict=True):
        cols = np.flatnonzero(q > 0)
        rows = np.concatenate([Rc.indices[Rc.indptr[c] : Rc.indptr[c + 1]] for c in cols])
        mins = np.concatenate([np.minimum(Rc.data[Rc.indptr[c] : Rc.indptr[c + 1]], q[c]) for c in cols])
        inter = np.bincount(rows, weights=mins, minlength=len(R))
        full = 1.0 - 2.0 * inter / np.maximum(R_sum + float(q.sum()), 1e-12)
        np.testing.assert_array_equal(d, full[i])
        assert np.all(np.sort(full)[: len(d)] == d)


def test_fingerprint_matrix_writes_what_a_loop_over_the_readings_writes():
    """The cached, scattered fill (scan_readings) against the per-reading loop it replaced: ages,
    device offsets, transmitters outside tx_index, scans reused with other indices and new ids."""
    from hybridloc.radio.locate import MISSING_DBM, fingerprint_matrix

    def loop(scans, tx_index, offsets=None, max_age_s=None):
        X = np.full((len(scans), len(tx_index)), MISSING_DBM, dtype=np.float32)
        for i, s in enumerate(scans):
            off = (offsets or {}).get(s.device_model, 0.0)
            for k, v in s.rssi_dbm.items():
                if max_age_s is not None and s.age_s.get(k, 0.0) > max_age_s:
                    continue
                j = tx_index.get(k)
                if j is not None:
                    X[i, j] = v - off
        return X

    rng = np.random.default_rng(17)
    pool = [f"ap{i:03d}" for i in range(60)]
    scans = []
    for n in range(40):
        keys = list(rng.choice(pool, size=int(rng.integers(0, 25)), replace=False))
        ages = {k: float(rng.uniform(0, 12)) for k in keys if rng.random() < 0.7} if n % 3 else {}
        scans.append(RfScan(float(n), "wifi", {k: float(rng.uniform(-99, -30)) for k in keys}, age_s=ages, device_model=["a", "b", ""][n % 3]))
    for tx in (pool, pool[::2], pool[::-3] + ["never-heard"], []):
        tx_index = {t: i for i, t in enumerate(tx)}
        for offsets in (None, {"a": 3.7, "b": -1.25}):
            for age in (None, 8.0, 0.0):
                got = fingerprint_matrix(scans, tx_index, offsets, age)
                np.testing.assert_array_equal(got, loop(scans, tx_index, offsets, age))
                assert got.dtype == np.float32
    # a scan with transmitters no other scan held, after the others were cached
    late = RfScan(99.0, "wifi", {"brand-new": -50.0, "ap001": -61.5})
    idx = {"brand-new": 0, "ap001": 1, "ap002": 2}
    np.testing.assert_array_equal(fingerprint_matrix(scans + [late], idx), loop(scans + [late], idx))
    assert fingerprint_matrix([], idx).shape == (0, 3)


def test_fingerprint_matrix_across_a_new_transmitter_registry(monkeypatch):
    """Past TX_REGISTRY_MAX ids a new registry starts: scans cached under the old one are coded again
    and the matrices stay what the readings say."""
    import hybridloc.radio.locate as L

    monkeypatch.setattr(L, "TX_REGISTRY_MAX", 5)
    monkeypatch.setattr(L, "_TX", L._TxRegistry(0))
    a = RfScan(0.0, "wifi", {"x1": -50.0, "x2": -60.0, "x3": -70.0})
    b = RfScan(1.0, "wifi", {f"y{i}": -40.0 - i for i in range(8)})
    idx = {"x2": 0, "y3": 1, "x1": 2}
    first = L.fingerprint_matrix([a, b], idx)
    gen = L._TX.gen
    assert len(L._TX.codes) > 5  # the next call starts a new registry
    again = L.fingerprint_matrix([b, a], idx)
    assert L._TX.gen == gen + 1
    expect = np.full((2, 3), L.MISSING_DBM, dtype=np.float32)
    expect[0, [0, 2]] = [-60.0, -50.0]
    expect[1, 1] = -43.0
    np.testing.assert_array_equal(first, expect)
    np.testing.assert_array_equal(again, expect[::-1])


def test_route_groups_and_folds_hold_a_repeated_route_together():
    """Walks of one route (same floor, the same marks give or take 0.3 m) share a group whatever their
    direction; the same marks on another floor, or a route 3 m aside, do not. Route folds never split
    a group, and use every fold they can."""
    from hybridloc.radio.evaluate import TraceData, route_folds, route_groups

    line = np.column_stack([np.arange(0.0, 30.0, 5.0), np.zeros(6)])
    rng = np.random.default_rng(3)

    def walk(name, xy, floor="F1"):
        return TraceData(name, floor, [], np.arange(len(xy), dtype=float), xy, [])

    traces = [
        walk("a", line),
        walk("b", line[::-1] + rng.normal(0, 0.3, line.shape)),
        walk("c", line, "F2"),
        walk("d", line + [0.0, 3.0]),
        walk("e", line + [0.0, 3.2]),
        walk("f", line + [100.0, 0.0]),
        walk("g", np.zeros((0, 2))),
    ]
    g = route_groups(traces)
    assert g[0] == g[1] and g[3] == g[4]
    assert len({g[0], g[2], g[3], g[5], g[6]}) == 5
    f = route_folds(traces, 3, np.random.default_rng(0))
    assert f[0] == f[1] and f[3] == f[4] and set(f) == {0, 1, 2}


def test_knn_subset_answers_as_a_locator_built_afresh():
    """A locator sliced to some of its references answers every query exactly as one built over them:
    the same neighbours and distances to the bit, the transmitters only the others heard out of its
    index (a query reading one must not count it), stale readings left out alike; with one phone model
    left the automatic representation changes as a fresh build's does; bad indices are refused."""
    rng = np.random.default_rng(11)
    refs = synth_survey(rng, n=300)
    # another phone model 6 dB weaker, some stale readings, and a transmitter only the last refs heard
    for i in range(0, 300, 3):
        r = refs[i]
        refs[i] = LabelledScan(
            RfScan(r.scan.t, "wifi", {k: v - 6.0 for k, v in r.scan.rssi_dbm.items()}, age_s={"ap1": 20.0}, device_model="phoneB"),
            r.pos_enu,
            0.5,
            "F1",
        )
    for i in range(280, 300):
        r = refs[i]
        refs[i] = LabelledScan(RfScan(r.scan.t, "wifi", {**r.scan.rssi_dbm, "lonely": -50.0}, device_model=r.scan.device_model), r.pos_enu, 0.5, "F1")
    queries = [RfScan(1e6 + i, "wifi", {**rssi_at(p, rng), "lonely": -55.0}) for i, p in enumerate(rng.uniform(0, 30, (40, 2)))]
    keep = np.ones(300, bool)
    keep[250:] = False
    for kw in ({"k": 5, "max_age_s": 8.0}, {"k": 3, "representation": "raw", "metric": "euclidean"}):
        full = KnnLocator(refs, **kw)
        for sel in (keep, np.flatnonzero(keep)):
            sub, fresh = full.subset(sel), KnnLocator([r for r, m in zip(refs, keep) if m], **kw)
            assert "lonely" in full.tx_index and sub.tx_index == fresh.tx_index and "lonely" not in sub.tx_index
            for a, b in zip(sub._search(queries), fresh._search(queries)):
                np.testing.assert_array_equal(a, b)
            fa, fb = sub.locate_many(queries, regions=False), fresh.locate_many(queries, regions=False)
            assert [x.fix.floor for x in fa] == [x.fix.floor for x in fb]
            np.testing.assert_array_equal([x.fix.pos_enu for x in fa], [x.fix.pos_enu for x in fb])
    full = KnnLocator(refs, k=5)
    assert full.representation == "powed-rel"
    only_a = np.array([r.scan.device_model == "phoneA" for r in refs])
    sub = full.subset(only_a)
    assert sub.representation == "powed" == KnnLocator([r for r, m in zip(refs, only_a) if m], k=5).representation
    for bad in (np.array([3, 1]), np.array([-1, 2]), np.array([0, 300])):
        with pytest.raises(ValueError, match="ascending"):
            full.subset(bad)
    with pytest.raises(ValueError, match="one entry per reference"):
        full.subset(np.ones(299, bool))
    with pytest.raises(ValueError, match="reference scans"):
        full.subset(np.zeros(300, bool))


def test_knn_extended_answers_as_a_locator_built_afresh():
    """A locator with references appended answers as one built over all of them: the same index (a
    transmitter only the new references heard in its sorted place), the same neighbours, floors and
    fixes, the distances within float64 rounding of the row sums; stale readings left out alike; k
    capped by few references grows back to the k asked; a new phone model switches the automatic
    representation as a fresh build does, and the Euclidean metric builds afresh."""
    rng = np.random.default_rng(12)
    refs = synth_survey(rng, n=300)
    for i in range(200, 300):  # the added part: a transmitter nobody else heard, stale readings, floor F2
        r = refs[i]
        refs[i] = LabelledScan(
            RfScan(r.scan.t, "wifi", {**r.scan.rssi_dbm, "lonely": -50.0}, age_s={"ap2": 30.0}, device_model=r.scan.device_model),
            r.pos_enu,
            0.7,
            "F2" if i % 2 else "F1",
        )
    queries = [RfScan(1e6 + i, "wifi", {**rssi_at(p, rng), "lonely": -55.0}) for i, p in enumerate(rng.uniform(0, 30, (40, 2)))]
    queries += [r.scan for r in refs[200::10]]  # scans of the added references themselves
    for kw in ({"k": 5, "max_age_s": 8.0}, {"k": 3, "representation": "raw", "metric": "euclidean"}):
        base = KnnLocator(refs[:200], **kw)
        ext, fresh = base.extended(refs[200:]), KnnLocator(refs, **kw)
        assert "lonely" not in base.tx_index and ext.tx_index == fresh.tx_index and list(ext.tx_index) == sorted(ext.tx_index)
        (da, ia, ka), (db, ib, kb) = ext._search(queries), fresh._search(queries)
        np.testing.assert_array_equal(ia, ib)
        np.testing.assert_array_equal(ka, kb)
        np.testing.assert_allclose(da, db, rtol=1e-12, atol=1e-15)
        fa, fb = ext.locate_many(queries, regions=False), fresh.locate_many(queries, regions=False)
        assert [x.fix.floor for x in fa] == [x.fix.floor for x in fb]
        np.testing.assert_allclose([x.fix.pos_enu for x in fa], [x.fix.pos_enu for x in fb], rtol=0, atol=1e-9)
        assert base.extended([]) is base and len(base.refs) == 200  # the base is left as it was
    few = KnnLocator(refs[:2], k=5)
    assert few.k == 2 and few.extended(refs[2:10]).k == 5
    other = [LabelledScan(RfScan(r.scan.t, "wifi", r.scan.rssi_dbm, device_model="phoneB"), r.pos_enu, 0.5, "F1") for r in refs[200:220]]
    base = KnnLocator(refs[:200], k=5)
    assert base.representation == "powed" and base.extended(other).representation == "powed-rel" == KnnLocator(refs[:200] + other, k=5).representation


def test_leave_one_route_out_keeps_the_route_out_and_chooses_settings_on_other_floors():
    """Two floors of synthetic walks (path loss, 2 dB noise) with one route walked twice with the very
    same scans. Left out with its twin, the route's scans cannot find themselves in the map (every error
    above zero; with the twin in the map the exact match would pull each onto its own label). Each
    floor's setting is the best on the other floor alone, and the score is each scan answered with its
    floor's choice. A 5-NN on a map 1.5 m dense is far better than a guess at the centre (~11 m)."""
    from hybridloc.radio.evaluate import TraceData, evaluate_ilc_loro

    rng = np.random.default_rng(5)

    def walk(name, floor, y, shift_db, scans_from=None):
        wp_t = np.array([0.0, 30.0])
        wp_xy = np.array([[0.0, y], [30.0, y]])
        if scans_from is not None:  # the very same scans at the same times
            scans = scans_from.scans
        else:
            scans = [RfScan(t, "wifi", {f"{floor}{k}": v + shift_db for k, v in rssi_at((t, y), rng).items()}) for t in np.arange(0.5, 30.0, 1.0)]
        lab = [LabelledScan(s, np.array([s.t, y]), 0.5, floor) for s in scans]
        return TraceData(name, floor, lab, wp_t, wp_xy, scans)

    traces = []
    for floor, shift in (("F1", 0.0), ("F2", -3.0)):
        for j, y in enumerate(np.arange(1.0, 30.0, 1.5)):
            traces.append(walk(f"{floor}-{j}", floor, y, shift))
    traces.append(walk("F1-twin", "F1", 1.0, 0.0, scans_from=traces[0]))
    settings = ((1, 8.0), (5, 8.0), (9, 8.0))
    lo = evaluate_ilc_loro(traces, settings)
    assert lo.n_routes == len(traces) - 1  # the twin shares its route
    # the route walked twice: no scan of it found itself (with k = 1 it would be exact)
    single = {s: evaluate_ilc_loro(traces, (s,)) for s in settings}
    first = np.array(single[(1, 8.0)].held_out.errors[: len(traces[0].scans)])  # route 0 comes first
    assert np.all(np.isfinite(first)) and first.min() > 0.05
    for fl, other in (("F1", "F2"), ("F2", "F1")):
        best = min(settings, key=lambda s: single[s].floor_mean_m[other][0])
        assert lo.chosen[fl] == best
        assert lo.floor_mean_m[fl][0] == pytest.approx(single[best].floor_mean_m[fl][0])
    assert np.mean(lo.held_out.floor_hits) > 0.95
    assert np.nanmean(lo.held_out.errors) < 4.0
    assert np.isfinite(np.nanmean(lo.plain.errors))


def test_hierarchical_vote_building_then_floor_then_position():
    """Synthetic neighbour lists with known answers: the building vote overrides a nearer stray
    neighbour, the floor is voted inside that building, the position averages that floor only."""
    from hybridloc.radio.hierarchy import VoteSettings, hierarchical_vote, offset_free

    building = np.array([0, 1, 1, 1, 1])
    floor = np.array([0, 2, 2, 3, 2])
    pos = np.array([[100.0, 0.0], [0.0, 0.0], [2.0, 0.0], [50.0, 0.0], [4.0, 0.0]])
    D = np.array([[0.1, 0.2, 0.2, 0.2, 0.2]])
    I = np.array([[0, 1, 2, 3, 4]])
    bb, ff, P = hierarchical_vote(D, I, building, floor, pos, VoteSettings(k=3, k_floor=4, k_building=5))
    assert bb[0] == 1 and ff[0] == 2
    np.testing.assert_allclose(P[0], [2.0, 0.0], atol=1e-9)  # equal weights: the mean of 0, 2, 4
    # a constant phone offset vanishes in the offset-free readings
    X = np.array([[-50.0, -70.0, -110.0], [-40.0, -60.0, -110.0]])
    Y = offset_free(X)
    np.testing.assert_allclose(Y[0], Y[1], atol=1e-9)
    assert Y[0, 2] == -110.0


def _synthetic_buildings(rng, phones=(0, 1, 2, 3), per_floor=60):
    """Two buildings 300 m apart, three floors each, 6 access points per floor; every phone walks
    every floor (its own RSSI offset); a reading falls 15 dB per floor between it and the AP."""
    aps = []  # (building, floor, x, y)
    for B in range(2):
        for F in range(3):
            for _ in range(6):
                aps.append((B, F, 300.0 * B + rng.uniform(0, 40), rng.uniform(0, 20)))
    ap = np.array(aps)
    rows = []
    for p in phones:
        offset = rng.normal(0, 6)
        for B in range(2):
            for F in range(3):
                for _ in range(per_floor):
                    xy = np.array([300.0 * B + rng.uniform(0, 40), rng.uniform(0, 20)])
                    d = np.hypot(ap[:, 2] - xy[0], ap[:, 3] - xy[1]) + 1.0
                    r = -35.0 - 25.0 * np.log10(d) - 15.0 * np.abs(ap[:, 1] - F) - 80.0 * (ap[:, 0] != B) + offset + rng.normal(0, 3, len(ap))
                    rows.append((np.where(r > -95.0, r, -110.0), xy, B, F, p))
    X = np.array([r[0] for r in rows])
    pos = np.array([r[1] for r in rows])
    return X, pos, np.array([r[2] for r in rows]), np.array([r[3] for r in rows]), np.array([r[4] for r in rows])


def test_restricted_neighbour_lists_are_the_direct_search():
    """Lists cut from the other-phone lists equal a direct search over the allowed references, also
    where the cut leaves too few entries and the rows are searched again."""
    from hybridloc.radio.hierarchy import Representation, other_group_neighbours, restricted_neighbours, sorensen_knn

    rng = np.random.default_rng(5)
    X, pos, b, f, ph = _synthetic_buildings(rng, phones=(0, 1, 2, 3), per_floor=8)
    R = Representation()(X)
    D, I = other_group_neighbours(R, ph, 30)
    for excluded in ({1}, {1, 2}):
        rows = np.flatnonzero(ph == 0)
        Dk, Ik = restricted_neighbours(R, D, I, ph, rows, excluded, 12)
        ref = np.flatnonzero(~np.isin(ph, list(excluded)) & (ph != 0))
        d, i = sorensen_knn(R[ref], R[rows], 12)
        np.testing.assert_allclose(Dk, d, atol=1e-6)
    # lists cut short (14 entries, phones 1 and 2 out): rows left with fewer than 12 are searched again
    Dk, Ik = restricted_neighbours(R, D[:, :14], I[:, :14], ph, np.flatnonzero(ph == 0), {1, 2}, 12)
    ref = np.flatnonzero(ph == 3)
    d, _ = sorensen_knn(R[ref], R[ph == 0], 12)
    np.testing.assert_allclose(Dk, d, atol=1e-6)
    assert set(ph[Ik.ravel()]) == {3}


def test_split_vote_finds_known_buildings_and_floors_held_out_by_phone():
    """Synthetic buildings with known floors, every phone held out in turn (settings chosen by
    leave-one-phone-out over the others): building 100 %, floor >= 95 %, position within metres."""
    from hybridloc.radio.hierarchy import (
        Representation,
        floor_grid,
        other_group_neighbours,
        position_grid,
        restricted_neighbours,
        score,
        split_search,
        split_vote,
    )

    rng = np.random.default_rng(7)
    X, pos, b, f, ph = _synthetic_buildings(rng)
    reps = [Representation("powed", np.e, True), Representation("exponential", 24.0, True)]
    base = {r: (r(X), *other_group_neighbours(r(X), ph, 60)) for r in reps}
    bb, ff, P = np.zeros(len(X), int), np.zeros(len(X), int), np.zeros((len(X), 2))
    for p in np.unique(ph):
        tr, te = np.flatnonzero(ph != p), np.flatnonzero(ph == p)
        lists = {r: restricted_neighbours(R, D, I, ph, tr, {p}, 20) for r, (R, D, I) in base.items()}
        c = split_search(lists, tr, b, f, pos, floor_grid(reps, (5, 10), (5,), (1.0,)), position_grid(reps, (3, 5), (1.0, 2.0)))
        assert c.fitted < 20.0
        lists = {r: restricted_neighbours(R, D, I, ph, te, {p}, 20) for r, (R, D, I) in base.items()}
        bb[te], ff[te], P[te] = split_vote(lists, c.floor, c.position, b, f, pos)
    s = score(bb, ff, P, b, f, pos).summary()
    assert s["building_hit_pct"] == 100.0
    assert s["floor_hit_pct"] >= 95.0
    assert s["mean_m"] < 8.0  # a 40 x 20 m floor: a guess at its centre would be ~11 m off


def test_position_search_scores_every_candidate_as_split_vote_does():
    """split_search scores the position votes with what they share computed once; each score must be
    the one split_vote gives that candidate alone, to the bit, fallbacks included (short lists leave
    rows with no neighbour on the chosen floor in one representation's list)."""
    from hybridloc.radio.hierarchy import (
        Representation,
        _position_penalties,
        floor_grid,
        other_group_neighbours,
        position_grid,
        position_on_floor,
        restricted_neighbours,
        score,
        split_search,
        split_vote,
        vote_floors,
    )

    rng = np.random.default_rng(11)
    X, pos, b, f, ph = _synthetic_buildings(rng)
    reps = [Representation("powed", np.e, True), Representation("exponential", 24.0, True), Representation("powed", np.e, False)]
    base = {r: (r(X), *other_group_neighbours(r(X), ph, 30)) for r in reps}
    p0 = np.unique(ph)[0]
    tr = np.flatnonzero(ph != p0)
    lists = {r: restricted_neighbours(R, D, I, ph, tr, {p0}, 4) for r, (R, D, I) in base.items()}
    # every 5th query's list in the third representation holds only references of another floor
    D3, I3 = (a.copy() for a in lists[reps[2]])
    for q in range(0, len(tr), 5):
        other = tr[(b[tr] == b[tr[q]]) & (f[tr] != f[tr[q]])]
        I3[q] = other[: I3.shape[1]]
    lists[reps[2]] = (D3, I3)
    positions = position_grid(reps, (1, 3, 4), (1.0, 4.0, 16.0))
    fallbacks = 0
    for fv in floor_grid(reps, (3,), (3,), (1.0,)):
        voted = vote_floors(*lists[fv.rep], b, f, pos, fv)
        fast = _position_penalties(lists, fv, positions, voted, b, f, pos, b[tr], f[tr], pos[tr])
        for pv in positions:
            one = float(score(*split_vote(lists, fv, pv, b, f, pos, voted), b[tr], f[tr], pos[tr]).penalised_m.mean())
            assert fast[pv] == one
            # the fallback rows, against the floor list's answer computed over every row
            D, I = lists[pv.rep]
            miss = ~((I >= 0) & (b[np.maximum(I, 0)] == voted[0][:, None]) & (f[np.maximum(I, 0)] == voted[1][:, None])).any(axis=1)
            Df, If = lists[fv.rep]
            P2, found2 = position_on_floor(Df, If, *voted, b, f, pos, pv.k, pv.weight_power)
            want = np.where(found2[:, None], P2, pos[np.maximum(If[:, 0], 0)])
            assert np.array_equal(split_vote(lists, fv, pv, b, f, pos, voted)[2][miss], want[miss])
        for r in reps:
            D, I = lists[r]
            on = (I >= 0) & (b[np.maximum(I, 0)] == voted[0][:, None]) & (f[np.maximum(I, 0)] == voted[1][:, None])
            fallbacks += int((~on.any(axis=1)).sum())
    assert fallbacks > 0  # the fallback path was exercised
    c = split_search(lists, tr, b, f, pos, floor_grid(reps, (3,), (3,), (1.0,)), positions)
    assert c.position in positions

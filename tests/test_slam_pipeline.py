"""Crowd SLAM end to end on simulated worlds with known truth (hybridloc.slam.pipeline, walkgraph,
output, the slam commands), and on a few real recordings when ../shared is present."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from hybridloc.slam.pipeline import MARKS, RELATIVE, SlamConfig, run_slam
from hybridloc.slam.walkgraph import KIND_MARK, KIND_SCAN, WalkGraphConfig, walk_pieces
from hybridloc.types import StepEvent, SurveyMark, Walk, WalkEnd

SHARED_SITE = Path(__file__).resolve().parents[2] / "shared" / "data" / "msft-ilc" / "site1"


# ------------------------------------------------------------------------------------ a simulated crowd
def _sim_crowd(seed: int, n_walks: int, minutes: float, floors: int = 1, marked: int = 3, wrong_floor: int | None = None):
    """Walks through a generated building: phone-like steps with a per-walk scale error and heading
    bias (the drift SLAM removes), WiFi scans from the radio model, and survey marks every ~15 s on the
    first ``marked`` walks. Returns (world, walks, truths) with truth(t) -> (n, 2)."""
    from hybridloc.sim.building import generate_world
    from hybridloc.sim.radio import make_radio_model, simulate_radio
    from hybridloc.sim.walker import simulate_walk

    rng = np.random.default_rng(seed)
    world = generate_world(rng, floors=floors, seed=seed)
    model = make_radio_model(world, rng)
    walks, truths = [], []
    for i in range(n_walks):
        sw = simulate_walk(world, rng, minutes, walker=i, t0=1.7e9 + 1000.0 * i)
        radio = simulate_radio(model, sw, rng)
        scale = float(rng.choice([0.85, 1.15]))
        bias = float(rng.choice([-1.0, 1.0])) * math.radians(8.0)
        steps = []
        for s in sw.steps:
            if s.dz != 0.0:
                continue
            steps.append(
                StepEvent(
                    s.t,
                    s.length * scale * float(rng.normal(1.0, 0.05)),
                    s.heading + bias + float(rng.normal(0.0, math.radians(2.0))),
                    0.05,
                    math.radians(10.0),
                    sigma_heading_change=math.radians(2.0),
                )
            )
        fl = world.floor_name(int(sw.start[2]))
        marks = ()
        if i < marked:
            ts = np.arange(sw.t0 + 5.0, sw.t1, 15.0)
            pos, f = sw.position_at(ts)
            marks = tuple(SurveyMark(float(t), float(p[0]), float(p[1]), world.floor_name(int(ff))) for t, p, ff in zip(ts, pos, f))
        floor_label = fl if wrong_floor != i else world.floor_name((int(sw.start[2]) + 1) % floors)
        walks.append(
            Walk(
                "sim",
                f"w{i:02d}",
                None,
                sw.t0,
                sw.t1,
                "SIM PHONE",
                (floor_label,),
                tuple(sorted(steps, key=lambda s: s.t)),
                tuple(radio.wifi),
                marks,
                WalkEnd.MARKER,
            )
        )
        truths.append(sw)
    return world, walks, truths


def _raw_error(piece, truth) -> float:
    """Median error of the dead-reckoned walk started at its true start (no correction)."""
    pos, _ = truth.position_at(piece.t)
    return float(np.median(np.linalg.norm(piece.q - piece.q[0] + pos[0] - pos, axis=1)))


# ------------------------------------------------------------------------------------ walk graph
def test_walk_pieces_nodes_and_odometry():
    _, walks, _ = _sim_crowd(3, 1, 1.0, marked=1)
    w = walks[0]
    (pc,) = walk_pieces(w, 0, WalkGraphConfig())
    assert pc.floor == w.floors[0]
    assert np.all(np.diff(pc.t) >= 0)
    assert (pc.kind == KIND_SCAN).sum() == sum(1 for s in w.scans if w.t_start - 1 <= s.t)
    assert (pc.kind == KIND_MARK).sum() == len(w.marks)
    # odometry composes back to the dead-reckoned walk: sum of edges = last - first node position
    D, S = pc.odometry()
    np.testing.assert_allclose(D.sum(axis=0), pc.q[-1] - pc.q[0], atol=1e-9)
    # the dead-reckoned end after all steps (exact sum of l * u(psi))
    end = sum(np.array([s.length * math.cos(s.heading), s.length * math.sin(s.heading)]) for s in w.steps)
    np.testing.assert_allclose(pc.step_q[-1], end, atol=1e-9)
    # covariances are symmetric positive definite, and the white covariance grows along the walk
    assert np.all(np.linalg.eigvalsh(S) > 0)
    assert np.all(np.diff(pc.C[:, 0, 0] + pc.C[:, 1, 1]) >= -1e-12)


def test_walk_pieces_split_at_floor_change():
    steps = [StepEvent(float(t), 0.7, 0.0, 0.05, 0.1, floor_change=1 if t == 10 else 0) for t in range(1, 21)]
    w = Walk("s", "d", None, 0.0, 21.0, floors=("F1", "F2"), steps=tuple(steps))
    pcs = walk_pieces(w, 0)
    assert [p.floor for p in pcs] == ["F1", "F2"]
    assert pcs[0].step_t[-1] < pcs[1].step_t[1]


# ------------------------------------------------------------------------------------ the pipeline
@pytest.fixture(scope="module")
def crowd():
    return _sim_crowd(11, 10, 2.0, marked=3)


def test_marks_correct_the_drift_and_loops_are_audited(crowd):
    """Walks with marks every 15 s: between the marks the corrected track follows the truth far better
    than the dead-reckoned walk started at its TRUE start (each walk carries a scale error and a
    heading bias, which only the per-segment nuisances can take out). Every loop candidate is kept in
    the audit trail with its weight; only anchored walks are labelled."""
    world, walks, truths = crowd
    res = run_slam(walks, world.plan, config=SlamConfig(em_rounds=1))
    (fs,) = res.floors.values()
    assert [fs.status[k] for k in range(3)] == [MARKS] * 3
    for k in range(3):
        pc = fs.pieces[k]
        between = pc.mark < 0
        pos, _ = truths[pc.walk].position_at(pc.t[between])
        corrected = np.median(np.linalg.norm(fs.pos[pc.nodes[between]] - pos, axis=1))
        # marks (0.5 m) 15 s apart leave ~ the PDR's white error over half a segment: well under a metre
        assert corrected < 1.0
        assert corrected < _raw_error(pc, truths[pc.walk])
        m = np.flatnonzero(pc.mark >= 0)
        pos, _ = truths[pc.walk].position_at(pc.t[m])
        assert np.median(np.linalg.norm(fs.pos[pc.nodes[m]] - pos, axis=1)) < 1.0
    # the audit trail: every candidate, accepted ones with a robust weight in [0, 1]
    assert res.loops
    assert all(0.0 <= lp.weight <= 1.0 for lp in res.loops)
    assert all(lp.reason for lp in res.loops if not lp.accepted)
    names = {pc.name for pc in fs.pieces}
    assert all(lp.walk_a in names and lp.walk_b in names and lp.walk_a != lp.walk_b for lp in res.loops)
    # labels: only anchored walks, each with a finite positive sigma
    assert res.labels and all(ls.sigma > 0 and math.isfinite(ls.sigma) for ls in res.labels)
    anchored_walks = {fs.pieces[k].walk for k in range(len(fs.pieces)) if fs.status[k] != RELATIVE}
    assert set(res.label_walk) <= anchored_walks


def test_no_anchor_no_plan_stays_relative(crowd):
    """Without marks, map or plan nothing can be placed: every walk is relative only and no scan is labelled."""
    _, walks, _ = crowd
    bare = [Walk(w.site, w.device, None, w.t_start, w.t_end, w.device_model, w.floors, w.steps, w.scans, (), w.end) for w in walks]
    res = run_slam(bare, None, config=SlamConfig(em_rounds=1))
    for fs in res.floors.values():
        assert set(fs.status) == {RELATIVE}
    assert res.labels == []


def test_walk_on_the_wrong_floor_does_not_bend_the_others():
    """A walk recorded on floor 0 but labelled floor 1 meets no consistent loop on floor 1 and cannot
    drag the walks of floor 0; floor 0's marked walks keep their marks."""
    world, walks, truths = _sim_crowd(5, 8, 1.5, floors=2, marked=4, wrong_floor=5)
    res = run_slam(walks, world.plan, config=SlamConfig(em_rounds=0))
    for fs in res.floors.values():
        for k, pc in enumerate(fs.pieces):
            if fs.status[k] == MARKS:
                m = np.flatnonzero(pc.mark >= 0)
                pos, _ = truths[pc.walk].position_at(pc.t[m])
                assert np.median(np.linalg.norm(fs.pos[pc.nodes[m]] - pos, axis=1)) < 1.0


# ------------------------------------------------------------------------------------ commands on real files
@pytest.fixture(scope="module")
def small_site(tmp_path_factory, request) -> Path:
    """A site folder of the real site1 F1 plan and 8 of its recordings (links, nothing copied)."""
    from tests.conftest import SHARED_DATA

    src = SHARED_DATA / "msft-ilc" / "site1" / "F1"
    if not src.is_dir():
        pytest.skip(f"real data folder {src} is absent")
    site = tmp_path_factory.mktemp("site") / "site1"
    fl = site / "F1"
    (fl / "path_data_files").mkdir(parents=True)
    for name in ("geojson_map.json", "floor_info.json"):
        (fl / name).symlink_to(src / name)
    for p in sorted((src / "path_data_files").iterdir())[:8]:
        (fl / "path_data_files" / p.name).symlink_to(p)
    return site


def test_slam_run_and_show_write_their_files(small_site, tmp_path):
    import csv

    from hybridloc.cli import main

    out = tmp_path / "slam"
    assert main(["slam", "run", str(small_site), "--out", str(out), "--workers", "1"]) == 0
    for name in ("tracks.csv", "tracks.geojson", "loops.csv", "raw.csv", "crowdmap_wifi.npz"):
        assert (out / name).is_file(), name
    with open(out / "tracks.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert rows and set(rows[0]) == {"walk", "t", "x", "y", "floor", "sigma_x", "sigma_y", "anchored"}
    # with marks kept every walk is anchored by its own marks
    assert {r["anchored"] for r in rows} == {"marks"}
    with open(out / "loops.csv") as fh:
        header = next(csv.reader(fh))
    assert header[:7] == ["walk_a", "t_a", "walk_b", "t_b", "similarity", "weight", "accepted"]
    from hybridloc.radio.radiomap import RadioMap

    rm = RadioMap.load(out / "crowdmap_wifi.npz")
    assert "F1" in rm.floors and rm.references
    png = tmp_path / "f1.png"
    assert main(["slam", "show", str(out), "--floor", "F1", "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000
    # marks stripped, no map: nothing can tie 8 short walks to the site frame but the plan, and what the
    # plan cannot place stays relative (never an absolute label)
    out2 = tmp_path / "slam-strip"
    assert main(["slam", "run", str(small_site), "--out", str(out2), "--marks", "strip", "--workers", "1"]) == 0
    with open(out2 / "tracks.csv") as fh:
        kinds = {r["anchored"] for r in csv.DictReader(fh)}
    assert "marks" not in kinds and kinds <= {"plan", "relative", "loops", "map"}


def test_slam_show_refuses_a_missing_floor(small_site, tmp_path):
    from hybridloc.cli import main

    assert main(["slam", "show", str(tmp_path), "--floor", "F1", "--out", str(tmp_path / "x.png")]) == 2


def test_eval_slam_prints_its_figures(small_site, capsys):
    """The evaluation's contract: per floor and overall figures, last line one JSON object with the
    issue's keys; the stripped walks reach the graph without marks."""
    import json

    from hybridloc.cli import main

    assert main(["eval", "slam", str(small_site), "--survey-fraction", "0.5", "--workers", "1"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    fig = json.loads(out[-1])
    for key in (
        "crowd_median_m",
        "coverage",
        "loop_precision_5m",
        "fused_mean_survey_only_m",
        "fused_mean_crowd_m",
        "fused_mean_all_marks_m",
        "seconds",
    ):
        assert key in fig
    assert fig["walks_survey"] == 2 and fig["walks_crowd"] == 2 and fig["walks_test"] == 4
    assert 0.0 <= fig["coverage"] <= 1.0
    assert any("floor F1" in line for line in out)


def test_eval_slam_refuses_bad_fractions(small_site):
    from hybridloc.cli import main

    assert main(["eval", "slam", str(small_site), "--survey-fraction", "1.5"]) == 2

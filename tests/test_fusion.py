"""Fusion filters: the particle filter with the map, the walk prior, the batch runner."""

import math

import numpy as np
import pytest
import shapely

from hybridloc.fusion import KourogiFusion, LocalFusion, ParticleConfig, ParticleFusion, WalkPrior, run_fusion
from hybridloc.types import AbsoluteFix, Floor, FloorPlan, StepEvent


def _walk(n, heading, length=0.7, t0=0.0, dt=0.5):
    return [StepEvent(t0 + dt * (i + 1), length, heading, 0.05, math.radians(2), 0.0, math.radians(1)) for i in range(n)]


def _corridor_plan(length=60.0, width=2.0) -> FloorPlan:
    """One floor: a straight corridor along +x, ``width`` m wide, walls along both sides."""
    poly = shapely.box(-2.0, -width / 2, length, width / 2)
    walls = [
        [[-2.0, -width / 2], [length, -width / 2]],
        [[-2.0, width / 2], [length, width / 2]],
        [[-2.0, -width / 2], [-2.0, width / 2]],
        [[length, -width / 2], [length, width / 2]],
    ]
    mp = shapely.MultiPolygon([poly])
    return FloorPlan("test", (Floor("F1", 0, 0.0, mp, mp, np.array(walls)),))


def test_walk_prior_from_points_and_plan():
    plan = _corridor_plan()
    walked = np.column_stack([np.linspace(0, 30, 200), np.zeros(200)])  # people walked the first 30 m
    pr = WalkPrior.from_points({"F1": walked}, plan, eps=0.05)
    v = pr.at("F1", np.array([[10.0, 0.0], [50.0, 0.0], [10.0, 5.0]]))
    assert v[0] == pytest.approx(1.0, abs=0.02)  # well walked
    assert v[1] == pytest.approx(0.05, abs=1e-3)  # walkable, never walked: the floor eps
    assert v[2] == 0.0  # outside the plan
    hit = pr.crosses_wall("F1", np.array([[5.0, 0.0], [5.0, 0.0]]), np.array([[5.0, 2.0], [6.0, 0.5]]))
    assert hit.tolist() == [True, False]
    assert pr.at("nofloor", np.zeros((2, 2))).tolist() == [1.0, 1.0]  # unknown floor: no constraint
    with pytest.raises(ValueError):
        WalkPrior.from_points({"F1": walked}, plan, eps=2.0)


def test_particle_filter_keeps_a_biased_walk_inside_the_corridor():
    """The PDR heading is 10 deg off: after 40 m dead reckoning alone is 40 sin 10 = 6.9 m out of a 2 m
    wide corridor; the particles that left it died at the walls, so the estimate stays inside and
    its along-track position keeps the step lengths (within the step noise, a few % of 40 m)."""
    plan = _corridor_plan(length=80.0)
    prior = WalkPrior.from_points({}, plan)
    steps = _walk(57, math.radians(10.0))  # 57 x 0.7 = 39.9 m
    kf = LocalFusion(init=(0.0, 0.0, 0.3), floor="F1", heading_bias=(0.0, math.radians(20)))
    # step scale known to 3 %: walls tell nothing about it (the cloud keeps the scale of its survivors)
    pf = ParticleFusion(
        prior, ParticleConfig(n_particles=500, sigma_scale0=0.03), init=(0.0, 0.0, 0.3), floor="F1", heading_bias=(0.0, math.radians(20))
    )
    for st in steps:
        e_kf = kf.predict(st)
        e_pf = pf.predict(st)
        # each living particle carries the prior of its own place, through every resampling (the
        # step's likelihood divides by it: a stale 0 from another particle would weigh it by 1e12)
        alive = pf.w > 0
        assert np.array_equal(pf._logpi[alive], np.log(prior.at("F1", pf.p[alive])))
    assert abs(e_kf.pos[1]) > 5.0
    assert abs(e_pf.pos[1]) < 1.0 and abs(e_pf.pos[0] - 39.9) < 3 * 0.03 * 39.9 + 0.5
    assert np.all(np.abs(pf.p[pf.w > 0, 1]) <= 1.0)  # no living particle beyond the walls (the dead go at the next resampling)
    assert np.isfinite(e_pf.cov).all() and np.linalg.eigvalsh(e_pf.cov).min() > 0
    # the corridor taught the filter the heading bias: its particles' mean bias is about -10 deg
    assert abs(float(pf.w @ pf.b) + math.radians(10.0)) < math.radians(6.0)


def test_particle_filter_fixes_gate_reinit_and_reproducibility():
    rng = np.random.default_rng(1)
    runs = []
    for _ in range(2):
        pf = ParticleFusion(None, ParticleConfig(n_particles=400, seed=3))
        ok, e = pf.correct(AbsoluteFix(0.0, [5.0, 5.0], np.eye(2) * 4.0, "wifi", "F1", 0.9))
        assert ok and e.kind == "init" and pf.floor == "F1"
        true = np.array([5.0, 5.0])
        for k in range(20):
            for st in _walk(4, 0.0, t0=2.0 * k):
                pf.predict(st)
                true = true + [0.7, 0.0]
            pf.correct(AbsoluteFix(2.0 * k + 2.0, true + rng.normal(0, 1.0, 2), np.eye(2), "wifi", "F1", 0.9))
        runs.append(pf.estimate("x").pos)
        # converged: within a few fix sigmas of the truth after 20 fixes
        assert np.linalg.norm(pf.estimate("x").pos - true) < 2.0
        n_rej = pf.n_rejected  # the 95 % gate also turns away ~5 % of good fixes
        ok, _ = pf.correct(AbsoluteFix(41.0, true + [60.0, 0.0], np.eye(2), "gps", "F1"))  # multipath
        assert not ok and pf.n_rejected == n_rej + 1
        for i in range(5):  # the world insists: lost, restart there
            ok, e = pf.correct(AbsoluteFix(42.0 + i, [200.0, 50.0], np.eye(2), "wifi", "F2", 0.95))
        assert ok and np.linalg.norm(e.pos - [200, 50]) < 1.0 and pf.floor == "F2"
        rng = np.random.default_rng(1)
    # the same seed and inputs give the same answer
    assert np.allclose(runs[0], runs[1])


def test_late_fix_is_compared_with_the_position_at_its_scan_time():
    """A fix for a scan 10 steps ago that agrees with where we were then must barely move us."""
    for make in (
        lambda: LocalFusion(init=(0.0, 0.0, 2.0)),
        lambda: ParticleFusion(None, init=(0.0, 0.0, 2.0)),
        lambda: KourogiFusion(init=(0.0, 0.0, 2.0)),
    ):
        f = make()
        for st in _walk(20, 0.0):
            f.predict(st)
        before = f.estimate("x").pos.copy()
        ok, e = f.correct(AbsoluteFix(5.0, [7.0, 0.0], np.eye(2) * 0.25, "wifi"))  # t=5 s: 10 steps, 7 m
        # where we were then (7 m) plus the 10 steps since (7 m): 14 m; an estimate compared with the
        # present position instead would have been dragged back towards 7 m
        assert ok and np.linalg.norm(e.pos - [14.0, 0.0]) < 0.7 and np.linalg.norm(e.pos - before) < 1.5


def test_run_fusion_reproduces_arrival_order():
    steps = _walk(30, 0.0)
    fixes = [AbsoluteFix(3.0 * k, [2.1 * k, 0.3], np.eye(2), "wifi") for k in range(1, 5)]
    # fixes arriving right after their scan (by time) or at given step counts: same result when they agree
    by_time = run_fusion(LocalFusion(init=(0.0, 0.0, 1.0)), steps, fixes)
    arrivals = [sum(1 for s in steps if s.t < f.t) for f in fixes]
    by_count = run_fusion(LocalFusion(init=(0.0, 0.0, 1.0)), steps, fixes, arrivals)
    assert len(by_time) == len(by_count) == 30 + 4
    assert all(np.allclose(a.pos, b.pos) and a.kind == b.kind for a, b in zip(by_time, by_count))
    with pytest.raises(ValueError):
        run_fusion(LocalFusion(), steps, fixes, arrivals[:2])


def test_measurement_jacobians_match_finite_differences():
    from hybridloc.fusion.measurements import CorridorHeading, PositionFix, StepDisplacement

    rng = np.random.default_rng(5)
    for _ in range(20):
        x = np.array([*rng.normal(0, 10, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0.7, 1.3)])
        for model in (PositionFix(np.eye(2)), StepDisplacement(rng.normal(0, 5, 2), np.eye(2)), CorridorHeading(rng.uniform(-3, 3), 0.1)):
            H = model.jacobian(x)
            num = np.zeros_like(H)
            for k in range(4):
                dx = np.zeros(4)
                dx[k] = 1e-6
                num[:, k] = (model.evaluate(x + dx) - model.evaluate(x - dx)) / 2e-6
            assert np.allclose(H, num, atol=1e-6)


def test_gps_differential_mode_teaches_heading_bias_and_scale_without_moving_the_position():
    """Kourogi eq 17: displacements between GPS fix pairs 5 s apart (random error 1 m per fix, the
    common bias cancelled) show the walker's true direction and speed. The PDR says heading 0 and
    0.7 m steps; the truth walks at +15 deg with 0.77 m steps. The filters learn both; the position
    itself is not what the measurement is about (a Kalman H with zeros there)."""
    from hybridloc.types import DisplacementFix

    rng = np.random.default_rng(2)
    bias, scale = math.radians(15.0), 1.1
    u = np.array([math.cos(bias), math.sin(bias)])
    for make in (lambda: LocalFusion(init=(0.0, 0.0, 0.5)), lambda: ParticleFusion(None, ParticleConfig(n_particles=2000), init=(0.0, 0.0, 0.5))):
        f = make()
        steps = _walk(200, 0.0)  # a step every 0.5 s
        n_ok = 0
        for i, st in enumerate(steps):
            f.predict(st)
            if i % 10 == 9 and i >= 19:  # every 5 s: the displacement over the last 5 s (10 steps)
                z = 10 * 0.7 * scale * u + rng.normal(0, 1.0, 2) - rng.normal(0, 1.0, 2)
                ok, e = f.correct(DisplacementFix(st.t - 5.0, st.t, z, np.eye(2) * 2.0))
                n_ok += ok
        assert n_ok >= 15  # the 95 % gate turns away few good ones
        if isinstance(f, LocalFusion):
            b, s, sb, ss = f.x[2], f.x[3], math.sqrt(f.P[2, 2]), math.sqrt(f.P[3, 3])
        else:
            b, s = float(f.w @ f.b), float(f.w @ f.s)
            sb, ss = math.sqrt(float(f.w @ (f.b - b) ** 2)), math.sqrt(float(f.w @ (f.s - s) ** 2))
        # consistent with its own spread (3 sigma, plus the particles' sampling floor) and informative:
        # ~17 windows of 7.7 m measured to sqrt(2) m per axis bound both to about
        # sqrt(2) / 7.7 / sqrt(17) = 0.045 (2.6 deg for the bias), well below the priors (30 deg, 0.15)
        assert abs(b - bias) < 3 * sb + math.radians(1.0) and sb < math.radians(4.5)
        assert abs(s - scale) < 3 * ss + 0.01 and ss < 0.065
    bad = DisplacementFix(1000.0, 1001.0, [1.0, 0.0], np.eye(2))  # a window the filter never saw
    assert f.correct(bad)[0] is False
    with pytest.raises(ValueError):
        DisplacementFix(2.0, 1.0, [1.0, 0.0], np.eye(2))


def test_fixes_csv_and_the_gps_differencer(tmp_path):
    from hybridloc.fusion import GpsDifferencer
    from hybridloc.io.fixes import read_fixes_csv
    from hybridloc.types import FixSource

    p = tmp_path / "f.csv"
    p.write_text(
        "t,x,y,floor,sigma,source,sigma_random\n"
        "2.0,11.0,0.0,F1,3.0,gps,1.5\n"
        "1.0,10.0,0.0,F1,3.0,gps,1.5\n"  # out of order: sorted
        "3.0,nan,0.0,F1,3.0,gps,1.5\n"  # bad: skipped and reported
        "4.0,5.0,5.0,F1,0.4,rfid,\n"
        "20.0,30.0,0.0,,3.0,gps,1.0\n"
    )
    rows, rep = read_fixes_csv(p)
    assert [f.t for f, _ in rows] == [1.0, 2.0, 4.0, 20.0] and not rep.ok
    assert rows[2][0].source is FixSource.RFID and rows[2][1] is None and rows[3][0].floor is None
    d = GpsDifferencer(min_dt=0.5, max_dt=10.0)
    assert d.push(*rows[0], accepted=True) is None  # the first of a pair
    disp = d.push(*rows[1], accepted=True)
    # the difference of the two positions, with only the random parts' variance (1.5^2 + 1.5^2)
    assert np.allclose(disp.delta_enu, [1.0, 0.0]) and np.allclose(disp.cov, np.eye(2) * 4.5) and (disp.t0, disp.t1) == (1.0, 2.0)
    assert d.push(*rows[2], accepted=True) is None  # RFID: not a GPS pair
    assert d.push(*rows[3], accepted=True) is None  # 18 s after the last GPS fix: too far apart
    assert d.push(rows[3][0], 1.0, accepted=False) is None  # a rejected (multipath) fix never pairs


def test_kourogi_filter_tracks_steps_and_its_uncertainty_grows_as_dead_reckoning():
    """Eq 9 on a straight walk: the velocity becomes l / T, the position the sum of the steps, and the
    position covariance grows like dead reckoning's (eqs 11-14): the clone keeps the previous
    position's covariance from being counted twice, which would halve it at every step. The
    constant-velocity projection is a second, weaker estimate of each displacement, so the growth is
    at least half of dead reckoning's (two independent estimates at best halve a variance) and at
    most all of it."""
    steps = _walk(60, math.radians(30.0))  # 0.7 m every 0.5 s
    f = KourogiFusion(init=(0.0, 0.0, 0.5))
    dr = np.eye(2) * 0.25
    traces = []
    for st in steps:
        e = f.predict(st)
        dr = st.propagate_position_covariance(dr)
        traces.append(np.trace(e.cov))
    d = np.array([math.cos(math.radians(30)), math.sin(math.radians(30))])
    assert np.allclose(e.pos, 60 * 0.7 * d, atol=0.05)
    assert np.allclose(f.x[2:], 1.4 * d, atol=0.05)  # l / T
    assert np.all(np.diff(traces) > 0)
    grown, dr_grown = traces[-1] - 0.5, np.trace(dr) - 0.5
    assert 0.5 * dr_grown <= grown <= 1.0001 * dr_grown
    assert np.linalg.eigvalsh(f.P).min() > 0


def test_kourogi_filter_fix_pause_and_gps_velocity():
    f = KourogiFusion(init=(0.0, 0.0, 3.0))
    for st in _walk(10, 0.0):
        f.predict(st)
    # eq 16: a fix moves the position (through the shared gated correct), infinite variance on velocity
    ok, e = f.correct(AbsoluteFix(5.0, [8.0, 1.0], np.eye(2) * 0.25, "wifi"))
    assert ok and e.pos[0] > 7.0 and e.pos[1] > 0.5
    ok, _ = f.correct(AbsoluteFix(5.0, [60.0, 40.0], np.eye(2) * 0.25, "wifi"))
    assert not ok  # outside the 95 % region of the dead-reckoned estimate (sec. 3.3)
    # eq 10: a pause longer than still_after is an observation of no movement: the 1.4 m/s along x
    # of the walk before it is gone when the walker sets off along y (a step period after the pause)
    later = _walk(1, math.pi / 2, t0=5.0 + 10.0)[0]
    f.predict(later)
    # (the projection through the 10 s pause leaves the velocity prior loose - q dt ~ 10 (m/s)^2 - so
    # the step's own l / T dominates; 25 % allows the pull of that prior towards the zero it observed)
    assert abs(f.x[2]) < 0.3 and f.x[3] == pytest.approx(0.7 / f.cfg.step_period, rel=0.25)
    # every observation went through the one core, counted by kind: 11 steps, 1 pause, 1 fix in, 1 out
    assert f.stats.accepted == {"step": 11, "still": 1, "position": 1} and f.stats.rejected == {"position": 1}
    # eqs 17-18: two GPS positions 1 s apart give the present velocity
    from hybridloc.types import DisplacementFix

    t1 = later.t
    v_before = f.x[2:].copy()
    v_gps = np.array([0.3, 1.0])
    ok, _ = f.correct(DisplacementFix(t1 - 1.0, t1, v_gps, np.eye(2) * 0.04, "gps"))
    # along the walk (now y) the step velocity is uncertain (sigma_v): the GPS pulls it a good part of
    # the way; across it eq 15 gives (sigma_v cos theta)^2 ~ 0 (plus the floor): it moves a little
    assert ok and abs(f.x[3] - v_gps[1]) < 0.7 * abs(v_before[1] - v_gps[1])
    assert 0.0 < f.x[2] - v_before[0] < 0.5 * (v_gps[0] - v_before[0])
    ok, _ = f.correct(DisplacementFix(t1 - 1.0, t1, [0.0, -3.0], np.eye(2) * 0.04, "gps"))
    assert not ok  # a velocity the steps deny: outside the gate
    ok, _ = f.correct(DisplacementFix(t1 - 20.0, t1 - 10.0, [0.0, 5.0], np.eye(2) * 0.01, "gps"))
    assert not ok  # not the present velocity any more


def test_corridor_heading_removes_a_heading_bias_along_the_grid_and_leaves_diagonals_alone():
    """Heuristic drift elimination: a walk straight along the grid (true heading 0) whose PDR heading
    reads 8 deg teaches the filter a bias of -8 deg (within 2: the pseudo-measurement's 10 deg over
    ~35 straight steps averages to ~2 deg, and the random walk adds 0.5 deg per step); the track then
    stays on the corridor. A walk at 45 deg (a diagonal, beyond the 20 deg capture) is left alone."""
    bias = math.radians(8.0)
    steps = _walk(40, bias)
    f = LocalFusion(init=(0.0, 0.0, 1.0), floor="F1", corridor_axes={"F1": 0.0})
    plain = LocalFusion(init=(0.0, 0.0, 1.0), floor="F1")
    for st in steps:
        f.predict(st)
        plain.predict(st)
    assert f.n_corridor >= 30
    assert math.degrees(f.x[2]) == pytest.approx(-8.0, abs=2.0)
    assert plain.x[2] == 0.0
    assert abs(f.x[1]) < 0.5 * abs(plain.x[1])  # the sideways drift of 40 x 0.7 m x sin(8 deg) = 3.9 m, mostly gone
    diag = LocalFusion(init=(0.0, 0.0, 1.0), floor="F1", corridor_axes={"F1": 0.0})
    for st in _walk(40, math.radians(45.0)):
        diag.predict(st)
    assert diag.n_corridor == 0 and diag.x[2] == 0.0
    # turning: no straight stretch, no correction
    turn = LocalFusion(init=(0.0, 0.0, 1.0), floor="F1", corridor_axes={"F1": 0.0})
    for i, st in enumerate(_walk(40, 0.0)):
        turn.predict(StepEvent(st.t, st.length, math.radians(5.0 * (i % 2)) + math.radians(3.0 * i), st.sigma_length, st.sigma_heading))
    assert turn.n_corridor <= 2


def test_particle_filter_corridor_heading_pulls_the_bias_cloud_to_the_grid():
    """The particle filter's drift elimination: a straight walk along the grid whose PDR heading reads
    8 deg moves the cloud's heading bias to -8 deg (each straight step weighs the particles by a
    10 deg Gaussian of their offset from the grid; allow 3 deg for the bias random walk and the
    sampling); a diagonal walk is never weighed, whatever single particles' biases would align."""
    steps = _walk(40, math.radians(8.0))
    f = ParticleFusion(init=(0.0, 0.0, 1.0), floor="F1", corridor_axes={"F1": 0.0})
    for st in steps:
        f.predict(st)
    assert f.n_corridor >= 30
    assert math.degrees(float(f.w @ f.b)) == pytest.approx(-8.0, abs=3.0)
    diag = ParticleFusion(init=(0.0, 0.0, 1.0), floor="F1", corridor_axes={"F1": 0.0})
    for st in _walk(40, math.radians(45.0)):
        diag.predict(st)
    assert diag.n_corridor == 0


def test_walk_prior_learns_an_entrance_from_walks_that_come_in_from_outdoors():
    """A closed 20 x 10 m building on the ground floor. Nobody walked outdoors: the street is
    impossible and every outer wall holds. Walks that came in from the street along y = 5 through the
    west wall: that path outdoors is walkable, the west wall is open where they crossed it and
    nowhere else, and the rest of the outdoors stays impossible."""
    box = shapely.MultiPolygon([shapely.box(0.0, 0.0, 20.0, 10.0)])
    c = np.array([[0, 0], [20, 0], [20, 10], [0, 10], [0, 0]], float)
    plan = FloorPlan("b", (Floor("F1", 0, 0.0, box, box, np.stack([c[:-1], c[1:]], axis=1)),))
    inside = np.column_stack([np.linspace(1, 19, 100), np.full(100, 5.0)])
    closed = WalkPrior.from_points({"F1": inside}, plan)
    street = np.column_stack([np.linspace(-8, 0, 40), np.full(40, 5.0)])
    learned = WalkPrior.from_points({"F1": np.vstack([inside, street])}, plan)
    probe = np.array([[-4.0, 5.0], [-4.0, 1.0], [30.0, 5.0]])  # on the street path, beside it, far away
    assert closed.at("F1", probe).tolist() == [0.0, 0.0, 0.0]
    v = learned.at("F1", probe)
    assert v[0] > 0.5 and v[1] == 0.0 and v[2] == 0.0
    moves_from, moves_to = np.array([[-2.0, 5.3], [-2.0, 0.6], [22.0, 5.3]]), np.array([[2.0, 5.3], [2.0, 0.6], [18.0, 5.3]])
    assert closed.crosses_wall("F1", moves_from, moves_to).tolist() == [True, True, True]
    assert learned.crosses_wall("F1", moves_from, moves_to).tolist() == [False, True, True]


def test_floor_switches_on_a_majority_of_the_fixs_neighbours():
    """The floor after a fix: the fix's when none is known; another floor once a clear majority of
    the fix's neighbours (3 of 5: 0.6) say so, not on a split vote; both filters alike."""
    from hybridloc.fusion.kalman import floor_after_fix

    def fix(floor, prob):
        return AbsoluteFix(0.0, [0.0, 0.0], np.eye(2), "wifi", floor, prob)

    for cfg in (LocalFusion().cfg, ParticleFusion().cfg):
        assert floor_after_fix(None, fix("F2", 0.4), cfg.floor_switch) == "F2"
        assert floor_after_fix("F1", fix("F2", 0.6), cfg.floor_switch) == "F2"
        assert floor_after_fix("F1", fix("F2", 0.5), cfg.floor_switch) == "F1"
        assert floor_after_fix("F1", fix(None, 1.0), cfg.floor_switch) == "F1"


def test_a_cloud_behind_a_wall_is_redrawn_around_fixes_beyond_it():
    """Two rooms split by a wall at y = 5, the door far off at x = 18-20. The cloud starts in the
    south room, the walker stands in the north one and the fixes say so (2 m sigma, 4 m away: each
    accepted by the gate, each outside the cloud's 50 % region and beyond the wall). Without resetting,
    no particle can be where the fixes are and the estimate stays south of the wall; with it, a share
    is redrawn around the fixes and the estimate crosses."""
    box = shapely.MultiPolygon([shapely.box(0.0, 0.0, 20.0, 10.0)])
    c = np.array([[0, 0], [20, 0], [20, 10], [0, 10], [0, 0]], float)
    walls = np.vstack([np.stack([c[:-1], c[1:]], axis=1), [[[0.0, 5.0], [18.0, 5.0]]]])
    prior = WalkPrior.from_points({}, FloorPlan("b", (Floor("F1", 1, 3.0, box, box, walls),)))
    ends = []
    for share in (0.0, 0.3):
        pf = ParticleFusion(prior, ParticleConfig(n_particles=500, reset_share=share), init=(5.0, 3.0, 0.3), floor="F1")
        for k in range(6):
            ok, e = pf.correct(AbsoluteFix(float(k), [5.0, 7.0], np.eye(2) * 4.0, "rfid", "F1", 1.0))
            assert ok
        ends.append(e.pos[1])
    assert ends[0] < 5.0 < 5.5 < ends[1]
    # the same under KLD-sampling, walking: a fix's resampling resizes the cloud before the redraw, which
    # must take its donors' positions then from the resized cloud (it once indexed the old one: an
    # IndexError whenever the cloud grew, a wrong shift whenever it was reordered)
    for seed in range(3):
        kld = ParticleConfig(n_particles=200, reset_share=0.3, kld_epsilon=0.05, n_min=100, seed=seed)
        pf = ParticleFusion(prior, kld, init=(10.0, 2.5, 0.3), floor="F1")
        counts, t = set(), 0.0
        for k in range(30):  # standing steps with a wide heading spread: the cloud diffuses, the fixes pull north
            t += 0.5
            pf.predict(StepEvent(t, 0.0, 0.0, 0.3, math.radians(40), 0.0, math.radians(1)))
            if k % 3 == 2:
                pf.correct(AbsoluteFix(t, [10.0, 7.5], np.eye(2) * 4.0, "rfid", "F1", 1.0))
            counts.add(pf.n_particles)
            assert len(pf.p) == len(pf.logw) == len(pf.b) == len(pf.s)
        assert len(counts) > 1  # KLD-sampling did resize the cloud
        assert pf.estimate("end").pos[1] > 5.0  # and the redraws took it across the wall


# ---------------------------------------------------------------------------------------------- re-anchoring
def _reanchor_walk():
    """20 steps of 0.7 m along +x every 0.5 s (t = 0.5 .. 10), one floor change up at the 15th."""
    steps = _walk(20, 0.0)
    steps[14] = StepEvent(steps[14].t, 0.7, 0.0, 0.05, math.radians(2), 0.0, math.radians(1), floor_change=1)
    return steps


def test_kalman_reanchor_replaces_the_estimate_at_t_and_reapplies_the_steps_since():
    """The smoothed estimate at t = 5 s (after step 10) replaces the filter's, and steps 11-20 are
    propagated again from it with the track's heading bias and scale: the result is exactly a filter
    started at t from (p_s, C_s) with (b', s') and the filter's own (b, s) variances, fed the same steps."""
    steps = _reanchor_walk()
    f = LocalFusion(init=(0.0, 0.0, 0.5), floor="F1")
    for st in steps:
        f.predict(st)
    P_bs = f.P[2:, 2:].copy()
    p_s, C_s, bias, scale = np.array([10.0, 3.0]), np.array([[0.04, 0.01], [0.01, 0.09]]), 0.1, 1.1
    e = f.reanchor(5.0, p_s, C_s, "F2", heading_bias=bias, scale=scale)
    since = [st for st in steps if st.t > 5.0]
    assert len(since) == 10
    want = p_s + sum(scale * 0.7 * np.array([math.cos(bias), math.sin(bias)]) for _ in since)
    assert e.kind == "reanchor" and e.t == 10.0 and np.allclose(e.pos, want, atol=1e-12)
    assert f.x[2] == bias and f.x[3] == scale and f.floor == "F3"  # the track's floor, then the step's floor change
    ref = LocalFusion(init=(0.0, 0.0, 0.5))
    ref.x[:] = [*p_s, bias, scale]
    ref.P[:] = 0.0
    ref.P[:2, :2], ref.P[2:, 2:] = C_s, P_bs
    for st in since:
        ref.predict(st)
    assert np.allclose(f.x, ref.x, atol=1e-12) and np.allclose(f.P, ref.P, atol=1e-12)
    # without bias and scale the filter keeps its own; a covariance that is not finite keeps the filter's
    g = LocalFusion(init=(0.0, 0.0, 0.5))
    for st in steps:
        g.predict(st)
    P_before = g.P[:2, :2].copy()
    e = g.reanchor(10.0, [1.0, 2.0], np.full((2, 2), np.nan), "")
    assert np.allclose(e.pos, [1.0, 2.0]) and np.allclose(e.cov, P_before) and g.x[3] == 1.0 and g.x[2] == 0.0


def test_kalman_reanchor_starts_a_cold_filter_and_a_late_fix_is_compared_with_the_new_track():
    steps = _reanchor_walk()
    f = LocalFusion()  # no start position, no fix yet
    with pytest.raises(ValueError):
        f.reanchor(1.0, [0.0, 0.0], np.eye(2), "F1")  # before the filter started: it has taken nothing
    for st in steps:
        f.predict(st)
    assert not f.initialised
    with pytest.raises(ValueError):
        f.reanchor(0.2, [0.0, 0.0], np.eye(2), "F1")  # before its first step
    e = f.reanchor(7.5, [20.0, 5.0], np.eye(2) * 0.25, "F1")
    assert f.initialised and np.allclose(e.pos, [20.0 + 5 * 0.7, 5.0])
    # a fix for the scan at t = 9 s (four steps ago ... two steps after the anchor): compared with the new track then
    ok, _ = f.correct(AbsoluteFix(9.0, [20.0 + 3 * 0.7, 5.0], np.eye(2) * 1.0, "wifi", "F1", 0.9))
    assert ok


def test_reanchor_refuses_a_time_older_than_the_steps_kept():
    from hybridloc.fusion.kalman import REANCHOR_STEPS

    f = LocalFusion(init=(0.0, 0.0, 0.5))
    for st in _walk(REANCHOR_STEPS + 10, 0.0):
        f.predict(st)
    assert f.reanchor_horizon == 0.5 * 10  # the 10th step was the newest forgotten
    with pytest.raises(ValueError):
        f.reanchor(4.0, [0.0, 0.0], np.eye(2), "F1")
    f.reanchor(5.0, [0.0, 0.0], np.eye(2), "F1")  # every step after it is kept


def test_kourogi_reanchor_moves_the_position_and_takes_the_heading_bias():
    steps = _reanchor_walk()
    f = KourogiFusion(init=(0.0, 0.0, 0.5))
    for st in steps:
        f.predict(st)
    e = f.reanchor(5.0, [10.0, 3.0], np.eye(2) * 0.04, "F1", heading_bias=math.radians(90), scale=1.3)
    # the ten steps since, turned by 90 deg: 7 m north of the anchor (no scale state: the steps' own length).
    # The velocity kept from before t (east, the old steps) is projected over the first step: that step's
    # estimate lies between the projection and the turned step, at most |v dt - l d| = 0.7 sqrt(2) m apart
    assert f.heading_offset == math.radians(90)
    assert np.linalg.norm(e.pos - [10.0, 3.0 + 10 * 0.7]) < 0.7 * math.sqrt(2), e.pos


def test_particle_reanchor_redraws_the_cloud_at_t_and_samples_the_steps_again():
    """The cloud at t is N(p_s, C_s) with the walk's mean bias and scale; after the steps since, its mean
    is p_s + the steps turned by the bias and scaled. Tolerances from the sampling: N = 2000 particles
    whose spread after 10 steps is about 0.5 m give a mean within 4 sigma / sqrt(N) = 0.05 m; a bias
    spread of ~2.5 deg shortens the mean step by 1 - cos(2.5 deg) = 0.1 % (7 mm over 7 m)."""
    steps = _reanchor_walk()
    cfg = ParticleConfig(n_particles=2000, sigma_scale0=0.01, seed=3)
    pf = ParticleFusion(None, cfg, init=(0.0, 0.0, 0.5), floor="F1", heading_bias=(0.0, math.radians(1.0)))
    for st in steps:
        pf.predict(st)
    p_s, C_s, bias, scale = np.array([10.0, 3.0]), np.array([[0.04, 0.01], [0.01, 0.09]]), 0.1, 1.1
    # at the newest step (nothing since): the cloud is the smoothed Gaussian, with the walk's bias and scale
    e = pf.reanchor(10.0, p_s, C_s, "F2", heading_bias=bias, scale=scale)
    n = cfg.n_particles
    assert e.kind == "reanchor" and pf.floor == "F2"
    assert np.linalg.norm(e.pos - p_s) < 4 * math.sqrt(0.09 / n)
    assert np.allclose(e.cov, C_s, rtol=0.15, atol=0.01)  # a sample covariance of 2000 draws: ~3 % each
    w = pf.w
    assert math.atan2(float(w @ np.sin(pf.b)), float(w @ np.cos(pf.b))) == pytest.approx(bias, abs=1e-9)
    assert float(w @ pf.s) == pytest.approx(scale, abs=1e-9)
    # at t = 5 s: ten steps since, sampled again
    pf2 = ParticleFusion(None, cfg, init=(0.0, 0.0, 0.5), floor="F1", heading_bias=(0.0, math.radians(1.0)))
    for st in steps:
        pf2.predict(st)
    e = pf2.reanchor(5.0, p_s, C_s, "F2", heading_bias=bias, scale=scale)
    want = p_s + 10 * scale * 0.7 * np.array([math.cos(bias), math.sin(bias)])
    assert e.t == 10.0 and np.linalg.norm(e.pos - want) < 0.05 + 0.007, (e.pos, want)
    assert pf2.floor == "F3"  # the floor change of step 15 re-applied
    # a fix right after, where the re-anchored cloud is, is taken (the history holds the new track)
    ok, _ = pf2.correct(AbsoluteFix(9.0, p_s + 8 * scale * 0.7 * np.array([math.cos(bias), math.sin(bias)]), np.eye(2), "wifi", "F3", 0.9))
    assert ok


def test_particle_reanchor_keeps_to_the_map_and_a_new_prior_replaces_the_old():
    plan = _corridor_plan()
    prior = WalkPrior.from_points({}, plan)
    pf = ParticleFusion(prior, ParticleConfig(n_particles=500, seed=1), init=(5.0, 0.0, 0.3), floor="F1")
    for st in _walk(10, 0.0, t0=0.0):
        pf.predict(st)
    e = pf.reanchor(5.0, [20.0, 0.0], np.eye(2) * 4.0, "F1")  # 2 m sigma in a 2 m wide corridor
    # drawn where the map allows (what a few rounds of rejection leave outside weighs nothing)
    alive = pf.w > 0
    assert abs(e.pos[1]) < 1.0 and alive.mean() > 0.95 and np.all(np.abs(pf.p[alive, 1]) < 1.0)
    wide = np.array([[10.0, 1.5]])  # beyond the old walls, inside the new ones
    assert pf.constraint.log_density("F1", wide)[0] == -np.inf
    pf.set_prior(WalkPrior.from_points({}, _corridor_plan(width=4.0)))
    assert pf.constraint.prior is pf.prior and np.isfinite(pf.constraint.log_density("F1", wide)[0])
    assert np.isfinite(pf._logpi[pf.w > 0]).all()  # the living particles' prior, from the new map
    cold = ParticleFusion(prior, ParticleConfig(n_particles=100))
    cold.predict(_walk(1, 0.0)[0])
    with pytest.raises(ValueError):
        cold.reanchor(0.5, [1.0, 0.0], np.full((2, 2), np.nan), "F1")  # a cold cloud needs a covariance
    assert cold.reanchor(0.5, [1.0, 0.0], np.eye(2) * 0.1, "F1").kind == "reanchor" and cold.initialised


# ------------------------------------------------------------------ KLD-sampling, smoothing, cold start
def test_kld_bound_is_fox_2003_and_the_sample_size_follows_the_occupied_bins():
    from scipy.stats import chi2

    from hybridloc.estimation.resampling import kld_bound, kld_size

    eps, delta = 0.05, 0.01
    for k in (10, 50, 500):
        # Fox's eq. 7 is the Wilson-Hilferty form of chi2_{k-1, 1-delta} / (2 eps); WH is within 1 %
        # of the exact quantile from k = 10 on
        exact = chi2.ppf(1 - delta, k - 1) / (2 * eps)
        assert abs(float(kld_bound(k, eps, delta)) - exact) < 0.01 * exact
    assert float(kld_bound(1, eps, delta)) == 0.0
    with pytest.raises(ValueError):
        kld_bound(5, 0.0, delta)
    # one bin: n_min is enough; every draw in a new bin: the bound is never met and all draws are used
    assert kld_size(np.zeros(1000, int), eps, delta, n_min=50) == 50
    assert kld_size(np.arange(1000), eps, delta, n_min=50) == 1000


def test_kld_particle_count_shrinks_as_fixes_concentrate_the_cloud():
    rng = np.random.default_rng(5)
    cfg = ParticleConfig(n_particles=20_000, seed=4, kld_epsilon=0.05, n_min=200, n_max=20_000)
    pf = ParticleFusion(None, cfg)
    ok, _ = pf.correct(AbsoluteFix(0.0, [5.0, 5.0], np.eye(2) * 100.0, "wifi", "F1", 0.9))  # a 10 m sigma start
    assert ok
    n_start = pf.n_particles
    assert cfg.n_min <= n_start <= cfg.n_max
    true = np.array([5.0, 5.0])
    for k in range(15):
        for st in _walk(4, 0.0, t0=2.0 * k):
            pf.predict(st)
            true = true + [0.7, 0.0]
        pf.correct(AbsoluteFix(2.0 * k + 2.0, true + rng.normal(0, 0.5, 2), np.eye(2) * 0.25, "wifi", "F1", 0.9))
        assert cfg.n_min <= pf.n_particles <= cfg.n_max
    # 0.5 m fixes concentrate the cloud onto far fewer (x, y, heading) bins than the 10 m start covered
    assert pf.n_particles < n_start / 2
    assert np.linalg.norm(pf.estimate("x").pos - true) < 2.0


def test_smoothed_track_is_one_estimate_per_step_and_no_worse_than_the_filtered_one():
    from hybridloc.fusion import run_fusion_smoothed

    rng = np.random.default_rng(8)
    steps = _walk(60, 0.0)
    truth = np.array([[0.7 * (i + 1), 0.0] for i in range(60)])
    fixes = [AbsoluteFix(steps[i].t, truth[i] + rng.normal(0, 1.5, 2), np.eye(2) * 2.25, "wifi", "F1", 0.9) for i in range(0, 60, 5)]
    pf = ParticleFusion(None, ParticleConfig(n_particles=3000, seed=2), init=(0.0, 0.0, 0.3))
    filtered, smoothed = run_fusion_smoothed(pf, steps, fixes, lags=(0, 10))
    assert len(smoothed[10]) == len(smoothed[0]) == len(steps)
    step_t = [s.t for s in steps]
    assert [e.t for e in smoothed[10]] == step_t
    err = {lag: np.mean([np.linalg.norm(e.pos[:2] - truth[i]) for i, e in enumerate(smoothed[lag])]) for lag in (0, 10)}
    # later fixes can only add information about earlier steps: a 10-step lag does not hurt beyond
    # Monte Carlo noise (a few % of the 1.5 m fix sigma)
    assert err[10] <= err[0] + 0.1
    with pytest.raises(ValueError):
        run_fusion_smoothed(LocalFusion(init=(0.0, 0.0, 0.5)), steps, fixes)


def test_time_to_within_scores_the_newest_row_against_interpolated_truth():
    from hybridloc.metrics import time_to_within

    wp_t, wp_xy = [0.0, 10.0, 20.0], [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]]
    # 8 m off until t = 6, then on the truth
    poses = [(t, t + (8.0 if t < 6 else 0.0), 0.0, "F1") for t in np.arange(1.0, 11.0)]
    assert time_to_within(poses, wp_t, wp_xy, 5.0, 30.0) == pytest.approx(6.0)
    assert time_to_within(poses, wp_t, wp_xy, 5.0, 4.0) == math.inf  # not within in the first 4 s
    assert time_to_within(poses, wp_t, wp_xy, 5.0, 30.0, wp_floors=["F2"] * 3) == math.inf  # wrong floor
    with pytest.raises(ValueError):
        time_to_within(poses, wp_t, wp_xy, 0.0, 30.0)


def test_containment_start_draws_every_particle_inside_the_servers_region():
    from hybridloc.types import ContainmentRegion, Fix

    # an L-shaped 95 % region (two rooms), far from its fix's Gaussian mean: the start follows the region
    area = shapely.MultiPolygon([shapely.box(0, 0, 4, 2), shapely.box(0, 2, 2, 6)])
    region = ContainmentRegion("F1", area, 0.95)
    fix = Fix(AbsoluteFix(0.0, [10.0, 10.0], np.eye(2) * 4.0, "wifi", "F1", 0.9), region, {"F1": 1.0})
    pf = ParticleFusion(None, ParticleConfig(n_particles=2000, seed=6, start="containment"))
    ok, e = pf.correct(fix)
    assert ok and e.kind == "init"
    assert shapely.contains_xy(area.buffer(1e-9), pf.p[:, 0], pf.p[:, 1]).all()
    # uniform: each room holds its share of the area (8 and 8 m^2), within 5 binomial sigmas
    in_a = float(np.mean(pf.p[:, 1] < 2.0))
    assert abs(in_a - 0.5) < 5 * math.sqrt(0.25 / 2000)
    # without a region, the fix's own 95 % ellipse
    pf = ParticleFusion(None, ParticleConfig(n_particles=2000, seed=6, start="containment"))
    f = AbsoluteFix(0.0, [10.0, 10.0], np.eye(2) * 4.0, "wifi", "F1", 0.9)
    pf.correct(f)
    from scipy.stats import chi2

    from hybridloc.fusion.kalman import correlated_fix_cov

    R = correlated_fix_cov(np.eye(2) * 4.0, f, pf.cfg.fix_correlation)  # the fix as the filter weighs it
    d = pf.p - [10.0, 10.0]
    d2 = np.einsum("ni,ij,nj->n", d, np.linalg.inv(R), d)
    assert d2.max() <= chi2.ppf(0.95, 2) * (1 + 1e-9)
    # uniform in the ellipse: the squared radius d2 / chi2 is uniform on [0, 1], mean 1/2
    assert abs(np.mean(d2) / chi2.ppf(0.95, 2) - 0.5) < 5 * math.sqrt(1 / 12 / 2000)


def test_cold_start_report_scores_each_walk_held_out_by_floor(capsys):
    """``eval fusion``'s cold-start figure on walks whose fixes scatter 1 m about the truth: the KLD
    particle filter, started uniform in the first fix's 95 % region, is within 5 m at the first fix (a
    5-sigma miss is not expected in 6 walks), on every floor; Fox's epsilon is chosen from the
    candidates on the other floors; the particle count stays within the goal's 50,000."""
    from types import SimpleNamespace

    from hybridloc.demo import COLD_N_MAX, _cold_start_report
    from hybridloc.types import Waypoints

    rng = np.random.default_rng(3)
    results = []
    for k in range(6):
        floor = "F1" if k % 2 else "F2"
        steps = _walk(80, 0.0, t0=float(k))  # 40 s along +x at 1.4 m/s
        wt = np.array([float(k), k + 20.0, k + 40.0])
        wxy = np.array([[0.0, 0.0], [28.0, 0.0], [56.0, 0.0]])
        fixes = []
        for i in range(3, 80, 4):  # a fix every 2 s, reaching the client one step later
            truth = np.array([0.7 * (i + 1), 0.0])
            fixes.append((i + 1, AbsoluteFix(steps[i].t, truth + rng.normal(0.0, 1.0, 2), np.eye(2) * 1.0, "wifi", floor, 1.0)))
        tr = SimpleNamespace(waypoints=Waypoints(wt, wxy, floor))
        results.append((tr, SimpleNamespace(step_events=steps, fix_log=fixes)))
    head = _cold_start_report(results, None, None, (0.1, 0.4))
    out = capsys.readouterr().out
    assert head["cold_within_5m_30s_pct"] == 100.0 and head["cold_within_5m_30s_worst_floor_pct"] == 100.0
    assert head["cold_within_5m_30s_fixed_pct"] == 100.0
    assert 0 < head["cold_particles_max"] <= COLD_N_MAX and head["cold_ms_per_step"] > 0
    assert "F1, held out" in out and "F2, held out" in out and "Fox's epsilon per held-out floor" in out
    # the Kalman filter's settings, held out by floor on the same walks: fixes 1 m off, so every
    # candidate's mean error stays near the fixes' own (a 2-D mean radial error of 1.25 m), far under 3 m
    from hybridloc.demo import _kalman_settings_held_out

    k = _kalman_settings_held_out(results, None)
    assert 0.0 < k["kalman_cold_held_out_mean_m"] < 3.0 and 0.0 < k["kalman_cold_fitted_mean_m"] <= k["kalman_cold_default_mean_m"] < 3.0


def test_eval_fusion_refuses_an_epsilon_outside_0_1(tmp_path):
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "hybridloc.cli", "eval", "fusion", str(tmp_path), "--kld-epsilons", "0.1,2"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode != 0 and "--kld-epsilons takes numbers between 0 and 1" in r.stderr

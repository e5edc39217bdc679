"""Simulator: determinism, physics of the synthesis, exact noiseless reproduction, formats, realism."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from hybridloc.geo import wall_crossings
from hybridloc.ins.foot import run_foot_ins
from hybridloc.io.msft import read_ilc_site, read_ilc_trace
from hybridloc.pdr.phone import run_phone_pdr
from hybridloc.sim.building import generate_world
from hybridloc.sim.imu import GRADES, foot_imu, phone_imu, phone_sensors
from hybridloc.sim.radio import PATH_LOSS_N, SHADOW_LENGTH, SHADOW_SD, make_radio_model, rssi, simulate_radio
from hybridloc.sim.walker import simulate_walk
from hybridloc.units import G0, wrap_angle


@pytest.fixture(scope="module")
def world():
    return generate_world(np.random.default_rng(5), 3, 5)


def test_world_is_deterministic_and_connected(world):
    again = generate_world(np.random.default_rng(5), 3, 5)
    assert again.width == world.width and again.ap_ids == world.ap_ids
    rooms = [i for i, k in enumerate(world.node_kind) if k == "room"]
    for r in rooms[:: max(1, len(rooms) // 8)]:
        path = world.shortest_path(world.outdoor_node, r)  # every room is reachable from outdoors
        assert path[0] == world.outdoor_node and path[-1] == r
    assert [f.name for f in world.plan.floors] == ["F1", "F2", "F3"] and len(world.plan.transitions) == 4


def test_wall_crossings():
    walls = np.array([[[0, -1], [0, 1]], [[2, -1], [2, 1]]], float)
    n = wall_crossings(walls, np.array([[-1.0, 0.0], [-1.0, 0.0], [0.5, 5.0]]), np.array([[3.0, 0.0], [1.0, 0.0], [0.5, 6.0]]))
    assert n.tolist() == [2, 1, 0]


def test_walk_steps_follow_the_walker(world):
    rng = np.random.default_rng(1)
    walk = simulate_walk(world, rng, 3.0)
    assert walk.steps and walk.steps[-1].t <= walk.t1
    flat = [s for s in walk.steps if s.dz == 0]
    lengths = np.array([s.length for s in flat])
    assert np.median(lengths) == pytest.approx(walk.step_length, rel=0.05)
    cad = 1 / np.median(np.diff([s.t for s in flat]))
    assert cad == pytest.approx(walk.speed / walk.step_length, rel=0.1)
    for s in walk.steps[::25]:  # every step lies in its floor's building footprint or the forecourt
        assert -15 <= s.y <= world.depth + 1 and -1 <= s.x <= world.width + 1


def test_noiseless_foot_imu_reproduces_truth_to_numerical_precision(world):
    rng = np.random.default_rng(2)
    walk = simulate_walk(world, rng, 2.0)
    imu, truth = foot_imu(walk, rng, grade=None)
    res = run_foot_ins(imu, stance=truth.stance, heading0=walk.steps[0].heading)
    err = (res.pos_enu - res.pos_enu[0]) - (truth.pos - truth.pos[0])
    assert np.abs(err).max() < 1e-8  # metres over ~150 m of walking: rounding only


def test_noiseless_phone_pdr_counts_every_step_and_every_turn(world):
    rng = np.random.default_rng(3)
    walk = simulate_walk(world, rng, 3.0)
    imu = phone_imu(walk, rng, grade=None)
    steps, _ = run_phone_pdr(imu)
    n_true = len(walk.steps)
    assert abs(len(steps) - n_true) <= 0.01 * n_true + 2  # the 1 % (+ a start/end cut)
    # the heading change from the first step to the last one taken walking straight (a step's heading
    # is its mean over the step, so a walk that stops inside a turn ends on a step half turned), modulo
    # a full turn: a U-turn while standing puts a change of ~pi between two steps, where unwrapping the
    # step headings cannot pick the branch
    tt, th = np.array([s.t for s in walk.steps]), np.array([s.heading for s in walk.steps])
    for last in reversed(steps):
        k = int(np.argmin(np.abs(tt - last.t)))
        if 0 < k and abs(wrap_angle(th[k] - th[k - 1])) < math.radians(1):
            break
    true_turn = th[k] - walk.steps[0].heading
    est_turn = last.heading - steps[0].heading
    assert abs(wrap_angle(est_turn - true_turn)) <= math.radians(10)


def test_handling_the_phone_is_a_rotation_the_three_sensors_agree_on(world):
    """Handling turns the phone about and puts it back. Integrating the simulated gyro across a
    handling pause predicts the magnetometer at every sample (noiseless, so to rounding), the
    accelerometer sees the same tilt (up to the shaking), and at the end the phone is level again
    (only the walker's own turn about the vertical remains)."""
    from scipy.spatial.transform import Rotation

    for seed in range(40):
        walk = simulate_walk(world, np.random.default_rng(seed), 3.0)
        handled = [(a, b) for a, b, h in walk.pauses if h and b - a > 3.0]
        if handled:
            break
    a, b = handled[0]
    imu = phone_imu(walk, np.random.default_rng(1), grade=None)
    idx = np.flatnonzero((imu.t >= a) & (imu.t < b))
    m0 = imu.mag_body[idx[0]].copy()  # core arrays are read-only; scipy wants a writable buffer
    R = Rotation.identity()  # the phone relative to where it was at the start of the pause
    turned = []
    for i in idx[:-2]:  # the last sample repeats the rate before it
        R = R * Rotation.from_rotvec(imu.gyro_body[i] * (imu.t[i + 1] - imu.t[i]))
        turned.append(R.magnitude())
        m_pred, m = R.inv().apply(m0), imu.mag_body[i + 1]
        assert np.arccos(np.clip(m_pred @ m / np.linalg.norm(m_pred) / np.linalg.norm(m), -1, 1)) < 1e-6
        up, acc = R.inv().apply([0.0, 0.0, 1.0]), imu.accel_body[i + 1]
        # the shaking (2 m/s^2 smooth, 1 sigma) tilts the specific force by up to ~20 deg
        assert np.degrees(np.arccos(np.clip(up @ acc / np.linalg.norm(acc), -1, 1))) < 30.0
    assert max(turned) > 0.2  # it really was turned about (~0.5 rad per axis)
    assert R.apply([0.0, 0.0, 1.0])[2] > math.cos(math.radians(0.5))  # level again at the end


def test_phone_imu_physics(world):
    rng = np.random.default_rng(4)
    walk = simulate_walk(world, rng, 1.0)
    imu = phone_imu(walk, rng, grade=None)
    # standing at the start: specific force is g straight up (flat phone), field is the Earth's
    still = imu.t < walk.pauses[0][1] - 0.1
    np.testing.assert_allclose(imu.accel_body[still].mean(0), [0, 0, G0], atol=1e-9)
    assert np.linalg.norm(imu.mag_body[still], axis=1).mean() == pytest.approx(48e-6, rel=1e-6)
    noisy = phone_imu(walk, np.random.default_rng(4), grade="consumer")
    assert np.abs(noisy.accel_body).max() <= GRADES["consumer"].accel_range  # saturation


def test_radio_follows_path_loss_and_is_spatially_correlated(world):
    model = make_radio_model(world, np.random.default_rng(6))
    rng = np.random.default_rng(7)
    ap = 0
    x0, y0, f0 = world.aps[ap]
    near = np.mean([rssi(model, np.array([ap]), np.array([x0 + 2.0, y0]), int(f0), rng)[0] for _ in range(200)])
    far = np.mean([rssi(model, np.array([ap]), np.array([x0 + 20.0, y0]), int(f0), rng)[0] for _ in range(200)])
    # one decade of distance: 10 n dB of path loss; the shadowing at two places 18 m apart differs by
    # sigma_S sqrt(2 (1 - rho)), rho = exp(-d^2 / 2 L^2) for the Gaussian-kernel field: 3 sigma of it
    rho = math.exp(-(18.0**2) / (2 * SHADOW_LENGTH**2))
    assert near - far > 10 * PATH_LOSS_N - 3 * SHADOW_SD * math.sqrt(2 * (1 - rho))
    a = [rssi(model, np.array([ap]), np.array([x0 + 10.0, y0 + 0.3]), int(f0), rng)[0] for _ in range(200)]
    b = [rssi(model, np.array([ap]), np.array([x0 + 10.3, y0 + 0.3]), int(f0), rng)[0] for _ in range(200)]
    assert abs(np.mean(a) - np.mean(b)) < 2.0  # 0.3 m apart (correlation length SHADOW_LENGTH, metres): nearly the same
    walk = simulate_walk(world, np.random.default_rng(8), 2.0)
    radio = simulate_radio(model, walk, np.random.default_rng(9), wifi_period=4.0)
    gaps = np.diff([s.t for s in radio.wifi])
    assert np.all((gaps > 3.5) & (gaps < 4.5))  # throttled scans
    assert all(-92 < r <= 0 for s in radio.wifi for r in s.rssi_dbm.values())
    assert all(f.source.value == "rfid" and f.sigma[0] == pytest.approx(0.4) for f in radio.rfid)


def test_cli_world_and_walk_write_readable_formats(tmp_path):
    run = lambda *a: subprocess.run([sys.executable, "-m", "hybridloc.cli", *a], capture_output=True, text=True, timeout=300)  # noqa: E731
    r = run("sim", "world", "--seed", "9", "--floors", "2", "--out", str(tmp_path / "w"))
    assert r.returncode == 0, r.stderr
    plan = read_ilc_site(tmp_path / "w")  # the ILC floor plan reader takes our world
    assert plan.floor_names == ["F1", "F2"]
    meta = json.loads((tmp_path / "w" / "world.json").read_text())
    x0, y0, x1, y1 = plan.floor("F1").bounds()
    assert x1 - x0 == pytest.approx(meta["width"], rel=1e-6) and y1 - y0 == pytest.approx(meta["depth"], rel=1e-6)
    r = run("sim", "walk", "--world", str(tmp_path / "w"), "--walkers", "2", "--minutes", "1", "--carrier", "both", "--out", str(tmp_path / "k"))
    assert r.returncode == 0, r.stderr
    tr = read_ilc_trace(tmp_path / "k" / "w0000.txt.gz")
    assert tr.report.ok and 49 < tr.imu.rate_hz < 51 and len(tr.waypoints) >= 2 and tr.wifi_scans
    # Android's rotation vector as real phones log it, one a sample: unit quaternions (w from x y z)
    rv_t, rv_q = tr.rotation_vector
    assert len(rv_t) == len(tr.imu) and np.abs(np.linalg.norm(rv_q, axis=1) - 1).max() < 1e-6
    truth = np.loadtxt(tmp_path / "k" / "w0000_truth_steps.csv", delimiter=",", skiprows=1, usecols=(0, 1, 2))
    assert len(truth) > 30
    # every mark carries its floor (walks take the stairs): the floor of the true step at its time
    true_floor = np.loadtxt(tmp_path / "k" / "w0000_truth_steps.csv", delimiter=",", skiprows=1, usecols=(4,), dtype=str)
    wps = tr.waypoints
    assert wps.floors is not None and wps.floor_of(0) == tr.floor
    for i in range(1, len(wps)):
        k = int(np.searchsorted(truth[:, 0], wps.t[i] - 1e-3, side="right")) - 1
        assert wps.floor_of(i) in set(true_floor[max(k, 0) : k + 2]), (i, wps.floor_of(i))
    r = run("pdr", "foot", str(tmp_path / "k" / "w0001_foot.csv"), "--out", str(tmp_path / "o"))
    assert r.returncode == 0, r.stderr


@pytest.mark.shared_data
def test_realism_statistics_inside_real_ranges(ilc_site1):
    from hybridloc.radio.evaluate import load_site_surveys
    from hybridloc.sim.evaluate import simulated_sample
    from hybridloc.sim.realism import in_range, rssi_slopes, spectrum_peaks

    real = [ls for t in load_site_surveys(ilc_site1 / "F2", every=4) for ls in t.labelled]
    _, sim_lab, walks, imus, _ = simulated_sample(6, 4.0)
    assert in_range(float(np.median(rssi_slopes(sim_lab))), rssi_slopes(real))
    real_peaks = []
    for p in sorted((ilc_site1 / "F2" / "path_data_files").glob("*.txt.gz"))[::6]:
        real_peaks += spectrum_peaks(read_ilc_trace(p).imu)
    sim_peaks = np.concatenate([spectrum_peaks(i) for i in imus])
    assert in_range(float(np.median(sim_peaks)), np.array(real_peaks))


def test_world_on_a_real_floor_plan_walkers_keep_to_its_corridors(tmp_path):
    """``sim world --floorplan`` on the bundled Indoor Location Competition floor: walkers route through
    the corridors (free space = walkable minus shops, whose doors the data lacks), never through a shop
    or outside the building, and the usual outputs come out readable; the world reloads identically."""
    import shapely
    from shapely.ops import unary_union

    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.sim.run import load_world

    run = lambda *a: subprocess.run([sys.executable, "-m", "hybridloc.cli", *a], capture_output=True, text=True, timeout=300)  # noqa: E731
    r = run("sim", "world", "--seed", "4", "--floorplan", str(ILC_SITE1_F1), "--out", str(tmp_path / "w"))
    assert r.returncode == 0, r.stderr
    w = load_world(str(tmp_path / "w"))
    assert w.source and len(w.rooms) > 20 and len(w.aps) >= 10 and len(w.rfid) >= 2
    fl = read_ilc_site(ILC_SITE1_F1).floor("F1")
    free = fl.walkable.difference(unary_union([p for _, p in fl.rooms]))
    # the infrastructure and the graph lie in the building (the outdoor node excepted)
    indoor = [i for i, k in enumerate(w.node_kind) if k not in ("entrance", "outdoor")]
    assert shapely.contains_xy(free, w.nodes[indoor, 0], w.nodes[indoor, 1]).all()
    assert shapely.contains_xy(free, w.aps[:, 0], w.aps[:, 1]).all()
    assert not shapely.contains_xy(fl.outline, *w.nodes[w.outdoor_node, :2])
    r = run("sim", "walk", "--world", str(tmp_path / "w"), "--walkers", "3", "--minutes", "1", "--seed", "2", "--out", str(tmp_path / "k"))
    assert r.returncode == 0, r.stderr
    for k in range(3):
        tr = read_ilc_trace(tmp_path / "k" / f"w{k:04d}.txt.gz")
        assert tr.report.ok and tr.wifi_scans and len(tr.waypoints) >= 2
        xy = np.loadtxt(tmp_path / "k" / f"w{k:04d}_truth_steps.csv", delimiter=",", skiprows=1, usecols=(1, 2))
        meta = json.loads((tmp_path / "k" / f"w{k:04d}.json").read_text())
        inside = shapely.contains_xy(free.buffer(0.3), xy[:, 0], xy[:, 1])
        if meta["outdoor_start"]:  # from the forecourt through the entrance: the first steps are outside
            assert inside[len(inside) // 2 :].all()
        else:
            assert inside.all()


def test_foot_ins_counts_clipped_readings(world):
    """A foot IMU whose gyro clips at 4 rad/s (a swing reaches 10+): the clipped samples are counted
    in the run's statistics (and printed by ``pdr foot``); the full-range recording has none."""
    from hybridloc.types import ImuBlock

    walk = simulate_walk(world, np.random.default_rng(8), 1.0)
    imu, _ = foot_imu(walk, np.random.default_rng(9), grade="industrial")
    assert run_foot_ins(imu).stats["saturated_samples"] == 0
    clipped = ImuBlock(imu.t, imu.accel_body, np.clip(imu.gyro_body, -4.0, 4.0), gyro_range=4.0)
    n = run_foot_ins(clipped).stats["saturated_samples"]
    assert n == int((np.abs(imu.gyro_body) >= 0.995 * 4.0).any(axis=1).sum()) and n > 100


def test_sim_floor_plan_file_carries_the_walls_and_walks_never_cross_them(tmp_path):
    """The ILC-format plan of a simulated world lists its walls (our extension), so the particle
    filter sees the rooms and the doors; no true step of a walk crosses one (the entrance link
    through the south rooms used to cross the ground floor's corridor wall)."""
    from hybridloc.fusion import WalkPrior
    from hybridloc.sim.run import load_world, make_world, simulate_walks

    make_world(7, 2, str(tmp_path / "w"))
    plan = read_ilc_site(tmp_path / "w")
    world = load_world(str(tmp_path / "w"))
    for fl, sim_fl in zip(plan.floors, world.plan.floors):
        assert len(fl.walls) == len(sim_fl.walls) > 4
        np.testing.assert_allclose(np.sort(fl.walls.reshape(-1, 4), axis=0), np.sort(sim_fl.walls.reshape(-1, 4), axis=0), atol=1e-3)
    prior = WalkPrior.from_points({}, plan)
    simulate_walks(world, 6, 2.0, "phone", str(tmp_path / "k"), seed=11)
    crossings = 0
    for f in sorted((tmp_path / "k").glob("w*_truth_steps.csv")):
        t = np.loadtxt(f, delimiter=",", skiprows=1, usecols=(1, 2))
        floor = np.loadtxt(f, delimiter=",", skiprows=1, usecols=(4,), dtype=str)
        same = floor[1:] == floor[:-1]
        for name in set(floor):
            m = same & (floor[1:] == name)
            crossings += int(prior.crosses_wall(name, t[:-1][m], t[1:][m]).sum())
    assert crossings == 0


def test_rotation_vector_heading_follows_the_magnetic_field_it_reads(world):
    """The rotation vector is the phone's own fused attitude: its heading error is the heading error
    of the field the simulated magnetometer reads (the noiseless readings turned to the nav frame with
    the true attitude: an independent path), low-passed with the fusion's time constant; what is left
    is its residual gyro bias x tau (1 sigma 0.05 deg/s x 4 s = 0.2 deg, plus its random walk)."""
    from scipy.signal import lfilter

    from hybridloc.pdr.attitude import forward_headings
    from hybridloc.sim.imu import RV_MAG_TAU_S, disturbance_field, magnetic_heading_error

    walk = simulate_walk(world, np.random.default_rng(12), 2.0)
    field = disturbance_field(np.random.default_rng(3), amplitude=12e-6)
    phone = phone_sensors(walk, np.random.default_rng(13), grade=None, mag_field=field)
    imu = phone.imu
    assert np.array_equal(imu.accel_body, phone_imu(walk, np.random.default_rng(13), grade=None, mag_field=field).accel_body)
    t, q = phone.rotation_vector
    assert np.array_equal(t, imu.t) and (q[:, 0] >= 0).all()
    held = np.zeros(len(t), bool)
    for a, b, handled in walk.pauses:
        held |= handled & (t >= a - 1.0) & (t < b + 1.0)
    # off handling the phone lies flat, Rz(psi - pi/2): its heading psi is the field's angle in the nav
    # frame minus its angle in the body frame, + pi/2 (body +y is forward)
    pos, _ = walk.position_at(t)
    m_nav_true = np.array([0.0, 48e-6 * math.cos(math.radians(63)), -48e-6 * math.sin(math.radians(63))]) + field(pos)
    ang_body = np.arctan2(imu.mag_body[:, 1], imu.mag_body[:, 0])  # the field's angle seen from the body
    ang_nav = np.arctan2(m_nav_true[:, 1], m_nav_true[:, 0])
    psi = wrap_angle(ang_nav - ang_body + math.pi / 2)  # body x is psi - pi/2 in nav
    e = np.unwrap(wrap_angle(forward_headings(q) - psi))
    e_m = np.unwrap(magnetic_heading_error(m_nav_true))
    a = math.exp(-float(np.median(np.diff(t))) / RV_MAG_TAU_S)
    e_lp, _ = lfilter([1 - a], [1, -a], e_m, zi=[a * e_m[0]])
    assert np.degrees(np.abs(e_m[~held])).max() > 10  # the field really disturbs the heading
    assert np.degrees(np.abs(e - e_lp)[~held]).max() < 1.0  # 0.2 deg bias x tau at 1 sigma, the rest its walk


def test_step_length_follows_the_bounce_as_weinberg_assumes(world):
    """Each step's vertical CoM excursion is the inverted pendulum's, h = l - sqrt(l^2 - (s / 2c)^2),
    and the phone's bounce swings G h (2 pi / T)^2: with the walk ratio r = s / f kept, the step length
    is K (a_max - a_min)^(1/4) with K = (2 l c^2 r^2 / (pi^2 G))^(1/4) (walker.com_excursion). On
    noiseless walks the PDR's own max - min per step gives each walker that K, to the hand's jitter:
    it widens max - min by about one to two jitter sigmas (1.4 of ~10 m/s^2: 3-6 % off in the fourth
    root, so the measured K is that much smaller) and
    the per-step CV of h (8 %, 2 % in the fourth root) averages out over the steps."""
    from hybridloc.pdr.phone import PhonePdr
    from hybridloc.sim.walker import com_excursion

    ks, preds = [], []
    for seed in range(4):
        walk = simulate_walk(world, np.random.default_rng(20 + seed), 1.5)
        flat = [s for s in walk.steps if s.dz == 0]
        h = np.array([s.bounce for s in flat])
        h0 = com_excursion(np.array([s.length for s in flat]), walk.leg_length, walk.pendulum_correction)
        assert np.median(h / h0) == pytest.approx(1.0, abs=0.03)  # the pendulum, per-step CV 8 %
        phone = phone_sensors(walk, np.random.default_rng(30 + seed), grade=None)
        pdr = PhonePdr(phone.imu.rate_hz)
        pdr.process(phone.imu)
        td = np.array([s.t for s in pdr.steps])
        feats = pdr.features
        tt = np.array([s.t for s in flat])
        k = np.clip(np.searchsorted(td, tt), 1, len(td) - 1)
        k = np.where(np.abs(td[k - 1] - tt) < np.abs(td[k] - tt), k - 1, k)
        near = np.abs(td[k] - tt) < 0.1
        L = np.array([s.length for s in flat])[near]
        ks.append(np.median(L / np.array([feats[i].bounce for i in k[near]]) ** 0.25))
        r = walk.step_length**2 / walk.speed  # walk ratio, m s
        preds.append((2 * walk.leg_length * walk.pendulum_correction**2 * r**2 / (math.pi**2 * phone.bounce_gain)) ** 0.25)
    ks, preds = np.array(ks), np.array(preds)
    assert np.all(np.abs(ks / preds - 1) < 0.08), ks / preds

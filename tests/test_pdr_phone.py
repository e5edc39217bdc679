"""Phone PDR on synthetic walks whose truth follows from the signal model, and on real traces."""

import math

import numpy as np
import pytest

from hybridloc.pdr import LengthCalibrator, PhonePdr, PhonePdrConfig, WeinbergLength, dead_reckon, run_phone_pdr
from hybridloc.pdr.attitude import AttitudeFilter, quat_mul, quat_normalize, quat_to_rot, triad
from hybridloc.pdr.steplength import StepFeatures
from hybridloc.types import ImuBlock
from hybridloc.units import DEG, G0

RATE = 50.0
B_FIELD, DIP = 45e-6, 45 * DEG


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def synth_walk(rng, seconds=60.0, f_step=1.8, amp=2.5, heading=lambda t: 0.0 * t, noise=0.08, mag=True, still=0.0):
    """Phone held flat (body y forward, z up) by a walker: vertical bounce at the step frequency.

    Specific force in nav = (0, 0, g + amp sin(2 pi f t)); body = R^T f_nav with R = Rz(psi - pi/2),
    so body +y points along the heading psi. One step per bounce cycle. ``still`` seconds of standing
    come first.
    """
    t = np.arange(0.0, seconds + still, 1 / RATE)
    psi = np.array([heading(max(0.0, x - still)) for x in t])
    walking = t >= still
    av = np.where(walking, amp * np.sin(2 * math.pi * f_step * (t - still)), 0.0)
    acc, gyr, mg = np.zeros((len(t), 3)), np.zeros((len(t), 3)), np.zeros((len(t), 3))
    dpsi = np.gradient(psi, t)
    m_nav = np.array([0.0, B_FIELD * math.cos(DIP), -B_FIELD * math.sin(DIP)])
    for i in range(len(t)):
        R = _rz(psi[i] - math.pi / 2)
        acc[i] = R.T @ np.array([0.0, 0.0, G0 + av[i]])
        gyr[i] = [0.0, 0.0, dpsi[i]]
        mg[i] = R.T @ m_nav
    acc += noise * rng.standard_normal(acc.shape)
    gyr += 0.003 * rng.standard_normal(gyr.shape)
    mg += 0.3e-6 * rng.standard_normal(mg.shape)
    n_true = int(math.floor(seconds * f_step))
    return ImuBlock(t, acc, gyr, mg if mag else None), n_true


def test_triad_recovers_attitude():
    R_true = _rz(0.7)
    acc = R_true.T @ [0, 0, G0]
    mag = R_true.T @ [0, B_FIELD * math.cos(DIP), -B_FIELD * math.sin(DIP)]
    np.testing.assert_allclose(np.array(quat_to_rot(triad(acc, mag))), R_true, atol=1e-9)


def test_attitude_follows_gyro_about_gravity_whatever_the_tilt():
    """Tilted phone turning about the vertical: the yaw change equals the integrated vertical rate."""
    rng = np.random.default_rng(0)
    tilt = np.array([[1, 0, 0], [0, math.cos(1.0), -math.sin(1.0)], [0, math.sin(1.0), math.cos(1.0)]])  # 57 deg pitch
    f = AttitudeFilter()
    rate = 0.5  # rad/s about nav up, for 3 s
    heads = []
    for i in range(201):
        t = i / RATE
        R = _rz(rate * min(t, 3.0)) @ tilt
        w_nav = np.array([0, 0, rate if t < 3.0 else 0.0])
        f.update(t, R.T @ [0, 0, G0], R.T @ w_nav + 1e-3 * rng.standard_normal(3), None)
        heads.append(f.forward_heading())
    turned = (heads[-1] - heads[0] + math.pi) % (2 * math.pi) - math.pi
    assert turned == pytest.approx(rate * 3.0 - rate / RATE, abs=2 * DEG)


def test_a_still_phone_reads_its_gyro_bias_and_then_holds_its_heading():
    """ZARU: a phone standing still with a raw gyro biased by 2 deg/s about the vertical (a consumer
    gyro's turn-on bias) has its bias read within the first seconds; walking on straight for 60 s,
    the heading holds to what the noise leaves (0.003 rad/s white at 50 Hz: ~1 deg), where the bias
    alone would turn it by 120 deg. No magnetometer: the gyro alone has to do it."""
    rng = np.random.default_rng(1)
    imu, _ = synth_walk(rng, seconds=60.0, mag=False, still=4.0)
    bias = np.array([0.0, 0.0, 2.0 * DEG])
    imu = ImuBlock(imu.t, imu.accel_body, imu.gyro_body + bias, None)
    pdr = PhonePdr(RATE, heading0=0.0)
    steps = pdr.process(imu)
    assert pdr.att.bias[2] == pytest.approx(bias[2], abs=0.1 * DEG)
    drift = max(abs(s.heading) for s in steps)
    assert drift < 3 * DEG


def test_the_magnetometer_does_not_turn_a_still_phone():
    """Standing still beside steel: the field here says North is 30 deg from where the gyro has
    carried the heading. Nothing moves, so the consistency test passes whatever the field; the
    heading must stay where the gyro holds it (k_mag = 0.1/s would have pulled it ~30 deg (1 - e^-2)
    = 26 deg over 20 s)."""
    f = AttitudeFilter()
    m_nav = np.array([0.0, B_FIELD * math.cos(DIP), -B_FIELD * math.sin(DIP)])
    acc = np.array([0.0, 0.0, G0])
    for i in range(int(22 * RATE)):
        t = i / RATE
        f.update(t, acc, np.zeros(3), m_nav)
        if i == int(1.0 * RATE):  # the heading as the gyro brought it here, 30 deg off this spot's field
            d = 30 * DEG
            f.q = quat_normalize(quat_mul((math.cos(d / 2), 0.0, 0.0, math.sin(d / 2)), f.q))
            h0 = f.forward_heading()
    assert f.still
    assert abs(f.forward_heading() - h0) < 0.5 * DEG


def test_a_slow_turn_while_standing_is_not_taken_for_gyro_bias():
    """Standing and turning slowly on the spot (4 deg/s for 10 s: 40 deg) with a gyro biased by
    1.5 deg/s: the rate is steady, so the gyro alone cannot tell the turn from a bias. With a
    magnetometer the field's turn in the body frame shows it; without one, a steady rate beyond
    3 sigma of a turn-on bias (0.05 rad/s) is not read as bias. Either way the turn is kept (within
    the 2 deg the bias's own first reading and the noise allow) and the bias stays the gyro's."""
    m_nav = np.array([0.0, B_FIELD * math.cos(DIP), -B_FIELD * math.sin(DIP)])
    rate, bias = 4 * DEG, np.array([0.0, 0.0, 1.5 * DEG])
    for with_mag in (True, False):
        rng = np.random.default_rng(0)
        f = AttitudeFilter()
        for i in range(int(20 * RATE)):
            t = i / RATE
            R = _rz(rate * (min(t, 15.0) - 5.0) if t > 5.0 else 0.0)
            w = np.array([0.0, 0.0, rate if 5.0 <= t < 15.0 else 0.0])
            m = R.T @ m_nav + 0.3e-6 * rng.standard_normal(3) if with_mag else None
            f.update(t, R.T @ [0.0, 0.0, G0] + 0.02 * rng.standard_normal(3), w + bias + 0.002 * rng.standard_normal(3), m)
            if i == int(4.9 * RATE):
                h0 = f.forward_heading()
        turned = math.remainder(f.forward_heading() - h0, 2 * math.pi)
        assert turned == pytest.approx(40 * DEG, abs=2 * DEG), with_mag
        assert f.bias[2] == pytest.approx(bias[2], abs=0.2 * DEG)


def test_step_count_and_turn_on_synthetic_walk():
    rng = np.random.default_rng(1)
    # 60 s straight, a 90 degree left turn spread over 4 s in the middle.
    turn = lambda t: (math.pi / 2) * min(max((t - 30.0) / 4.0, 0.0), 1.0)  # noqa: E731
    imu, n_true = synth_walk(rng, heading=turn)
    for det in ("peak", "autocorr"):
        steps, stats = run_phone_pdr(imu, WeinbergLength(), PhonePdrConfig(detector=det))
        # One step per bounce; at most the first and last cycles can be cut by the filters' edges.
        assert abs(len(steps) - n_true) <= 2, (det, len(steps), n_true)
        total_turn = sum(s.heading_change for s in steps[1:])
        assert total_turn == pytest.approx(math.pi / 2, abs=2 * DEG)
        assert all(s.sigma_length > 0 and s.sigma_heading > 0 for s in steps)


def test_standing_gives_no_steps():
    rng = np.random.default_rng(2)
    still, _ = synth_walk(rng, seconds=60.0, amp=0.0)
    assert len(run_phone_pdr(still)[0]) == 0


def _handling(seed: int) -> ImuBlock:
    """Smooth random (non-periodic) accelerations of 2 m/s^2 and rotations of ~1 rad/s, 60 s."""
    rng = np.random.default_rng(seed)
    n = int(60 * RATE)
    t = np.arange(n) / RATE
    k = np.exp(-0.5 * (np.arange(-25, 26) / 8.0) ** 2)
    k /= np.sqrt((k**2).sum())
    smooth = lambda: np.convolve(rng.standard_normal(n), k, mode="same")  # noqa: E731
    acc = np.column_stack([2 * smooth(), 2 * smooth(), G0 + 2 * smooth()])
    gyr = np.column_stack([smooth(), smooth(), smooth()])
    return ImuBlock(t, acc, gyr)


def test_handling_gives_at_most_one_false_step_per_minute():
    counts = [len(run_phone_pdr(_handling(seed))[0]) for seed in range(6)]
    assert np.mean(counts) <= 1.0, counts


def test_handling_right_before_walking_off_adds_no_steps():
    """Steps are held back until walking is confirmed, then released; candidates left by a phone
    handled just before the walk (irregular, every axis shaken) must not be released with them."""
    false_before, count_err = [], []
    for seed in range(6):
        rng = np.random.default_rng(100 + seed)
        walk, n_true = synth_walk(rng, seconds=30.0, still=12.0, mag=False)
        hand = _handling(seed)
        m = int(11.0 * RATE)  # handled until 1 s before the first step
        acc, gyr = walk.accel_body.copy(), walk.gyro_body.copy()
        acc[:m], gyr[:m] = hand.accel_body[:m], hand.gyro_body[:m]
        steps, _ = run_phone_pdr(ImuBlock(walk.t, acc, gyr))
        false_before.append(sum(s.t < 12.0 for s in steps))
        count_err.append(len(steps) - n_true)
    assert np.mean(false_before) <= 0.5, false_before  # at most one every other walk-off
    assert max(abs(c) for c in count_err) <= 3, count_err  # the walk itself is still counted


def test_a_walk_from_the_first_sample_is_recognised_within_two_seconds():
    """Walking is confirmed once the auto-correlation sees periodic steps; after a start (or a gap) it
    may use the signal so far once it spans nasc_min_window = 1.2 s (two 0.56 s steps), not the full
    2.4 s window. Three consistent periodic candidates confirm walking, so the first steps come out
    by 1.2 + 3 x 0.56 = 2.9 s (the full window alone: 2.4 + 2 x 0.56 = 3.5 s at the earliest), and
    none of the held-back ones is lost."""
    rng = np.random.default_rng(21)
    imu, n_true = synth_walk(rng, seconds=20.0, f_step=1.8, mag=False)
    pdr = PhonePdr(RATE)
    first_out = None
    for i in range(len(imu.t)):
        if pdr.update(imu.t[i], imu.accel_body[i], imu.gyro_body[i]) and first_out is None:
            first_out = imu.t[i]
    assert first_out is not None and first_out < 1.2 + 3 / 1.8, first_out
    assert abs(len(pdr.steps) - n_true) <= 2


def test_streaming_equals_batch():
    rng = np.random.default_rng(3)
    imu, _ = synth_walk(rng, seconds=20.0)
    batch, _ = run_phone_pdr(imu)
    pdr = PhonePdr(imu.rate_hz, heading0=0.0)
    online = []
    for i in range(len(imu)):
        online += pdr.update(float(imu.t[i]), imu.accel_body[i].tolist(), imu.gyro_body[i].tolist(), imu.mag_body[i].tolist())
    assert [s.t for s in online] == [s.t for s in batch]
    assert [s.heading for s in online] == [s.heading for s in batch]


def test_bad_samples_are_counted_and_gaps_flagged():
    rng = np.random.default_rng(4)
    imu, _ = synth_walk(rng, seconds=30.0)
    pdr = PhonePdr(imu.rate_hz, heading0=0.0)
    out = []
    for i in range(len(imu)):
        t = float(imu.t[i])
        if 10.0 <= t < 12.0:
            continue  # a 2 s gap
        acc = imu.accel_body[i].tolist()
        if i == 100:
            acc[0] = float("nan")
        out += pdr.update(t, acc, imu.gyro_body[i].tolist(), imu.mag_body[i].tolist())
        if i == 200:
            out += pdr.update(t, acc, imu.gyro_body[i].tolist(), None)  # duplicate time
    assert pdr.stats.rejected_samples == {"non-finite": 1, "not-increasing-time": 1}
    assert pdr.stats.gaps == 1
    assert any(s.degraded == "gap" for s in out)
    assert all(math.isfinite(s.heading) for s in out)


def test_missing_magnetometer_is_reported_on_every_step():
    rng = np.random.default_rng(5)
    imu, _ = synth_walk(rng, seconds=20.0, mag=False)
    steps, _ = run_phone_pdr(imu)
    assert steps and all(s.degraded == "no-mag" for s in steps)


def test_dead_reckon_covariance_grows():
    rng = np.random.default_rng(6)
    imu, _ = synth_walk(rng, seconds=20.0)
    steps, _ = run_phone_pdr(imu)
    tr = dead_reckon(steps, 5.0, 5.0)
    assert tr.pos_enu[0, 0] == 5.0 and np.all(np.diff(tr.sigma_enu[:, 0]) >= 0)
    # heading0 = 0: the straight walk goes East
    assert tr.pos_enu[-1, 0] - 5.0 == pytest.approx(sum(s.length for s in steps), rel=0.01)


def test_calibrator_recovers_weinberg_k(tmp_path):
    rng = np.random.default_rng(7)
    K = 0.42
    cal = LengthCalibrator(WeinbergLength(0.3), forgetting=1.0)
    for _ in range(40):
        feats = [StepFeatures(0.55, float(b)) for b in rng.uniform(2.0, 8.0, 20)]
        D = sum(K * f.bounce**0.25 for f in feats) + 0.05 * rng.standard_normal()
        cal.update(feats, D, sigma_distance=0.05)
    assert cal.model.coef[0] == pytest.approx(K, rel=0.01)
    cal.save(tmp_path / "dev.json")
    back = LengthCalibrator.load(tmp_path / "dev.json")
    assert back.model.coef[0] == cal.model.coef[0] and back.n_segments == 40


def test_calibrator_is_not_dragged_by_mis_marked_segments():
    """Huber in the relative residual: 40 good segments (2 % distance noise) and 8 whose known
    distance is 60 % too long (a mis-marked waypoint). Least squares moves K by about 8 / 48 x 60 % =
    10 %. Robust, a bad segment's residual is 0.6 / 1.6 = 37.5 % of its distance, so it weighs
    0.15 / 0.375 = 0.4 of a good one and K moves by about 3.2 / 43.2 x 60 % = 4.4 %."""
    rng = np.random.default_rng(12)
    K = 0.42
    segs = []
    for j in range(48):
        feats = [StepFeatures(0.55, float(b)) for b in rng.uniform(2.0, 8.0, 20)]
        D = sum(K * f.bounce**0.25 for f in feats) * (1 + 0.02 * rng.standard_normal())
        segs.append((feats, D * (1.6 if j % 6 == 5 else 1.0)))
    fits = {}
    for name, hr in (("robust", 0.15), ("plain", None)):
        cal = LengthCalibrator(WeinbergLength(0.3), forgetting=1.0, huber_rel=hr)
        for feats, D in segs:
            cal.update(feats, D, sigma_distance=0.5)
        fits[name] = cal.model.coef[0]
    assert fits["robust"] == pytest.approx(1.044 * K, rel=0.015)
    assert fits["plain"] == pytest.approx(1.10 * K, rel=0.015)


def test_kim_model_uses_the_mean_vertical_acceleration_and_calibrates():
    """Kim et al.: L = K (mean |a_v|)^(1/3). Same RLS as every model; 40 segments of 20 steps with 5 cm
    of distance noise pin K to well under 1 % (the regressor sums are ~25, so sigma_K ~ 0.05 / 25 / sqrt(40))."""
    from hybridloc.pdr.steplength import KimLength

    assert KimLength(0.5).length(StepFeatures(0.55, 6.0, 2.0)) == pytest.approx(0.5 * 2.0 ** (1 / 3))
    rng = np.random.default_rng(9)
    K = 0.5
    cal = LengthCalibrator(KimLength(0.3), forgetting=1.0)
    for _ in range(40):
        feats = [StepFeatures(0.55, 5.0, float(m)) for m in rng.uniform(0.8, 3.0, 20)]
        D = sum(K * f.mean_abs ** (1 / 3) for f in feats) + 0.05 * rng.standard_normal()
        cal.update(feats, D, sigma_distance=0.05)
    assert cal.model.coef[0] == pytest.approx(K, rel=0.01)


def test_bounce_height_model_is_kim_on_the_bounce_height():
    """L = K (mean |a_v| T^2)^(1/3): a sinusoidal bounce z = h sin(2 pi t / T) has mean |a_v| =
    (2 / pi) h (2 pi / T)^2 = 8 pi h / T^2, so the regressor is (8 pi h)^(1/3) whatever the cadence:
    the same bounce height gives the same step at 1.5 and at 2.2 steps/s (Kim's model would not)."""
    from hybridloc.pdr.steplength import BounceHeightLength, KimLength, make_model

    h = 0.04  # m, a typical walking bounce
    feats = [StepFeatures(T, 0.0, 8 * math.pi * h / T**2) for T in (1 / 1.5, 1 / 2.2)]
    m = make_model("height", [0.7])
    assert isinstance(m, BounceHeightLength)
    L = [m.length(f) for f in feats]
    assert L[0] == pytest.approx(L[1], rel=1e-12) and L[0] == pytest.approx(0.7 * (8 * math.pi * h) ** (1 / 3), rel=1e-12)
    kim = [KimLength(0.46).length(f) for f in feats]
    assert kim[1] / kim[0] == pytest.approx((2.2 / 1.5) ** (2 / 3), rel=1e-9)  # Kim grows with cadence alone
    rng = np.random.default_rng(11)
    cal = LengthCalibrator(BounceHeightLength(0.5), forgetting=1.0)
    for _ in range(40):  # same RLS as every model: recovers K from segments of known length
        fs = [StepFeatures(float(T), 5.0, float(a)) for T, a in zip(rng.uniform(0.45, 0.65, 20), rng.uniform(0.8, 3.0, 20))]
        D = sum(0.7 * (f.mean_abs * f.duration**2) ** (1 / 3) for f in fs) + 0.05 * rng.standard_normal()
        cal.update(fs, D, sigma_distance=0.05)
    assert cal.model.coef[0] == pytest.approx(0.7, rel=0.01)


@pytest.mark.shared_data
def test_real_traces_give_human_step_lengths(ilc_site1, tmp_path):
    import subprocess
    import sys

    from hybridloc.pdr.evaluate import collect_runs

    paths = sorted((ilc_site1 / "F1" / "path_data_files").glob("*.txt.gz"))[:8]
    runs, _ = collect_runs(paths, PhonePdrConfig())
    m_per_step = []
    for r in runs:
        ts = np.array([s.t for s in r.steps])
        n = ((ts > r.wp_t[0]) & (ts <= r.wp_t[-1])).sum()
        D = np.linalg.norm(np.diff(r.wp_xy, axis=0), axis=1).sum()
        m_per_step.append(D / max(n, 1))
    # Adult walking steps are 0.5-0.9 m; waypoint polylines cut corners, so allow 0.4-1.0 m.
    assert 0.4 <= np.median(m_per_step) <= 1.0
    r = subprocess.run(
        [sys.executable, "-m", "hybridloc.cli", "pdr", "phone", str(paths[0]), "--out", str(tmp_path), "--start", "3,4,90deg"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    d = tmp_path / paths[0].name.replace(".txt.gz", "")
    assert (d / "steps.csv").read_text().splitlines()[0].startswith("t,length,heading,sigma_length,sigma_heading")
    first = (d / "trajectory.csv").read_text().splitlines()[1].split(",")
    assert float(first[1]) == 3.0 and float(first[2]) == 4.0
    second = (d / "steps.csv").read_text().splitlines()[1].split(",")
    assert float(second[2]) == pytest.approx(math.pi / 2, abs=1e-4)


def test_segment_error_decomposition_recovers_both_parts():
    """e = n_end + s D with known sigmas: the robust fit gives both back. Tolerance: the median of
    e^2 over ~1,000 segments per bin has a relative standard error near 7 %, so 20 % on sigma^2
    (10 % on sigma) is 3 standard errors."""
    from hybridloc.pdr.evaluate import decompose_segment_errors

    rng = np.random.default_rng(7)
    D = rng.uniform(3.0, 20.0, 5000)
    e = rng.normal(0.0, 0.8, D.size) + rng.normal(0.0, 0.06, D.size) * D
    e[:50] += 40.0  # gross outliers (a lost trace) must not dominate
    s_end, s_rel = decompose_segment_errors(D, e)
    assert s_end == pytest.approx(0.8, rel=0.1)
    assert s_rel == pytest.approx(0.06, rel=0.1)


def test_turn_error_decomposition_recovers_both_parts():
    """Turn error = the PDR's own (sigma_turn) + the marks' (sqrt(2) sigma_mark / D per segment, two
    segments a turn): the robust fit returns both. 15 %: the two parts share the same five bins, whose
    spread in 1/D^2 is narrower than the length split's in D^2, so each is looser than there."""
    from hybridloc.pdr.evaluate import decompose_turn_errors

    rng = np.random.default_rng(11)
    L = rng.uniform(3.0, 15.0, (5000, 2))
    s_turn, s_mark = math.radians(6.0), 0.5
    mark = lambda D: rng.normal(0.0, math.sqrt(2.0) * s_mark / D)  # noqa: E731
    e = rng.normal(0.0, s_turn, 5000) + mark(L[:, 0]) - mark(L[:, 1])
    got_turn, got_mark = decompose_turn_errors(L, e)
    assert got_turn == pytest.approx(s_turn, rel=0.15)
    assert got_mark == pytest.approx(s_mark, rel=0.15)


def test_android_step_headings_match_our_forward_heading():
    """Android's rotation vector goes through the same "forward" as our filter: a phone held flat and
    yawed by psi from facing North points at heading pi/2 + psi (CCW from East); per step the
    circular mean over the step's interval (continuous across +-pi)."""
    from hybridloc.pdr.attitude import forward_heading_of, forward_headings
    from hybridloc.pdr.evaluate import android_step_headings
    from hybridloc.types import StepEvent

    t = np.arange(0.0, 10.0, 0.02)
    yaw = np.where(t < 5.0, 0.3, 0.3 + math.pi / 2)  # a left turn of 90 deg at t = 5 s: heading crosses +pi
    tilt = 20 * DEG  # pitched up, as a phone read while walking
    # q = q_yaw(z) * q_pitch(x): body-to-nav, nav ENU with y toward North
    cz, sz, cx, sx = np.cos(yaw / 2), np.sin(yaw / 2), math.cos(tilt / 2), math.sin(tilt / 2)
    q = np.column_stack([cz * cx, cz * sx, sz * sx, sz * cx])
    h = forward_headings(q)
    for i in (0, 249, 250, 499):  # the vectorised form equals the filter's own, per sample
        assert abs(h[i] - forward_heading_of(quat_to_rot(q[i]))) < 1e-12
    assert abs(h[0] - (math.pi / 2 + 0.3)) < 1e-9
    steps = [StepEvent(float(ts), 0.7, 0.0, 0.1, 0.1) for ts in np.arange(0.6, 9.9, 0.6)]
    got = android_step_headings(steps, t, q)
    want = np.array([math.pi / 2 + (0.3 if s.t < 5.0 else 0.3 + math.pi / 2) for s in steps])
    err = np.abs((got - want + math.pi) % (2 * math.pi) - math.pi)
    straddles = np.array([steps[i - 1].t < 5.0 <= steps[i].t if i else False for i in range(len(steps))])
    assert err[~straddles].max() < 1e-9  # steps within one heading: exact
    assert err[straddles].max() < math.pi / 2  # the step over the turn: between the two


def test_cli_updates_a_device_calibration_from_waypointed_walks(tmp_path):
    """The bundled sample's walks (shipped, no ../shared needed) calibrate a device: the file is made
    from the model's default, learns from the waypoint segments, stays a human step constant (the
    bounce-height K is 0.70 +- ~10 % across people), and is then used as it is."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    import hybridloc

    walks = sorted((Path(hybridloc.__file__).parent / "data" / "ilc_site1_F1" / "F1" / "path_data_files").glob("*.txt*"))[:3]
    assert walks
    cal = tmp_path / "dev.json"

    def run(*extra):
        return subprocess.run(
            [
                sys.executable,
                "-m",
                "hybridloc.cli",
                "pdr",
                "phone",
                *map(str, walks),
                "--out",
                str(tmp_path / "o"),
                "--calibration",
                str(cal),
                *extra,
            ],
            capture_output=True,
            text=True,
            timeout=300,
        )

    r = run()
    assert r.returncode != 0 and "not found" in r.stderr  # no silent default when the file is missing
    r = run("--update-calibration")
    assert r.returncode == 0, r.stderr
    d = json.loads(cal.read_text())
    assert d["model"] == "height" and d["n_segments"] >= 3
    assert 0.5 <= d["coef"][0] <= 0.9
    r = run()
    assert r.returncode == 0, r.stderr
    assert f"height [{d['coef'][0]}]" in r.stdout  # the saved constant is what the walks now use
    assert json.loads(cal.read_text())["n_segments"] == d["n_segments"]  # and, without --update-calibration, it is left alone


def test_walking_offset_is_recovered_whatever_way_the_phone_is_carried():
    """A real walk (bundled sample) with the phone turned about its screen's normal by 90, 180 or
    -90 deg for the whole recording (all three sensors rotate together): with the offset estimated,
    the walking heading is the unturned walk's within 20 deg (the estimator's spread on real walks),
    not 180 deg off, as the principal axis signed by continuity with a zero prior leaves it at 180."""
    from hybridloc.io.msft import find_ilc_traces, read_ilc_trace
    from hybridloc.pdr.evaluate import turn_in_hand
    from hybridloc.samples import ILC_SITE1_F1
    from hybridloc.units import wrap_angle

    # the longest bundled walk: the estimate needs a few dozen steps to settle
    imu = max((read_ilc_trace(p).imu for p in find_ilc_traces(ILC_SITE1_F1)), key=lambda b: b.t[-1] - b.t[0])

    def walk_heading(block, rule):
        steps = PhonePdr(block.rate_hz, config=PhonePdrConfig(estimate_offset=True, offset_sign=rule)).process(block)
        assert len(steps) > 40
        return float(np.angle(np.exp(1j * np.array([s.heading for s in steps[len(steps) // 2 :]])).mean()))

    for rule in ("gait", "continuity"):
        h0 = walk_heading(imu, rule)
        for deg in (90, 180, -90):
            d = abs(wrap_angle(walk_heading(turn_in_hand(imu, math.radians(deg)), rule) - h0))
            if rule == "gait":
                assert d < math.radians(20), (deg, math.degrees(d))
            elif deg == 180:
                assert d > math.radians(160)  # the textbook rule keeps the wrong half it started with


def test_a_clipped_gyro_is_flagged_and_widens_the_heading_sigma():
    """A walk with a quick 90 deg turn (3 rad/s for ~0.5 s) read by a gyro whose full scale is 2 rad/s:
    the clipped samples are counted, the steps around them say "saturated", and the heading sigma
    after the turn grows by about what the clipping may have lost (~(3 - 2) rad/s x 0.5 s = 0.5 rad,
    bounded below by the clipped rate x the clipped time's share counted, 2 x 0.5 = 1 rad at most).
    With the full scale unknown, the flat-topped plateau gives the same flag."""
    rng = np.random.default_rng(2)
    turn = lambda t: 0.0 if t < 20 else min((t - 20) * 3.0, math.pi / 2)  # noqa: E731
    imu, _ = synth_walk(rng, seconds=40.0, heading=turn, mag=False)
    full = 2.0
    clipped = ImuBlock(imu.t, imu.accel_body, np.clip(imu.gyro_body, -full, full), None, gyro_range=full)
    pdr = PhonePdr(RATE)
    steps = pdr.process(clipped)
    assert pdr.stats.saturated > 10  # ~0.5 s at 50 Hz
    flagged = [s for s in steps if s.degraded == "saturated"]
    assert 1 <= len(flagged) <= 3
    before = max(s.sigma_heading for s in steps if s.t < 19.5)
    after = min(s.sigma_heading for s in steps if s.t > 21.0)
    assert after**2 - before**2 > 0.3**2
    unknown = PhonePdr(RATE)  # no full scale: the repeated extreme reading is the sign
    unknown.process(ImuBlock(imu.t, imu.accel_body, np.clip(imu.gyro_body, -6.5, 6.5), None))
    assert unknown.stats.saturated == 0  # never reached: nothing repeats at the clip
    plateau = PhonePdr(RATE)
    g = imu.gyro_body.copy()
    g[(imu.t > 20.0) & (imu.t < 20.5), 2] = 7.0  # a flat top beyond a walking phone's range
    plateau.process(ImuBlock(imu.t, imu.accel_body, g, None))
    assert plateau.stats.saturated >= 20


def test_marks_on_straight_walks_are_the_marks_own_turns():
    """Two headings that both see a straight walk east; the waypoints zig-zag 1 m either side every
    7 m. What ``marks_on_straight_walks`` reports is the marks' own turns (2 atan(2/7) each), and a
    walk whose headings do turn is not counted as straight."""
    from hybridloc.pdr.evaluate import TraceRun, marks_on_straight_walks
    from hybridloc.pdr.steplength import ConstantLength
    from hybridloc.types import StepEvent

    t = np.arange(0.5, 40.0, 0.5)  # steps of 0.5 m every 0.5 s: 1 m/s east
    feats = [StepFeatures(0.5, 3.0, 1.0)] * len(t)
    wp_t = np.arange(0.0, 36.0, 7.0)
    wp_xy = np.column_stack([wp_t, np.where(np.arange(wp_t.size) % 2 == 0, 1.0, -1.0)])

    def run(heading):
        steps = [StepEvent(t=float(ti), length=0.5, heading=heading(ti), sigma_length=0.05, sigma_heading=0.05) for ti in t]
        return TraceRun("walk", steps, feats, wp_t, wp_xy, np.array([s.heading for s in steps]))

    seen, n = marks_on_straight_walks([run(lambda ti: 0.0)], ConstantLength(0.5))
    assert n == wp_t.size - 2 and seen.size == n
    assert np.allclose(seen, math.degrees(2 * math.atan2(2.0, 7.0)), atol=0.5)  # the marks' turn, to the track's interpolation
    curving = run(lambda ti: 0.3 * math.sin(ti / 3.0))  # swings +-17 deg: these turns are the walker's
    seen, n = marks_on_straight_walks([curving], ConstantLength(0.5))
    assert n == wp_t.size - 2 and seen.size < n

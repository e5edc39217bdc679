"""IMU synthesis for simulated walks: a phone in the hand at 50 Hz and a foot-mounted unit at 200 Hz,
with sensor error models by grade.

Phone (held flat, screen up, top edge forward): specific force R^T (0, 0, g + a_v), with the vertical
bounce a_v peaking at each heel strike (the centre of mass lowest, double support),
a_v = (A_k/2) cos(2 pi (t - t_k) / T_k) around step k, plus the hand's own jitter. The bounce is the
body's: the step's vertical CoM excursion h_k (:func:`.walker.com_excursion`, the inverted pendulum
of the stance leg) moved once per step period T_k swings the acceleration by h_k (2 pi / T_k)^2 peak
to peak, which the phone in the hand sees times a gain G per walk (:data:`PHONE_BOUNCE_GAIN`: the
heel strike's transient and the arm), A_k = G h_k (2 pi / T_k)^2, kept within 0.5-3x the walker's
natural bounce (a short stopping step still bounces). The hand adds smooth vertical jitter while
walking (:data:`HAND_JITTER`). So the step length follows the bounce the way the inverted pendulum
makes it (a Weinberg-type model with one constant is off by each walker's leg, correction factor,
walk ratio and grip, and per step by the jitter). The attitude is R = Rz(psi - pi/2) (body +y along the
heading psi), so the gyro reads (0, 0, dpsi/dt) when walking. Handling (while standing) is a real
motion: the phone is picked up, turned about (a smooth random rotation theta(t), about 0.5 rad per axis,
that starts and ends at zero: put back in the same grip) and shaken with smooth accelerations, so the
attitude is R = Rz(psi - pi/2) Exp(theta), the gyro reads that attitude's body rate and the
accelerometer and magnetometer see the turned phone: the three sensors agree, as on a real phone.
The magnetometer reads the Earth field (48 uT, dip 63 deg) plus a smooth indoor disturbance field.

Rotation vector (:func:`phone_sensors`): Android's TYPE_ROTATION_VECTOR, the phone's own fused
attitude (gyro, accelerometer, magnetometer; body to ENU with y to magnetic North, as the real
traces log it). Its heading follows the magnetometer's through a first-order fusion of time constant
:data:`RV_MAG_TAU_S`, de/dt = b(t) - (e - e_m(t)) / tau, so its heading error e is the magnetometer's
heading error e_m low-passed, plus a residual gyro bias b (turn-on :data:`RV_GYRO_BIAS` and a random
walk) that the pull holds at b tau. e_m comes from the same field the magnetometer reads: a
horizontal field h (nav frame) at angle atan2(h_y, h_x) makes North look rotated by that minus pi/2,
and every heading read against it is off by e_m = pi/2 - atan2(h_y, h_x). The estimated attitude is
Rz(e) R (tilt is taken as exact: the accelerometer levels it within a degree).

Foot (body x forward, y left, z up): per stride (two steps) the foot stands still for 60 % of the
stride and swings 40 %. The swing's nav-frame acceleration is chosen sample by sample,
a_i = A sin(2 pi i / N), which sums to exactly zero over the swing, and the truth is *defined* as the
discrete strapdown integral of it (the same scheme as :func:`hybridloc.ins.strapdown.mechanise`), so a
noiseless foot INS must reproduce the truth to rounding. The gyro is the discrete log of consecutive
truth attitudes; the foot pitches up to 25 degrees during the swing.

Sensor errors (:data:`GRADES`, from datasheets of the classes the seeds use: consumer MEMS as in
phones, industrial as the MicroStrain 3DM-GX3-25 of PyShoe / Ojeda's unit, tactical): white noise
densities, turn-on biases, bias random walk (instability), scale factors and saturation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..ins.strapdown import quat_from_rotvec, quat_mult, quat_to_dcm
from ..types import ImuBlock
from ..units import DEG, G0, UT_TO_T, wrap_angle
from .walker import Walk


@dataclass(frozen=True)
class SensorGrade:
    accel_noise: float  # m/s^2/sqrt(Hz)
    gyro_noise: float  # rad/s/sqrt(Hz)
    accel_bias: float  # m/s^2, turn-on (1 sigma)
    gyro_bias: float  # rad/s, turn-on (1 sigma)
    accel_bias_rw: float  # m/s^3/sqrt(Hz)
    gyro_bias_rw: float  # rad/s^2/sqrt(Hz)
    scale: float  # relative scale-factor error (1 sigma)
    accel_range: float  # m/s^2
    gyro_range: float  # rad/s


GRADES = {
    # phone MEMS (e.g. BMI160: 180 ug/rtHz, 0.007 dps/rtHz, +-40 mg, +-3 dps turn-on)
    "consumer": SensorGrade(180e-6 * G0, 0.007 * DEG, 0.04 * G0, 1.0 * DEG, 1e-3, 2e-5, 0.005, 4 * G0, 2000 * DEG),
    # MicroStrain 3DM-GX3-25 class: 80 ug/rtHz, 0.03 dps/rtHz, bias stability 0.04 mg / 18 deg/h
    "industrial": SensorGrade(80e-6 * G0, 0.03 * DEG, 0.002 * G0, 0.05 * DEG, 1e-4, 5e-6, 0.0005, 16 * G0, 1200 * DEG),
    # tactical (e.g. ADIS16490-class or better): 30 ug/rtHz, 0.002 dps/rtHz, 1 deg/h stability
    "tactical": SensorGrade(30e-6 * G0, 0.002 * DEG, 0.0005 * G0, 0.002 * DEG, 2e-5, 2e-7, 0.0001, 40 * G0, 2000 * DEG),
}

EARTH_FIELD_T = 48.0 * UT_TO_T
EARTH_DIP = 63.0 * DEG


def apply_errors(t: np.ndarray, acc: np.ndarray, gyr: np.ndarray, grade: SensorGrade, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Add turn-on bias, bias random walk, white noise and scale factor, then saturate."""
    n = len(t)
    dt = float(np.median(np.diff(t))) if n > 1 else 0.01
    out = []
    for x, noise, bias, rw, rng_max in (
        (acc, grade.accel_noise, grade.accel_bias, grade.accel_bias_rw, grade.accel_range),
        (gyr, grade.gyro_noise, grade.gyro_bias, grade.gyro_bias_rw, grade.gyro_range),
    ):
        b = bias * rng.standard_normal(3) + np.cumsum(rw * math.sqrt(dt) * rng.standard_normal((n, 3)), axis=0)
        s = 1.0 + grade.scale * rng.standard_normal(3)
        y = x * s + b + noise / math.sqrt(dt) * rng.standard_normal((n, 3))
        out.append(np.clip(y, -rng_max, rng_max))
    return out[0], out[1]


def _full_scale(grade: str) -> dict:
    """The grade's full scale as ImuBlock fields (the simulated sensors clip there)."""
    return {"accel_range": GRADES[grade].accel_range, "gyro_range": GRADES[grade].gyro_range}


def _smooth_noise(rng: np.random.Generator, n: int, width: int) -> np.ndarray:
    k = np.exp(-0.5 * (np.arange(-3 * width, 3 * width + 1) / width) ** 2)
    k /= np.sqrt((k**2).sum())
    return np.convolve(rng.standard_normal(n + len(k)), k, mode="same")[:n]


#: s: a walker who stood turns to the next heading in this last moment before walking on
TURN_S = 1.0
#: Handling: rotation about each axis, rad (1 sigma), its correlation time, s, and the shaking, m/s^2.
HANDLING_ANGLE = 0.5
HANDLING_TIME_S = 0.5
HANDLING_ACCEL = 2.0


def _handle(
    idx: np.ndarray,
    t: np.ndarray,
    psi: np.ndarray,
    f_nav: np.ndarray,
    m_nav: np.ndarray,
    acc: np.ndarray,
    gyr: np.ndarray,
    mag: np.ndarray,
    rng: np.random.Generator,
):
    """One handling interval (samples ``idx``), written into acc, gyr and mag in place (module docstring);
    returns the phone's attitudes there (scipy Rotation, body to nav).

    theta(t) = w(t) n(t): n smooth unit noise per axis, w = HANDLING_ANGLE sin^2 of the interval's phase,
    so the phone leaves and returns to its grip smoothly. Attitude R_k = Rz(psi_k - pi/2) Exp(theta_k);
    the gyro at sample k is the body rate log(R_k^T R_(k+1)) / dt that carries it to the next sample
    (the last sample's rate is the one before it: the grip is back, the rate is ~0)."""
    from scipy.spatial.transform import Rotation

    m = len(idx)
    dt = float(np.median(np.diff(t[idx])))
    width = max(1, int(round(HANDLING_TIME_S / dt)))
    w = HANDLING_ANGLE * np.sin(math.pi * (np.arange(m) + 0.5) / m) ** 2
    theta = w[:, None] * np.column_stack([_smooth_noise(rng, m, width) for _ in range(3)])
    R = Rotation.from_euler("z", (psi[idx] - math.pi / 2)[:, None]) * Rotation.from_rotvec(theta)
    shake = HANDLING_ACCEL * np.column_stack([_smooth_noise(rng, m, width) for _ in range(3)]) * (w / HANDLING_ANGLE)[:, None]
    acc[idx] = R.inv().apply(f_nav[idx] + shake)
    mag[idx] = R.inv().apply(m_nav[idx])
    rate = (R[:-1].inv() * R[1:]).as_rotvec() / np.diff(t[idx])[:, None]
    gyr[idx] = np.vstack([rate, rate[-1:]])
    return R


def disturbance_field(rng: np.random.Generator, n_terms: int = 24, length: float = 4.0, amplitude: float = 8e-6):
    """A smooth random indoor magnetic disturbance (random Fourier features), tesla, f(x, y) -> (N, 3)."""
    w = rng.normal(0.0, 1.0 / length, (n_terms, 2))
    b = rng.uniform(0, 2 * math.pi, n_terms)
    c = rng.normal(0.0, amplitude * math.sqrt(2.0 / n_terms), (n_terms, 3))

    def field(xy: np.ndarray) -> np.ndarray:
        return np.cos(np.asarray(xy) @ w.T + b) @ c

    return field


#: The phone's peak-to-peak vertical acceleration (max - min over a step) over the CoM's
#: h (2 pi / T)^2: median and log sd between walks (how the phone is held, the heel strike's impact
#: transient riding on the sinusoid). The median is set on ILC site1: our PDR's max - min of the
#: vertical acceleration per step has a median of 11.1 m/s^2 there (285 walks), and a pendulum bounce
#: of 3.8 cm at 1.9 Hz (l 0.90 m, c 1.25, 0.65 m steps) swings 5.5 m/s^2; the jitter adds ~1 m/s^2.
PHONE_BOUNCE_GAIN = (1.6, 0.10)
#: The hand's vertical jitter while walking: sd, m/s^2, and correlation time, s. Set on ILC site1's
#: per-step max - min, whose spread within a walk (robust CV) is 0.30 and whose ratio to the mean
#: |a_v| over the step is 3.6 (a pure sinusoid: pi); a steady bounce alone gives 0.05 and 3.1.
HAND_JITTER = (1.4, 0.02)
#: s: the time constant of the rotation vector's pull to the magnetometer's heading
RV_MAG_TAU_S = 4.0
#: rad/s: residual gyro bias of the rotation vector's fusion (Android calibrates the gyro online),
#: turn-on 1 sigma, and its random walk, rad/s/sqrt(s)
RV_GYRO_BIAS = (0.05 * DEG, 0.002 * DEG)


@dataclass(frozen=True)
class PhoneSensors:
    """What a simulated phone logs: the IMU and Android's rotation vector."""

    imu: ImuBlock
    rotation_vector: tuple[np.ndarray, np.ndarray]  # (t (N,), body-to-ENU unit quaternions (N, 4) w x y z, w >= 0)
    bounce_gain: float  # G of this walk: the phone's peak-to-peak bounce over the CoM's h (2 pi / T)^2


def _field_along(mag_field, pos: np.ndarray, every: int = 5) -> np.ndarray:
    """The disturbance field at the (N, 2) positions, evaluated at every ``every``-th one and linear
    between: at walking speed 0.1 s apart is 0.13 m against the field's 4 m length, an interpolation
    error of ~(0.13 / 4)^2 / 8 of its amplitude (1e-4: 1 nT against the magnetometer's 400 nT noise)."""
    n = len(pos)
    if n <= 2 * every:
        return mag_field(pos)
    k = np.unique(np.concatenate([np.arange(0, n, every), [n - 1]]))
    coarse = mag_field(pos[k])
    i = np.arange(n)
    return np.column_stack([np.interp(i, k, coarse[:, j]) for j in range(coarse.shape[1])])


def phone_imu(walk: Walk, rng: np.random.Generator, rate: float = 50.0, grade: str | None = "consumer", mag_field=None) -> ImuBlock:
    """The phone's IMU over the walk (see module docstring); ``grade=None`` gives noiseless data."""
    return _phone(walk, rng, rate, grade, mag_field, rotation_vector=False)[0]


def phone_sensors(walk: Walk, rng: np.random.Generator, rate: float = 50.0, grade: str | None = "consumer", mag_field=None) -> PhoneSensors:
    """The phone's IMU and rotation vector (module docstring). The IMU is the one :func:`phone_imu`
    gives for the same ``rng`` (the rotation vector's errors are drawn from a child of it)."""
    imu, rv, gain = _phone(walk, rng, rate, grade, mag_field, rotation_vector=True)
    assert rv is not None
    return PhoneSensors(imu, rv, gain)


def _phone(walk: Walk, rng: np.random.Generator, rate: float, grade: str | None, mag_field, rotation_vector: bool):
    rv_rng = rng.spawn(1)[0] if rotation_vector else None  # spawning draws nothing from rng
    t = np.arange(walk.t0, walk.t1, 1.0 / rate)
    n = len(t)
    ts = np.array([s.t for s in walk.steps])
    hs = np.unwrap(np.array([s.heading for s in walk.steps])) if walk.steps else np.zeros(0)
    # heading: turn during the step that changes it (linear between step times); across a pause the
    # walker stands facing the way they came and turns in the last TURN_S before walking on (not
    # slowly through the whole pause, which would leave no still moment)
    T_nat = walk.step_length / walk.speed
    kt, kh = list(ts), list(hs)
    for i in np.flatnonzero(np.diff(ts) > 2.0 * T_nat)[::-1]:
        turn_s = min(TURN_S, 0.5 * (ts[i + 1] - ts[i]))
        kt.insert(i + 1, ts[i + 1] - turn_s)
        kh.insert(i + 1, hs[i])
    psi = np.interp(t, kt, kh) if len(ts) else np.zeros(n)
    dpsi = np.gradient(psi, t) if n > 1 else np.zeros(n)
    av = np.zeros(n)
    gain = PHONE_BOUNCE_GAIN[0] * math.exp(PHONE_BOUNCE_GAIN[1] * float(rng.standard_normal()))
    if len(ts):
        k = np.clip(np.searchsorted(ts, t), 0, len(ts) - 1)
        k0 = np.clip(k - 1, 0, len(ts) - 1)
        # nearest step event and its period
        near = np.where(np.abs(t - ts[k0]) < np.abs(t - ts[k]), k0, k)
        # a step's period is the time since the previous step, but a first step after standing takes
        # no longer than a slow step (the bounce is the step's, not a slow swell through the pause)
        T_step = np.minimum(np.diff(np.concatenate([[ts[0] - 0.55], ts])), 1.5 * T_nat)
        h_nat = walk.natural_bounce
        h = np.array([s.bounce if s.bounce > 0 else h_nat for s in walk.steps])
        # A_k = G h_k (2 pi / T_k)^2 (module docstring), within 0.5-3x the natural step's
        A_nat = gain * h_nat * (2 * math.pi / T_nat) ** 2
        A = np.clip(gain * h * (2 * math.pi / T_step) ** 2, 0.5 * A_nat, 3.0 * A_nat)[near]
        phase = (t - ts[near]) / T_step[near]
        walking = np.abs(phase) <= 0.5
        av = np.where(walking, 0.5 * A * np.cos(2 * math.pi * phase), 0.0)
        if walking.any():
            width = max(1, int(round(HAND_JITTER[1] * rate)))
            av = av + np.where(walking, HAND_JITTER[0] * _smooth_noise(rng, n, width), 0.0)
    c, s = np.cos(psi - math.pi / 2), np.sin(psi - math.pi / 2)
    f_nav = np.column_stack([np.zeros(n), np.zeros(n), G0 + av])
    # R = Rz(psi - pi/2): body = R^T nav
    acc = np.column_stack([c * f_nav[:, 0] + s * f_nav[:, 1], -s * f_nav[:, 0] + c * f_nav[:, 1], f_nav[:, 2]])
    gyr = np.column_stack([np.zeros(n), np.zeros(n), dpsi])
    m_nav = np.tile([0.0, EARTH_FIELD_T * math.cos(EARTH_DIP), -EARTH_FIELD_T * math.sin(EARTH_DIP)], (n, 1))
    if mag_field is not None:
        pos, _ = walk.position_at(t)
        m_nav = m_nav + _field_along(mag_field, pos)
    mag = np.column_stack([c * m_nav[:, 0] + s * m_nav[:, 1], -s * m_nav[:, 0] + c * m_nav[:, 1], m_nav[:, 2]])
    handled_att = []
    for a, b, handled in walk.pauses:
        idx = np.flatnonzero((t >= a) & (t < b))
        if handled and len(idx) > 2:
            handled_att.append((idx, _handle(idx, t, psi, f_nav, m_nav, acc, gyr, mag, rng)))
    rv = _rotation_vector(t, psi, m_nav, handled_att, rv_rng) if rv_rng is not None else None
    if grade is None:
        return ImuBlock(t, acc, gyr, mag), rv, gain
    acc, gyr = apply_errors(t, acc, gyr, GRADES[grade], rng)
    mag = mag + 0.4 * UT_TO_T * rng.standard_normal(mag.shape)
    return ImuBlock(t, acc, gyr, mag, **_full_scale(grade)), rv, gain


def magnetic_heading_error(m_nav: np.ndarray) -> np.ndarray:
    """rad: the error of a heading read against the field ``m_nav`` (N, 3, nav frame): North looks
    rotated by atan2(h_y, h_x) - pi/2, so e_m = pi/2 - atan2(h_y, h_x) (0 in the Earth's field alone)."""
    return wrap_angle(math.pi / 2 - np.arctan2(m_nav[:, 1], m_nav[:, 0]))


def _rotation_vector(t: np.ndarray, psi: np.ndarray, m_nav: np.ndarray, handled_att, rng: np.random.Generator):
    """Android's rotation vector (module docstring): (t, quaternions w x y z with w >= 0)."""
    from scipy.signal import lfilter
    from scipy.spatial.transform import Rotation

    n = len(t)
    if n == 0:
        return t.copy(), np.zeros((0, 4))
    dt = float(np.median(np.diff(t))) if n > 1 else 0.02
    e_m = np.unwrap(magnetic_heading_error(m_nav))
    bias = RV_GYRO_BIAS[0] * float(rng.standard_normal()) + np.cumsum(RV_GYRO_BIAS[1] * math.sqrt(dt) * rng.standard_normal(n))
    # de/dt = b - (e - e_m) / tau, discretised exactly for a held input: e_k = a e_(k-1) + (1 - a) x_k,
    # x = e_m + b tau, a = exp(-dt / tau); started converged (e_0 = x_0)
    x = e_m + bias * RV_MAG_TAU_S
    a = math.exp(-dt / RV_MAG_TAU_S)
    e, _ = lfilter([1.0 - a], [1.0, -a], x, zi=[a * x[0]])
    # walking and standing the attitude is Rz(psi - pi/2), estimated Rz(psi - pi/2 + e)
    yaw = psi - math.pi / 2 + e
    q = np.column_stack([np.cos(yaw / 2), np.zeros(n), np.zeros(n), np.sin(yaw / 2)])
    for idx, R in handled_att:  # handled: Rz(e) R, R = Rz(psi - pi/2) Exp(theta)
        q[idx] = (Rotation.from_euler("z", e[idx][:, None]) * R).as_quat(scalar_first=True)
    q[q[:, 0] < 0] *= -1.0  # Android's rotation vector carries x y z; w = sqrt(1 - |xyz|^2) >= 0
    return t.copy(), q


@dataclass
class FootTruth:
    t: np.ndarray
    pos: np.ndarray  # (N, 3) foot position, m
    quat: np.ndarray  # (N, 4) body-to-nav
    stance: np.ndarray  # (N,) bool


def foot_imu(
    walk: Walk,
    rng: np.random.Generator,
    rate: float = 200.0,
    grade: str | None = "industrial",
    stride_stance: float = 0.6,
    max_pitch: float = 25 * DEG,
) -> tuple[ImuBlock, FootTruth]:
    """The right foot's IMU and its truth (see module docstring). Strides join every second step."""
    dt = 1.0 / rate
    t = np.arange(walk.t0, walk.t1, dt)
    n = len(t)
    acc_nav = np.zeros((n, 3))
    h0 = walk.steps[0].heading if walk.steps else 0.0
    yaw = np.full(n, h0)
    pitch = np.zeros(n)
    stance = np.ones(n, bool)
    strides = walk.steps[1::2]
    prev_t = walk.t0
    prev_xy = np.array(walk.start[:2], float)
    cur_yaw = h0
    for st in strides:
        T = st.t - prev_t
        i0 = int(np.searchsorted(t, prev_t + stride_stance * T))
        i1 = int(np.searchsorted(t, st.t))
        N = i1 - i0
        target = np.array([st.x, st.y])
        d = target - prev_xy
        if N >= 8 and np.linalg.norm(d) > 1e-3:
            k = np.arange(1, N + 1)
            prof = np.sin(2 * math.pi * k / N)
            # displacement of the discrete scheme for a unit profile: sum over j of (v_{j-1} dt + a_j dt^2 / 2)
            v = np.cumsum(prof) * dt
            disp = float(np.sum(np.concatenate([[0.0], v[:-1]]) * dt + 0.5 * prof * dt * dt))
            amp = d / disp
            acc_nav[i0:i1, :2] = prof[:, None] * amp[None, :]
            dz = sum(s.dz for s in walk.steps if prev_t < s.t <= st.t)
            if dz:
                acc_nav[i0:i1, 2] = prof * (dz / disp)
            stance[i0:i1] = False
            new_yaw = math.atan2(d[1], d[0])
            dyaw = math.atan2(math.sin(new_yaw - cur_yaw), math.cos(new_yaw - cur_yaw))
            yaw[i0:i1] = cur_yaw + dyaw * (k / N)
            cur_yaw = cur_yaw + dyaw
            pitch[i0:i1] = max_pitch * np.sin(2 * math.pi * k / N)
            yaw[i1:] = cur_yaw
        prev_t, prev_xy = st.t, target if N >= 8 else prev_xy
    # truth attitude: R = Rz(yaw) Ry(-pitch) (nose-up pitch about the body's left axis)
    quat = np.zeros((n, 4))
    for i in range(n):
        qz = quat_from_rotvec(np.array([0.0, 0.0, yaw[i]]))
        qy = quat_from_rotvec(np.array([0.0, -pitch[i], 0.0]))
        q = quat_mult(qz, qy)
        quat[i] = q / np.linalg.norm(q)
    # discrete truth: integrate the chosen nav accelerations with the strapdown scheme
    pos = np.zeros((n, 3))
    vel = np.zeros(3)
    p = np.array([walk.start[0], walk.start[1], walk.start[2] * 3.5])
    pos[0] = p
    gyr = np.zeros((n, 3))
    acc = np.zeros((n, 3))
    acc[0] = quat_to_dcm(quat[0]).T @ np.array([0.0, 0.0, G0])
    for i in range(1, n):
        # the interval the INS will see: t is Unix time, whose float spacing (2.4e-7 s near 1.7e9)
        # makes consecutive differences differ from 1/rate in the 5th digit
        dt = float(t[i] - t[i - 1])
        a = acc_nav[i]
        p = p + vel * dt + 0.5 * a * dt * dt
        vel = vel + a * dt
        pos[i] = p
        # the specific force at t_i, in the body frame at t_i (what the INS resolves with q_i)
        acc[i] = quat_to_dcm(quat[i]).T @ (a + np.array([0.0, 0.0, G0]))
        dq = quat_mult(np.array([quat[i - 1][0], -quat[i - 1][1], -quat[i - 1][2], -quat[i - 1][3]]), quat[i])
        if dq[0] < 0:
            dq = -dq
        vn = np.linalg.norm(dq[1:])
        ang = 2 * math.atan2(vn, dq[0])
        gyr[i] = (dq[1:] * (ang / vn) if vn > 1e-15 else 2 * dq[1:]) / dt
    if grade is None:
        return ImuBlock(t, acc, gyr), FootTruth(t, pos, quat, stance)
    acc, gyr = apply_errors(t, acc, gyr, GRADES[grade], rng)
    return ImuBlock(t, acc, gyr, **_full_scale(grade)), FootTruth(t, pos, quat, stance)

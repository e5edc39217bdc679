"""IMU synthesis for simulated walks: a phone in the hand at 50 Hz and a foot-mounted unit at 200 Hz,
with sensor error models by grade.

Phone (held flat, screen up, top edge forward): specific force R^T (0, 0, g + a_v), with the vertical
bounce a_v peaking at each heel strike, a_v = (A/2) cos(2 pi (t - t_k) / T_k) around step k, and the
peak-to-peak bounce A chosen so that the bounce-height model with the walker's own K gives the true
step length: mean |a_v| = A / pi = (L / K)^3 / T^2, kept within a factor 2 of the walker's natural
bounce (short turning steps still bounce). The attitude is R = Rz(psi - pi/2) (body +y along the
heading psi), so the gyro reads (0, 0, dpsi/dt) when walking. Handling (while standing) is a real
motion: the phone is picked up, turned about (a smooth random rotation theta(t), about 0.5 rad per axis,
that starts and ends at zero: put back in the same grip) and shaken with smooth accelerations, so the
attitude is R = Rz(psi - pi/2) Exp(theta), the gyro reads that attitude's body rate and the
accelerometer and magnetometer see the turned phone: the three sensors agree, as on a real phone.
The magnetometer reads the Earth field (48 uT, dip 63 deg) plus a smooth indoor disturbance field.

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
from ..units import DEG, G0, UT_TO_T
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
) -> None:
    """One handling interval (samples ``idx``), written into acc, gyr and mag in place (module docstring).

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


def disturbance_field(rng: np.random.Generator, n_terms: int = 24, length: float = 4.0, amplitude: float = 8e-6):
    """A smooth random indoor magnetic disturbance (random Fourier features), tesla, f(x, y) -> (N, 3)."""
    w = rng.normal(0.0, 1.0 / length, (n_terms, 2))
    b = rng.uniform(0, 2 * math.pi, n_terms)
    c = rng.normal(0.0, amplitude * math.sqrt(2.0 / n_terms), (n_terms, 3))

    def field(xy: np.ndarray) -> np.ndarray:
        return np.cos(np.asarray(xy) @ w.T + b) @ c

    return field


def phone_imu(walk: Walk, rng: np.random.Generator, rate: float = 50.0, grade: str | None = "consumer", mag_field=None) -> ImuBlock:
    """The phone's IMU over the walk (see module docstring); ``grade=None`` gives noiseless data."""
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
    if len(ts):
        k = np.clip(np.searchsorted(ts, t), 0, len(ts) - 1)
        k0 = np.clip(k - 1, 0, len(ts) - 1)
        # nearest step event and its period
        near = np.where(np.abs(t - ts[k0]) < np.abs(t - ts[k]), k0, k)
        # a step's period is the time since the previous step, but a first step after standing takes
        # no longer than a slow step (the bounce is the step's, not a slow swell through the pause)
        T = np.minimum(np.diff(np.concatenate([[ts[0] - 0.55], ts])), 1.5 * T_nat)[near]
        # On stairs the horizontal step is short but the body still bounces like a full step:
        # use the walker's natural step length there.
        # The bounce-height relation (mean |a_v| = A / pi = (L / K)^3 / T^2) holds for steady walking; a
        # short step (turning, stopping) still bounces at least half as hard as a full one, and a stair
        # step like a full one.
        L = np.array([s.length if s.dz == 0 else walk.step_length for s in walk.steps])[near]
        A_nat = math.pi * (walk.step_length / walk.length_k) ** 3 / T_nat**2
        A = A_nat * np.clip((L / walk.step_length) ** 3 * (T_nat / T) ** 2, 0.5, 2.0)
        phase = (t - ts[near]) / T
        walking = np.abs(phase) <= 0.5
        av = np.where(walking, 0.5 * A * np.cos(2 * math.pi * phase), 0.0)
    c, s = np.cos(psi - math.pi / 2), np.sin(psi - math.pi / 2)
    f_nav = np.column_stack([np.zeros(n), np.zeros(n), G0 + av])
    # R = Rz(psi - pi/2): body = R^T nav
    acc = np.column_stack([c * f_nav[:, 0] + s * f_nav[:, 1], -s * f_nav[:, 0] + c * f_nav[:, 1], f_nav[:, 2]])
    gyr = np.column_stack([np.zeros(n), np.zeros(n), dpsi])
    pos, _ = walk.position_at(t)
    m_nav = np.tile([0.0, EARTH_FIELD_T * math.cos(EARTH_DIP), -EARTH_FIELD_T * math.sin(EARTH_DIP)], (n, 1))
    if mag_field is not None:
        m_nav = m_nav + mag_field(pos)
    mag = np.column_stack([c * m_nav[:, 0] + s * m_nav[:, 1], -s * m_nav[:, 0] + c * m_nav[:, 1], m_nav[:, 2]])
    for a, b, handled in walk.pauses:
        idx = np.flatnonzero((t >= a) & (t < b))
        if handled and len(idx) > 2:
            _handle(idx, t, psi, f_nav, m_nav, acc, gyr, mag, rng)
    if grade is None:
        return ImuBlock(t, acc, gyr, mag)
    acc, gyr = apply_errors(t, acc, gyr, GRADES[grade], rng)
    mag = mag + 0.4 * UT_TO_T * rng.standard_normal(mag.shape)
    return ImuBlock(t, acc, gyr, mag, **_full_scale(grade))


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

"""Phone attitude and heading: a complementary (Mahony-type) filter with magnetic disturbance rejection.

State: the body-to-nav quaternion ``q = (w, x, y, z)`` (nav = ENU with y toward magnetic North) and
a gyro bias estimate. Each sample:

1. **Gyro propagation**: q <- q * exp(0.5 (omega - b) dt).
2. **Tilt correction** from the accelerometer: the error between measured up (a/|a|) and predicted
   up (R^T e_z) drives omega as in Mahony et al. (2008), weighted down when | |a| - g | is large
   (walking accelerations) so steps do not tilt the estimate.
3. **Yaw correction** from the magnetometer, about the nav vertical only (so a disturbed field can
   never tilt the attitude), applied only while the field looks clean (Harle's survey sec. V-B:
   Kim & Park's magnitude/dip checks and Afzal et al.'s gyro-vs-magnetometer consistency):
   * magnitude within ``mag_norm_tol`` of the reference field strength,
   * dip (inclination) within ``mag_dip_tol`` of the reference dip,
   * the magnetometer's heading change over ``consistency_window`` agrees with the gyro's within
     ``consistency_tol``.
   The references are learned from the first clean seconds and follow slowly afterwards.
4. **Gyro bias**, which a phone's raw gyro has (1-3 deg/s at turn-on for consumer MEMS) and which
   would otherwise turn into a heading drift no magnetometer pull can hold in a disturbed building:
   * the accelerometer's tilt error drives the bias (Mahony's integral term) about the horizontal axes;
   * standing still (zero angular rate update, ZARU; the survey's Ojeda & Borenstein use it on the
     foot): while the specific force and the rate stay within ``still_acc_tol`` and
     ``still_gyro_dev`` of their 0.5 s averages, the rate within ``still_gyro_max`` of the bias
     estimate and the magnetic field (body frame) within ``still_mag_noise`` + ``still_mag_rate`` x the
     spell's duration of where it was when the spell began (a slow steady turn looks like a bias to
     the gyro, not to the magnetometer), for ``still_time``, the gyro reads its own bias (the mean of
     what was read still, then averaged over ``zaru_tau``).
     While still, the magnetometer does not turn the heading (step 3 cannot tell a clean field from
     a steady disturbance when nothing moves).

All per-sample arithmetic is plain Python floats: at 50 Hz this is several times faster than
numpy on 3-vectors, and the filter is inherently sequential.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..units import DEG, G0


@dataclass
class AttitudeConfig:
    kp_acc: float = 1.0  # tilt correction gain, rad/s per unit error
    ki_acc: float = 0.005  # gyro-bias integral gain (acc), rad/s^2 per unit error
    # yaw correction rate, 1/s: time constant ~30 s. Indoors the field is disturbed most of the time;
    # a slow pull keeps the gyro's heading changes and still bounds its drift over minutes. With the
    # gyro bias read while standing (ZARU), less pull is better on both data sets. ILC site1 eval
    # pdr-phone, k_mag 0 / 0.01 / 0.02 / 0.03 / 0.05 / 0.1: PDR-only waypoint error 3.88 / 3.90 / 3.91 /
    # 3.93 / 3.97 / 4.05 m, heading-change median 9.0 / 8.9 / 8.7 / 8.6 / 9.0 / 9.0 deg. The demo's
    # simulated walks: median heading error 2.0 (k_mag 0) / 4.7 (0.03) / 10.4 (0.1) deg. 0 would leave
    # a phone with no absolute heading for hours; 0.03 keeps one.
    k_mag: float = 0.03
    acc_gate: float = 0.25  # relative | |a| - g | / g beyond which the tilt correction fades out
    #: s; the tilt correction uses the accelerometer low-passed in the body frame over this time,
    #: carried through rotations by the gyro (d g_b/dt = -w x g_b): over a step cycle the body's
    #: bounce averages out and gravity remains, so walking - whose raw |a| swings beyond the gate
    #: most of the time - keeps correcting the tilt (a phone re-gripped while walking re-levels in
    #: seconds, not never). 0: the raw accelerometer.
    gravity_tau: float = 1.0
    mag_norm_tol: float = 0.15  # relative deviation of |B| from the reference accepted as clean
    mag_dip_tol: float = 8.0 * DEG  # dip deviation accepted as clean, rad
    consistency_window: float = 0.5  # s
    consistency_tol: float = 8.0 * DEG  # rad over the window
    settle_time: float = 1.0  # s of clean field before the magnetometer corrects yaw again
    zaru: bool = True  # read the gyro bias while standing still (as FootInsConfig.zaru on the foot)
    #: still: the specific force within this of its own 0.5 s average, m/s^2 (a hand's tremor is
    #: ~0.05-0.1; not |a| against g, which an accelerometer bias of 0.04 g would already fail) ...
    still_acc_tol: float = 0.25
    #: ... the rate within ``still_gyro_dev`` of its own average, rad/s ...
    still_gyro_dev: float = 0.03
    #: ... and, with a magnetometer, the field in the body frame turned since the spell began by less
    #: than ``still_mag_noise`` + ``still_mag_rate`` x its duration (the one sensor that sees a slow
    #: steady turn, which the gyro alone cannot tell from a bias; 0.3 uT of noise on 45 uT is 0.4 deg)
    #: and the rate within ``still_gyro_max`` of the bias estimate; without one, within
    #: ``still_gyro_max_nomag`` (a person standing and turning slowly, 4 deg/s = 0.07 rad/s, is not
    #: still; a bias beyond it, 3 sigma of a consumer gyro's turn-on bias, is not learned)
    still_mag_noise: float = 0.5 * DEG
    still_mag_rate: float = 0.5 * DEG
    still_gyro_max: float = 0.15
    still_gyro_max_nomag: float = 0.05
    still_time: float = 0.5  # s the stillness must last before the gyro is read as bias
    zaru_tau: float = 2.0  # s: averaging time of the bias while still
    max_bias: float = 0.1  # rad/s: bias estimates are kept within this (a gyro beyond it is broken)


def quat_mul(a, b):
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_normalize(q):
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def quat_to_rot(q):
    """R_body_to_nav as three row tuples."""
    w, x, y, z = q
    return (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )


def forward_heading_of(R) -> float:
    """Heading (rad, CCW from nav East) of a phone's forward direction given R_body_to_nav: the
    horizontal projection of body +y (top edge, phone flat) plus body -z (back, phone upright)."""
    return math.atan2(R[1][1] - R[1][2], R[0][1] - R[0][2])


def forward_headings(quat_wxyz):
    """:func:`forward_heading_of` for an (N, 4) array of body-to-nav quaternions (e.g. Android's
    rotation vector, whose nav frame is the same ENU with y toward magnetic North)."""
    w, x, y, z = np.asarray(quat_wxyz, float).T
    r01, r02 = 2 * (x * y - w * z), 2 * (x * z + w * y)
    r11, r12 = 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    return np.arctan2(r11 - r12, r01 - r02)


def rot_to_quat(R):
    """Shepperd's method, R as nested sequences (body to nav)."""
    tr = R[0][0] + R[1][1] + R[2][2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        return quat_normalize(((s / 4), (R[2][1] - R[1][2]) / s, (R[0][2] - R[2][0]) / s, (R[1][0] - R[0][1]) / s))
    if R[0][0] > R[1][1] and R[0][0] > R[2][2]:
        s = math.sqrt(1.0 + R[0][0] - R[1][1] - R[2][2]) * 2
        return quat_normalize(((R[2][1] - R[1][2]) / s, s / 4, (R[0][1] + R[1][0]) / s, (R[0][2] + R[2][0]) / s))
    if R[1][1] > R[2][2]:
        s = math.sqrt(1.0 + R[1][1] - R[0][0] - R[2][2]) * 2
        return quat_normalize(((R[0][2] - R[2][0]) / s, (R[0][1] + R[1][0]) / s, s / 4, (R[1][2] + R[2][1]) / s))
    s = math.sqrt(1.0 + R[2][2] - R[0][0] - R[1][1]) * 2
    return quat_normalize(((R[1][0] - R[0][1]) / s, (R[0][2] + R[2][0]) / s, (R[1][2] + R[2][1]) / s, s / 4))


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _norm(a):
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


def triad(acc, mag):
    """Initial body-to-nav quaternion from one accelerometer (up) and magnetometer (North) reading.

    With no magnetometer the yaw is set so that the device's forward axis points East (heading 0).
    """
    an = _norm(acc)
    up = (acc[0] / an, acc[1] / an, acc[2] / an)
    if mag is not None and _norm(mag) > 0:
        east = _cross(mag, up)
        en = _norm(east)
    else:
        en = 0.0
    if en < 1e-9:  # no (usable) magnetometer: pick any horizontal axis as East
        ref = (0.0, 1.0, 0.0) if abs(up[1]) < 0.9 else (1.0, 0.0, 0.0)
        north = _cross(up, _cross(ref, up))
        nn = _norm(north)
        north = (north[0] / nn, north[1] / nn, north[2] / nn)
        east = _cross(north, up)
    else:
        east = (east[0] / en, east[1] / en, east[2] / en)
        north = _cross(up, east)
    # Rows of R_nav_to_body^T ... R_body_to_nav has rows = nav axes expressed in body.
    R = (east, north, up)
    return rot_to_quat(R)


class AttitudeFilter:
    """Streaming attitude estimator; call :meth:`update` once per sample."""

    def __init__(self, config: AttitudeConfig | None = None):
        self.cfg = config or AttitudeConfig()
        self._q: tuple[float, float, float, float] | None = None
        #: R_body_to_nav of ``q`` (:func:`quat_to_rot`), kept with it: every sample reads it several times
        self.R: tuple | None = None
        self.bias = [0.0, 0.0, 0.0]
        self.t: float | None = None
        self.mag_ref_norm: float | None = None
        self.mag_ref_dip: float | None = None
        self.mag_ok = False
        self.mag_clean_since: float | None = None
        self.has_mag = False
        # (t, North's angle in nav) history for the gyro-vs-magnetometer consistency test
        self._hist: deque = deque()
        self.n_mag_rejected = 0
        self.n_mag_used = 0
        self._g_body: list[float] | None = None  # low-passed specific force in the body frame
        self._still_since: float | None = None
        self._still_mag: list[float] | None = None  # the field (body frame, 0.5 s average) when the still spell began
        self._mag_avg: list[float] | None = None
        self._acc_avg: list[float] | None = None  # 0.5 s averages for the stillness test
        self._gyr_avg: list[float] | None = None
        self.n_zaru = 0  # samples read as gyro bias (standing still)
        self.still = False  # held still for still_time: the ZARU is reading the bias

    @property
    def q(self) -> tuple[float, float, float, float] | None:
        """The body-to-nav attitude quaternion (w, x, y, z); setting it also sets :attr:`R`."""
        return self._q

    @q.setter
    def q(self, q) -> None:
        self._q = None if q is None else tuple(q)
        self.R = None if q is None else quat_to_rot(self._q)

    def initialise(self, t: float, acc, mag) -> None:
        self.q = triad(acc, mag)
        self.t = t
        self.has_mag = mag is not None

    def update(self, t: float, acc, gyr, mag=None) -> None:
        """One sample: time (s), specific force (m/s^2), rate (rad/s), field (T) or None."""
        if self._q is None:
            self.initialise(t, acc, mag)
            return
        dt = t - self.t
        self.t = t
        if not (0.0 < dt < 1.0):  # a gap: re-level from the accelerometer, keep yaw
            dt = min(max(dt, 0.0), 0.05)
        cfg = self.cfg
        q = self._q
        R = self.R
        if cfg.zaru:
            self._zaru(t, dt, acc, gyr, mag)
        wx, wy, wz = gyr[0] - self.bias[0], gyr[1] - self.bias[1], gyr[2] - self.bias[2]
        if cfg.gravity_tau > 0:
            g = self._g_body
            if g is None:
                g = [acc[0], acc[1], acc[2]]
            else:
                # the nav-fixed vector turns by -w x g in the body (c = w x g, _cross written out)
                c0, c1, c2 = wy * g[2] - wz * g[1], wz * g[0] - wx * g[2], wx * g[1] - wy * g[0]
                a = min(dt / cfg.gravity_tau, 1.0)
                p0, p1, p2 = g[0] - c0 * dt, g[1] - c1 * dt, g[2] - c2 * dt
                g = [p0 + a * (acc[0] - p0), p1 + a * (acc[1] - p1), p2 + a * (acc[2] - p2)]
            self._g_body = g
            acc = g
        # --- tilt correction (Mahony): e = a_hat x v, v = predicted up in body = third row of R
        an = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
        if an > 1e-6:
            rel = abs(an - G0) / G0
            w_acc = max(0.0, 1.0 - rel / cfg.acc_gate)
            if w_acc > 0:
                v = R[2]
                u0, u1, u2 = acc[0] / an, acc[1] / an, acc[2] / an
                e0, e1, e2 = u1 * v[2] - u2 * v[1], u2 * v[0] - u0 * v[2], u0 * v[1] - u1 * v[0]
                k = cfg.kp_acc * w_acc
                wx += k * e0
                wy += k * e1
                wz += k * e2
                ki = cfg.ki_acc * w_acc * dt
                bias = self.bias
                bias[0] -= ki * e0
                bias[1] -= ki * e1
                bias[2] -= ki * e2
        # --- propagate: q <- q * exp(0.5 w dt)
        ang = math.sqrt(wx * wx + wy * wy + wz * wz) * dt
        if ang > 1e-12:
            s = math.sin(ang / 2) / (ang / dt)
            dq = (math.cos(ang / 2), wx * s, wy * s, wz * s)
        else:
            dq = (1.0, wx * dt / 2, wy * dt / 2, wz * dt / 2)
        # quat_normalize(quat_mul(q, dq)) and quat_to_rot, written out (the same operations)
        aw, ax, ay, az = q
        bw, bx, by, bz = dq
        w = aw * bw - ax * bx - ay * by - az * bz
        x = aw * bx + ax * bw + ay * bz - az * by
        y = aw * by - ax * bz + ay * bw + az * bx
        z = aw * bz + ax * by - ay * bx + az * bw
        n = math.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / n, x / n, y / n, z / n
        q = (w, x, y, z)
        R = (
            (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
        )
        # --- magnetometer yaw correction with disturbance rejection
        if mag is not None:
            self.has_mag = True
            mn = math.sqrt(mag[0] * mag[0] + mag[1] * mag[1] + mag[2] * mag[2])
            m_nav = (
                R[0][0] * mag[0] + R[0][1] * mag[1] + R[0][2] * mag[2],
                R[1][0] * mag[0] + R[1][1] * mag[1] + R[1][2] * mag[2],
                R[2][0] * mag[0] + R[2][1] * mag[1] + R[2][2] * mag[2],
            )
            if mn > 0:
                dip = math.asin(max(-1.0, min(1.0, -m_nav[2] / mn)))
                yaw_err = math.atan2(m_nav[0], m_nav[1])  # angle of measured North east of nav +y
                self._hist.append((t, yaw_err))
                while self._hist and t - self._hist[0][0] > cfg.consistency_window:
                    self._hist.popleft()
                if self.mag_ref_norm is None:
                    self.mag_ref_norm, self.mag_ref_dip = mn, dip
                clean = abs(mn - self.mag_ref_norm) <= cfg.mag_norm_tol * self.mag_ref_norm and abs(dip - self.mag_ref_dip) <= cfg.mag_dip_tol
                if clean and len(self._hist) > 2:
                    # The attitude already follows the gyro, so in a steady field the measured
                    # North stays put in nav: any drift of it over the window is the field (or the
                    # gyro) disagreeing, and the magnetometer is not trusted.
                    mismatch = _wrap(yaw_err - self._hist[0][1])
                    clean = abs(mismatch) <= cfg.consistency_tol
                if clean:
                    if self.mag_clean_since is None:
                        self.mag_clean_since = t
                    # References follow slowly (building steel shifts the "clean" field over time).
                    a = min(1.0, dt / 30.0)
                    self.mag_ref_norm += a * (mn - self.mag_ref_norm)
                    self.mag_ref_dip += a * (dip - self.mag_ref_dip)
                else:
                    self.mag_clean_since = None
                self.mag_ok = clean and (t - self.mag_clean_since) >= cfg.settle_time if self.mag_clean_since is not None else False
                if self.mag_ok and self.still:
                    # Standing still, the consistency test sees nothing move and passes whatever the
                    # field: a steel frame's steady pull would turn the heading by tens of degrees
                    # over a pause. The gyro, its bias just read by the ZARU, holds the heading instead.
                    self.mag_ok = False
                if self.mag_ok:
                    self.n_mag_used += 1
                    # Rotate about nav z by k*err*dt: q <- qz * q, turning measured North onto +y.
                    d = cfg.k_mag * _wrap(yaw_err) * dt
                    # quat_normalize(quat_mul((cos d/2, 0, 0, sin d/2), q)) and quat_to_rot, written out
                    aw, ax, ay, az = math.cos(d / 2), 0.0, 0.0, math.sin(d / 2)
                    bw, bx, by, bz = q
                    w = aw * bw - ax * bx - ay * by - az * bz
                    x = aw * bx + ax * bw + ay * bz - az * by
                    y = aw * by - ax * bz + ay * bw + az * bx
                    z = aw * bz + ax * by - ay * bx + az * bw
                    n = math.sqrt(w * w + x * x + y * y + z * z)
                    w, x, y, z = w / n, x / n, y / n, z / n
                    q = (w, x, y, z)
                    R = (
                        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
                        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
                        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
                    )
                else:
                    self.n_mag_rejected += 1
        else:
            self.mag_ok = False
        self._q, self.R = q, R

    def _zaru(self, t: float, dt: float, acc, gyr, mag=None) -> None:
        """Zero angular rate update: a phone held still reads its gyro bias (see module docstring)."""
        cfg = self.cfg
        if self._acc_avg is None:
            self._acc_avg, self._gyr_avg = list(acc), list(gyr)
        a = min(dt / 0.5, 1.0)
        for i in range(3):
            self._acc_avg[i] += a * (acc[i] - self._acc_avg[i])
            self._gyr_avg[i] += a * (gyr[i] - self._gyr_avg[i])
        b, aa, ga = self.bias, self._acc_avg, self._gyr_avg
        still = (
            _norm((acc[0] - aa[0], acc[1] - aa[1], acc[2] - aa[2])) <= cfg.still_acc_tol
            and _norm((gyr[0] - ga[0], gyr[1] - ga[1], gyr[2] - ga[2])) <= cfg.still_gyro_dev
            and _norm((gyr[0] - b[0], gyr[1] - b[1], gyr[2] - b[2])) <= (cfg.still_gyro_max if mag is not None else cfg.still_gyro_max_nomag)
        )
        if mag is not None:  # the field's 0.5 s average: a turn of a few tenths of a degree shows through the noise
            if self._mag_avg is None:
                self._mag_avg = list(mag)
            for i in range(3):
                self._mag_avg[i] += a * (mag[i] - self._mag_avg[i])
            mag = self._mag_avg
        if still and mag is not None and self._still_mag is not None:  # set with _still_since, when a spell begins
            m0 = self._still_mag
            c = (m0[0] * mag[0] + m0[1] * mag[1] + m0[2] * mag[2]) / max(_norm(m0) * _norm(mag), 1e-30)
            still = c >= math.cos(min(cfg.still_mag_noise + cfg.still_mag_rate * (t - self._still_since), math.pi))
        self.still = False
        if not still:
            self._still_since = None
            self._still_mag = None
            return
        if self._still_since is None:
            self._still_since = t
            self._still_mag = list(mag) if mag is not None else None
        if t - self._still_since < cfg.still_time:
            return
        self.still = True
        self.n_zaru += 1
        # the plain mean of all rates read still while they span less than zaru_tau (the first short
        # pause gives the whole bias at once), an exponential average over zaru_tau afterwards
        a = max(min(dt / cfg.zaru_tau, 1.0), 1.0 / self.n_zaru)
        for i in range(3):
            self.bias[i] = min(max(self.bias[i] + a * (gyr[i] - self.bias[i]), -cfg.max_bias), cfg.max_bias)

    def forward_heading(self) -> float:
        """Heading (rad, CCW from nav East) of the device's forward direction, horizontal.

        Forward is the top edge of the screen when the phone is held flat (body +y) and the back of
        the phone when it is held upright (body -z); their horizontal projections are summed so the
        heading stays continuous as the phone tilts between the two.
        """
        return forward_heading_of(self.R)

    def vertical_accel(self, acc) -> float:
        """Vertical (nav up) component of specific force minus g, m/s^2."""
        R = self.R
        return R[2][0] * acc[0] + R[2][1] * acc[1] + R[2][2] * acc[2] - G0

    def horizontal_accel(self, acc) -> tuple[float, float]:
        R = self.R
        return (R[0][0] * acc[0] + R[0][1] * acc[1] + R[0][2] * acc[2], R[1][0] * acc[0] + R[1][1] * acc[1] + R[1][2] * acc[2])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi

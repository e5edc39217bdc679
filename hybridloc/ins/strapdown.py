"""Strapdown inertial mechanisation in a local-level ENU frame, with quaternions.

Ojeda & Borenstein (2007) eqs 1-4 in quaternion form, Earth rotation and Coriolis neglected (valid
for walks of minutes, as they note; a consumer MEMS gyro's noise dwarfs the 7.3e-5 rad/s Earth rate):

* attitude:  q_{k+1} = q_k (x) exp(0.5 (omega_k - b_g) dt)            (body-to-nav, Hamilton)
* velocity:  v_{k+1} = v_k + (R_{k+1} (f_k - b_a) + g_nav) dt,  g_nav = (0, 0, -g)
* position:  p_{k+1} = p_k + v_k dt + 0.5 (R_{k+1} (f_k - b_a) + g_nav) dt^2

Sample k (f_k, omega_k) is taken at the end of the step, so f_k is resolved with the attitude at that
time, R_{k+1} = R(q_{k+1}) (the same sample's rotation already applied).

The nominal state never carries uncertainty; the error-state filter (:mod:`.eskf`) does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..units import DEG


def normal_gravity(lat_rad: float = 45.0 * DEG, height_m: float = 0.0) -> float:
    """WGS84 normal gravity (Somigliana) with the free-air height correction, m/s^2."""
    s2 = math.sin(lat_rad) ** 2
    g0 = 9.7803253359 * (1 + 0.00193185265241 * s2) / math.sqrt(1 - 0.00669437999013 * s2)
    return g0 - 3.086e-6 * height_m


def skew(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def quat_mult_floats(a, b) -> tuple[float, float, float, float]:
    """The Hamilton product a (x) b of two (w, x, y, z) quaternions given as floats (4-vectors are
    cheaper outside numpy; the same IEEE operations as on numpy's scalars)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_mult(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array(quat_mult_floats(a, b))


def rotvec_to_quat_floats(px: float, py: float, pz: float) -> tuple[float, float, float, float]:
    """exp map of a rotation vector (rad) given as floats -> unit quaternion (w, x, y, z) as floats.
    (``**`` is libm's pow for numpy's scalars as for Python's: the same numbers either way.)"""
    a = math.sqrt(px**2 + py**2 + pz**2)
    if a < 1e-12:
        return 1.0, 0.5 * px, 0.5 * py, 0.5 * pz
    s = math.sin(a / 2) / a
    return math.cos(a / 2), px * s, py * s, pz * s


def quat_from_rotvec(phi: np.ndarray) -> np.ndarray:
    """exp map: rotation vector (rad) -> unit quaternion (w, x, y, z)."""
    return np.array(rotvec_to_quat_floats(float(phi[0]), float(phi[1]), float(phi[2])))


def dcm_from_quat_floats(w: float, x: float, y: float, z: float) -> np.ndarray:
    """R_body_to_nav of a unit quaternion (w, x, y, z) given as floats."""
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_to_dcm(q: np.ndarray) -> np.ndarray:
    """R_body_to_nav of a unit quaternion (w, x, y, z)."""
    return dcm_from_quat_floats(float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def dcm_to_quat(R: np.ndarray) -> np.ndarray:
    tr = np.trace(R)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = np.array([0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s])
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        q = np.array([(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s])
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        q = np.array([(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s])
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        q = np.array([(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s])
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def level_from_accel(f_body_mean: np.ndarray, yaw: float = 0.0) -> np.ndarray:
    """Body-to-nav quaternion whose roll and pitch put the mean specific force straight up.

    The body x axis's horizontal projection is placed at heading ``yaw`` (rad, CCW from East).
    Works for any mounting, including a z-down unit (specific force reading (0, 0, -g)).
    """
    up_b = f_body_mean / np.linalg.norm(f_body_mean)
    ref = np.array([1.0, 0.0, 0.0]) if abs(up_b[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x_h = ref - up_b * (ref @ up_b)  # body axis made horizontal
    x_h /= np.linalg.norm(x_h)
    y_h = np.cross(up_b, x_h)
    # Rows of R_body_to_nav are the nav axes in body coordinates; first build "x_h -> East".
    R0 = np.vstack([x_h, y_h, up_b])
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return dcm_to_quat(Rz @ R0)


@dataclass
class NominalState:
    """The INS nominal state. Shapes: p, v, b_a, b_g (3,); q (4,) body-to-nav, scalar first."""

    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    b_a: np.ndarray
    b_g: np.ndarray

    def copy(self) -> NominalState:
        return NominalState(self.p.copy(), self.v.copy(), self.q.copy(), self.b_a.copy(), self.b_g.copy())

    @property
    def R(self) -> np.ndarray:
        return quat_to_dcm(self.q)

    def plus(self, dx: np.ndarray) -> NominalState:
        """Inject an error state dx = (dp, dv, dtheta, db_a, db_g) (closed loop).

        The attitude error is a rotation in the nav frame: R_true = exp([dtheta]x) R.
        """
        # exp(dtheta) (x) q in Python floats (a fifth of the cost of the numpy 4-vectors, same numbers)
        q = np.array(quat_mult_floats(rotvec_to_quat_floats(*dx[6:9].tolist()), self.q.tolist()))
        return NominalState(self.p + dx[0:3], self.v + dx[3:6], _normalize(q), self.b_a + dx[9:12], self.b_g + dx[12:15])

    def minus(self, other: NominalState) -> np.ndarray:
        """The error state taking ``other`` to ``self`` (inverse of :meth:`plus`)."""
        dq = quat_mult(self.q, _conj(other.q))
        if dq[0] < 0:
            dq = -dq
        vnorm = np.linalg.norm(dq[1:])
        ang = 2 * math.atan2(vnorm, dq[0])
        dth = dq[1:] * (ang / vnorm) if vnorm > 1e-15 else 2 * dq[1:]
        return np.concatenate([self.p - other.p, self.v - other.v, dth, self.b_a - other.b_a, self.b_g - other.b_g])


def _normalize(q):
    return q / math.sqrt(float(q @ q))


def _conj(q):
    return np.array([q[0], -q[1], -q[2], -q[3]])


def mechanise(x: NominalState, f_body: np.ndarray, w_body: np.ndarray, dt: float, g: float) -> NominalState:
    """One strapdown step (module docstring equations); returns the new nominal state."""
    q = _normalize(quat_mult(x.q, quat_from_rotvec((w_body - x.b_g) * dt)))
    a_nav = quat_to_dcm(q) @ (f_body - x.b_a)
    a_nav[2] -= g
    return NominalState(x.p + x.v * dt + 0.5 * a_nav * dt * dt, x.v + a_nav * dt, q, x.b_a, x.b_g)

"""The foot filter's per-sample arithmetic, compiled with Numba (issue #24 point 6: 200 samples a second
for hours, where the interpreter's overhead on 3- and 15-vectors cost more than the arithmetic).

Each kernel performs the same IEEE operations, in the same order, as the numpy and Python-float code it
replaced (:mod:`.eskf` keeps the equations in its docstrings): the matrix products go to BLAS
(Numba's ``@`` on float64 arrays calls dgemm / dgemv through scipy's BLAS, the same OpenBLAS kernels
as numpy's) and the scalar expressions are written operand for operand, without fast-math or
contraction. The foot INS's outputs are identical to the bit (a digest of every output over the
shared foot trials, before and after; a test pins the step against the numpy code it replaced).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def strapdown_predict(q, p, v, b_a, b_g, f_body, w_body, dt, g, P, Phi, qd_rate):  # pragma: no cover - compiled
    """One strapdown step and covariance propagation of :meth:`.eskf.ErrorStateEkf.predict`.

    Rewrites the time-varying blocks of ``Phi`` in place and returns the new (q, p, v, P):

        q+ = q (x) exp((w - b_g) dt / 2), normalised    (Ojeda & Borenstein eq 1, quaternion form)
        a  = R(q+) (f - b_a)
        Phi = I + F dt:  Phi[dp, dv] = I dt, Phi[dv, dtheta] = -[a]x dt, Phi[dv, db_a] = Phi[dtheta, db_g] = -R dt
        P+ = Phi P Phi^T + diag(q_c) dt
        p+ = p + v dt + (a - g up) dt^2 / 2,   v+ = v + (a - g up) dt
    """
    # exp map of phi = (w - b_g) dt, its norm squared by multiplying: strapdown.rotvec_to_quat_floats
    # squares by pow, and the two differ in the last bit now and then (this filter's outputs would move)
    px = (w_body[0] - b_g[0]) * dt
    py = (w_body[1] - b_g[1]) * dt
    pz = (w_body[2] - b_g[2]) * dt
    ang = math.sqrt(px * px + py * py + pz * pz)
    if ang < 1e-12:
        bw, bx, by, bz = 1.0, 0.5 * px, 0.5 * py, 0.5 * pz
    else:
        s = math.sin(0.5 * ang) / ang
        bw, bx, by, bz = math.cos(0.5 * ang), px * s, py * s, pz * s
    aw, ax_, ay_, az_ = q[0], q[1], q[2], q[3]
    w = aw * bw - ax_ * bx - ay_ * by - az_ * bz
    x = aw * bx + ax_ * bw + ay_ * bz - az_ * by
    y = aw * by - ax_ * bz + ay_ * bw + az_ * bx
    z = aw * bz + ax_ * by - ay_ * bx + az_ * bw
    n = math.sqrt(w * w + x * x + y * y + z * z)
    q_new = np.empty(4)
    q_new[0], q_new[1], q_new[2], q_new[3] = w / n, x / n, y / n, z / n
    w, x, y, z = q_new[0], q_new[1], q_new[2], q_new[3]
    R = np.empty((3, 3))
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    fb = f_body - b_a
    a_nav = R @ fb
    ax, ay, az = a_nav[0], a_nav[1], a_nav[2]
    Phi[0, 3] = Phi[1, 4] = Phi[2, 5] = dt
    Phi[3, 7], Phi[3, 8] = az * dt, -ay * dt
    Phi[4, 6], Phi[4, 8] = -az * dt, ax * dt
    Phi[5, 6], Phi[5, 7] = ay * dt, -ax * dt
    for r in range(3):
        for c in range(3):
            m = R[r, c] * -dt
            Phi[3 + r, 9 + c] = m
            Phi[6 + r, 12 + c] = m
    P_new = Phi @ P @ Phi.T
    for k in range(15):
        P_new[k, k] += qd_rate[k] * dt  # Q_d is diagonal: R diag(s) R^T = s I for isotropic noise
    az -= g
    h = 0.5 * dt * dt
    p_new = np.empty(3)
    v_new = np.empty(3)
    p_new[0], p_new[1], p_new[2] = p[0] + v[0] * dt + h * ax, p[1] + v[1] * dt + h * ay, p[2] + v[2] * dt + h * az
    v_new[0], v_new[1], v_new[2] = v[0] + ax * dt, v[1] + ay * dt, v[2] + az * dt
    return q_new, p_new, v_new, P_new

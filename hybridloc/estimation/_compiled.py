"""The arithmetic of the one gated update (:func:`.update.correct`), compiled with Numba.

The foot filter makes a zero-velocity and a zero-angular-rate update at every stance sample, 200 a
second: on 15 x 15 covariances the interpreter's overhead around a dozen small products cost several
times the products themselves (issue #24 point 6). :func:`gated_joseph` performs the same IEEE
operations in the same order as the numpy code of :func:`.update._update_numpy`, which stays the
reference (and the path of robust kernels and of measurements of more than 3 components): the
products go to BLAS as numpy's do (Numba's ``@`` on float64 arrays calls dgemm / dgemv / ddot through
scipy's BLAS, the same OpenBLAS kernels as numpy's), and the closed-form inverse is
:func:`.update.inv_spd_small`'s, operand for operand, with no fast-math. A test holds the two to the
bit on random states and models.
"""

from __future__ import annotations

import numpy as np
from numba import njit

REJECTED, ACCEPTED, SINGULAR = 0, 1, -1


@njit(cache=True, nogil=True)
def _inv_spd_closed(S):  # pragma: no cover - compiled
    """:func:`.update.inv_spd_small` for 1-3 dimensions; ok False when the determinant is not positive."""
    m = S.shape[0]
    out = np.empty((m, m))
    if m == 1:
        out[0, 0] = 1.0 / S[0, 0]
        return out, True
    if m == 2:
        a, b, d = S[0, 0], S[0, 1], S[1, 1]
        det = a * d - b * b
        if det > 0.0:
            out[0, 0], out[0, 1], out[1, 0], out[1, 1] = d / det, -b / det, -b / det, a / det
            return out, True
        return out, False
    a, b, c = S[0, 0], S[0, 1], S[0, 2]
    e, f = S[1, 1], S[1, 2]
    i = S[2, 2]
    A, B, C = e * i - f * f, c * f - b * i, b * f - c * e
    det = a * A + b * B + c * C
    if det > 0.0:
        E, F, I_ = a * i - c * c, b * c - a * f, a * e - b * b
        out[0, 0], out[0, 1], out[0, 2] = A / det, B / det, C / det
        out[1, 0], out[1, 1], out[1, 2] = B / det, E / det, F / det
        out[2, 0], out[2, 1], out[2, 2] = C / det, F / det, I_ / det
        return out, True
    return out, False


@njit(cache=True, nogil=True)
def gated_joseph(P, H, R, y, sel_start, sel_stop, threshold):  # pragma: no cover - compiled
    """One gated Kalman update in Joseph form (the equations of :mod:`.update`), for m <= 3.

    ``sel_start >= 0``: H = [0 I 0] picks P's rows and columns sel_start:sel_stop (``H`` unused).
    Returns (status, S, nis, dx, P+): status REJECTED (NIS beyond ``threshold``; dx and P+ empty),
    ACCEPTED, or SINGULAR (S not positive definite in closed form: the caller takes numpy's path).
    """
    n = P.shape[0]
    if sel_start >= 0:
        PHt = np.ascontiguousarray(P[:, sel_start:sel_stop])  # P H^T: P's block columns, exactly
        HPHt = PHt[sel_start:sel_stop]
    else:
        PHt = P @ H.T
        HPHt = H @ PHt
    S = HPHt + R
    S = 0.5 * (S + S.T)
    empty = np.empty((0, 0))
    Sinv, ok = _inv_spd_closed(S)
    if not ok:
        return SINGULAR, S, 0.0, np.empty(0), empty
    nis = (y @ Sinv) @ y
    if nis > threshold:
        return REJECTED, S, nis, np.empty(0), empty
    K = PHt @ Sinv
    if sel_start >= 0:  # I - K H: K in the selected columns
        IKH = np.eye(n)
        IKH[:, sel_start:sel_stop] -= K
    else:
        IKH = np.eye(n) - K @ H
    P_new = IKH @ P @ IKH.T + K @ R @ K.T
    dx = K @ y
    return ACCEPTED, S, nis, dx, 0.5 * (P_new + P_new.T)

"""The interval RTS smoother against the textbook RTS on a linear system."""

import numpy as np

from hybridloc.ins.smoother import IntervalRts


def _kf_run(rng, n=30, update_at=(12, 29)):
    """A constant-velocity model (position, velocity) with position measurements at ``update_at``:
    forward Kalman filter, keeping what the textbook RTS and the interval smoother need."""
    dt = 0.1
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = np.diag([1e-4, 1e-2])
    H = np.array([[1.0, 0.0]])
    R = np.array([[0.01]])
    x = np.array([0.0, 1.0])
    P = np.diag([0.01, 0.04])
    xs_post, Ps_post, xs_pred, Ps_pred, dxs = [x.copy()], [P.copy()], [None], [None], [np.zeros(2)]
    for k in range(1, n):
        x_pred, P_pred = F @ x, F @ P @ F.T + Q
        dx = np.zeros(2)
        x, P = x_pred, P_pred
        if k in update_at:
            z = np.array([0.1 * k + rng.normal(0, 0.1) + 0.3])
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            dx = K @ (z - H @ x)
            x = x + dx
            P = (np.eye(2) - K @ H) @ P
        xs_post.append(x.copy()), Ps_post.append(P.copy()), xs_pred.append(x_pred), Ps_pred.append(P_pred), dxs.append(dx)
    return F, xs_post, Ps_post, xs_pred, Ps_pred, dxs


def test_interval_rts_equals_textbook_rts():
    rng = np.random.default_rng(7)
    F, xp, Pp, xpr, Ppr, dxs = _kf_run(rng)
    n = len(xp)
    # textbook RTS from the last sample back
    xs = [None] * n
    xs[-1] = xp[-1]
    for k in range(n - 2, -1, -1):
        C = Pp[k] @ F.T @ np.linalg.inv(Ppr[k + 1])
        xs[k] = xp[k] + C @ (xs[k + 1] - xpr[k + 1])
    rts = IntervalRts(0, dim=2)
    for k in range(1, n):
        rts.add(k, F, Pp[k - 1], Ppr[k], dxs[k])
    idx, e = rts.flush()
    assert list(idx) == list(range(n - 1))
    for j, k in enumerate(idx):
        np.testing.assert_allclose(xp[k] + e[j], xs[k], atol=1e-12)
    # the next interval starts at the last sample, and an empty flush is harmless
    idx2, e2 = rts.flush()
    assert idx2.size == 0 and e2.shape == (0, 2)


def test_interval_rts_restart_does_not_smooth_across():
    rng = np.random.default_rng(8)
    F, xp, Pp, xpr, Ppr, dxs = _kf_run(rng)
    rts = IntervalRts(0, dim=2)
    for k in range(1, 10):
        rts.add(k, F, Pp[k - 1], Ppr[k], dxs[k])
    rts.restart(10)  # e.g. a re-initialised filter at sample 10
    assert len(rts) == 0
    for k in range(11, 20):
        rts.add(k, F, Pp[k - 1], Ppr[k], dxs[k])
    idx, _ = rts.flush()
    assert idx[0] == 10 and idx.max() < 20

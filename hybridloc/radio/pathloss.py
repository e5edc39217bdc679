"""A log-distance path-loss model per transmitter, fitted to a floor's labelled readings: the radio
map's prior where the crowd or the survey has not walked (``BuildParams.prior = "path-loss"``).

Model (log-distance path loss, Rappaport, Wireless Communications, eq. 4.68, with the transmitter's
height offset ``h`` above the walker so the model stays finite under it):

    r(p) = P0 - 10 n log10( sqrt(|p - a|^2 + h^2) )        [dBm]

per transmitter j: its position a_j (m, floor frame), its power P0_j at 1 m and its exponent n_j,
fitted to the readings of the scans that heard it by robust least squares (soft-L1 with a 4 dB scale:
shops' walls and people make the residuals heavy-tailed). Not heard at all where the model says it
is strong is evidence too; it enters through the detection model

    P(detected | p) = sigmoid( (r(p) - r50) / s )                                  (one per floor)

fitted by logistic regression over every (labelled scan, transmitter of the floor) pair.

A kernel map (radiomap.py) knows a transmitter only within a few bandwidths of a labelled scan; a
walker on a path nobody labelled is then located at the nearest labelled place. The model extends
every transmitter over the whole walkable floor with a wide spread (its fit's residual sd), so a scan
from an unlabelled corridor can match the corridor's predicted fingerprint; near the data the kernel
estimates dominate as before (the prior has weight ``prior_weight`` samples).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: The transmitter's height above the phone, m (access points on a mall's ceiling, phones at the chest).
HEIGHT_M = 3.0
#: Fewest readings for a transmitter's own fit; transmitters with fewer keep the floor-mean prior.
MIN_READINGS = 8
#: Most readings a transmitter's fit uses (evenly thinned beyond): the fit's cost, not its answer
MAX_READINGS = 300
#: Path-loss exponent bounds: free space is 2, indoor NLOS 2.5-4.5 (Rappaport, table 4.2 / 4.6).
N_BOUNDS = (1.5, 5.0)


@dataclass
class PathLossModel:
    """Fitted transmitters of one floor (arrays over the floor's transmitter columns)."""

    a: np.ndarray  # (m, 2) position, m
    p0: np.ndarray  # (m,) dBm at 1 m
    n: np.ndarray  # (m,) exponent
    resid_sd: np.ndarray  # (m,) robust sd of the fit's residuals, dB
    ok: np.ndarray  # (m,) bool: fitted (else the caller keeps its own prior)
    r50: float  # dBm where detection is 50 % likely
    s50: float  # dB, logistic scale of detection

    def mean(self, cells: np.ndarray) -> np.ndarray:
        """Predicted RSSI (n_cells, m), dBm."""
        d2 = ((cells[:, None, :] - self.a[None, :, :]) ** 2).sum(-1) + HEIGHT_M**2
        return (self.p0[None, :] - 5.0 * self.n[None, :] * np.log10(d2)).astype(np.float32)

    def detection(self, mu: np.ndarray) -> np.ndarray:
        """Detection probability for predicted RSSI ``mu``."""
        z = np.clip((mu - self.r50) / self.s50, -30.0, 30.0)
        return (1.0 / (1.0 + np.exp(-z))).astype(np.float32)


def _fit_all(P: np.ndarray, r: np.ndarray, valid: np.ndarray, iters: int = 40) -> tuple[np.ndarray, ...]:
    """Every transmitter's (a, P0, n, robust residual sd) at once: ``P`` (m, k, 2) reading positions,
    ``r`` (m, k) dBm, ``valid`` (m, k) which entries are readings (rows padded to k).

    Levenberg-Marquardt on iteratively reweighted least squares, batched over the transmitters (a 4 x 4
    system each): the residual e = P0 - 5 n log10(d^2) - r with d^2 = |p - a|^2 + h^2 has the Jacobian

        de/dP0 = 1,   de/dn = -5 log10(d^2),   de/da = 10 n (p - a) / (ln(10) d^2),

    and soft-L1 weights w = 1 / sqrt(1 + (e / f)^2), f = 4 dB (the robust loss's IRLS weights; Triggs et
    al., Bundle adjustment, 2000, sec. 3.3). Bounds are kept by clipping each step's result."""
    m = len(r)
    vf = valid.astype(np.float64)
    cnt = vf.sum(1)
    # start: at the strongest readings, n = 2.5, P0 from the median reading's distance
    rr = np.where(valid, r, -np.inf)
    top = np.argsort(-rr, axis=1)[:, :3]
    a = np.take_along_axis(P, top[:, :, None], axis=1).mean(1)
    n = np.full(m, 2.5)
    d2 = ((P - a[:, None, :]) ** 2).sum(-1) + HEIGHT_M**2
    p0 = np.array([np.median((r[j] + 5.0 * n[j] * np.log10(d2[j]))[valid[j]]) for j in range(m)])
    lo_a = np.array([np.where(valid[j][:, None], P[j], np.inf).min(0) for j in range(m)]) - 30.0
    hi_a = np.array([np.where(valid[j][:, None], P[j], -np.inf).max(0) for j in range(m)]) + 30.0
    lam = np.full(m, 1e-2)
    f = 4.0

    def cost(a, p0, n):
        d2 = ((P - a[:, None, :]) ** 2).sum(-1) + HEIGHT_M**2
        e = p0[:, None] - 5.0 * n[:, None] * np.log10(d2) - r
        return (2.0 * f * f * (np.sqrt(1.0 + (e / f) ** 2) - 1.0) * vf).sum(1), e, d2

    c, e, d2 = cost(a, p0, n)
    for _ in range(iters):
        w = vf / np.sqrt(1.0 + (e / f) ** 2)
        J = np.empty((m, P.shape[1], 4))
        g = 10.0 * n[:, None] / (math.log(10.0) * d2)
        J[:, :, 0] = g * (P[:, :, 0] - a[:, None, 0])
        J[:, :, 1] = g * (P[:, :, 1] - a[:, None, 1])
        J[:, :, 2] = 1.0
        J[:, :, 3] = -5.0 * np.log10(d2)
        JW = J * w[:, :, None]
        JWt = JW.transpose(0, 2, 1)
        H = JWt @ J
        b = -(JWt @ e[:, :, None])[:, :, 0]
        Hd = H + lam[:, None, None] * (np.eye(4)[None] * np.maximum(np.diagonal(H, axis1=1, axis2=2), 1e-9)[:, :, None])
        step = np.linalg.solve(Hd, b[:, :, None])[:, :, 0]
        a2 = np.clip(a + step[:, :2], lo_a, hi_a)
        p02 = np.clip(p0 + step[:, 2], -90.0, 20.0)
        n2 = np.clip(n + step[:, 3], *N_BOUNDS)
        c2, e2, d22 = cost(a2, p02, n2)
        better = c2 < c
        a[better], p0[better], n[better] = a2[better], p02[better], n2[better]
        c = np.where(better, c2, c)
        e[better], d2[better] = e2[better], d22[better]
        lam = np.clip(np.where(better, lam * 0.3, lam * 10.0), 1e-6, 1e8)
    med = np.array([np.median(e[j][valid[j]]) for j in range(m)])
    mad = np.array([np.median(np.abs(e[j][valid[j]] - med[j])) for j in range(m)])
    return a, p0, n, np.maximum(1.4826 * mad, 2.0), cnt


def fit_path_loss(pos: np.ndarray, r_scan: np.ndarray, r_col: np.ndarray, r_val: np.ndarray, m: int) -> PathLossModel:
    """Fit the model (module docstring) to one floor's readings: ``pos`` (S, 2) labelled scan positions,
    readings (scan ``r_scan``, transmitter column ``r_col`` in 0..m-1, value ``r_val`` dBm)."""
    a = np.zeros((m, 2))
    p0 = np.full(m, -200.0)
    n = np.full(m, 2.0)
    sd = np.full(m, 10.0)
    ok = np.zeros(m, bool)
    order = np.argsort(r_col, kind="stable")
    bounds = np.searchsorted(r_col[order], np.arange(m + 1))
    fit = [j for j in range(m) if bounds[j + 1] - bounds[j] >= MIN_READINGS]
    if fit:
        k = min(MAX_READINGS, max(int(bounds[j + 1] - bounds[j]) for j in fit))
        Pp = np.zeros((len(fit), k, 2))
        rp = np.zeros((len(fit), k))
        vp = np.zeros((len(fit), k), bool)
        for i, j in enumerate(fit):
            sel = order[bounds[j] : bounds[j + 1]]
            if len(sel) > k:  # evenly thinned: four parameters need far fewer readings than a busy floor has
                sel = sel[np.linspace(0, len(sel) - 1, k).astype(np.int64)]
            Pp[i, : len(sel)] = pos[r_scan[sel]]
            rp[i, : len(sel)] = r_val[sel]
            vp[i, : len(sel)] = True
        fa, fp0, fn, fsd, _ = _fit_all(Pp, rp, vp)
        a[fit], p0[fit], n[fit], sd[fit], ok[fit] = fa, fp0, fn, fsd, True
    model = PathLossModel(a, p0, n, sd, ok, -90.0, 3.0)
    model.r50, model.s50 = _fit_detection(model, pos, r_scan, r_col, m)
    return model


def _fit_detection(model: PathLossModel, pos: np.ndarray, r_scan: np.ndarray, r_col: np.ndarray, m: int) -> tuple[float, float]:
    """Logistic regression of detected (0/1) on the predicted RSSI over every (scan, fitted transmitter)
    pair: P = sigmoid(b0 + b1 mu) -> r50 = -b0 / b1, s = 1 / b1. Newton's method on the two weights."""
    cols = np.flatnonzero(model.ok)
    if len(cols) == 0 or len(pos) == 0:
        return -90.0, 3.0
    mu = model.mean(pos)[:, cols].astype(np.float64).ravel()
    det = np.zeros((len(pos), m), bool)
    det[r_scan, r_col] = True
    y = det[:, cols].ravel().astype(np.float64)
    X = np.column_stack([np.ones_like(mu), (mu + 80.0) / 10.0])  # scaled for conditioning
    w = np.zeros(2)
    for _ in range(30):
        z = np.clip(X @ w, -30, 30)
        pr = 1.0 / (1.0 + np.exp(-z))
        g = X.T @ (y - pr)
        H = (X * (pr * (1 - pr))[:, None]).T @ X + 1e-9 * np.eye(2)
        step = np.linalg.solve(H, g)
        w += step
        if np.abs(step).max() < 1e-8:
            break
    b1 = w[1] / 10.0
    b0 = w[0] + w[1] * 8.0
    if not (b1 > 1e-3 and math.isfinite(b0)):
        return -90.0, 3.0
    return float(-b0 / b1), float(1.0 / b1)

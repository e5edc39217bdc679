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
#: A transmitter's readings must span at least this (the diagonal of their positions' bounding box, m):
#: readings from one spot fix neither where it is nor how fast it fades
MIN_SPAN_M = 5.0
#: Least residual spread of a fit, dB: a reading's own scatter about a local mean (radiomap's var0 floor)
MIN_RESID_SD = 3.0
#: A-priori detection law (used when the data cannot fit one) and the bounds a fitted one is kept in:
#: phones stop reporting between -100 and -85 dBm, over a few dB
R50_PRIOR, S50_PRIOR = -90.0, 3.0
R50_BOUNDS, S50_BOUNDS = (-110.0, -60.0), (1.0, 10.0)
#: Most (scan, transmitter) pairs the detection law is fitted on (scans evenly thinned beyond)
MAX_PAIRS = 2_000_000
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

    def mean(self, cells: np.ndarray, cols: np.ndarray | None = None) -> np.ndarray:
        """Predicted RSSI (n_cells, m), or (n_cells, len(cols)) for the columns ``cols``, dBm (float32,
        in blocks of cells: no (n_cells, m, 2) temporary)."""
        cols = np.arange(len(self.p0)) if cols is None else np.asarray(cols)
        a, p0, n = self.a[cols].astype(np.float32), self.p0[cols].astype(np.float32), self.n[cols].astype(np.float32)
        c = np.asarray(cells, np.float32).reshape(-1, 2)
        out = np.empty((len(c), len(cols)), np.float32)
        step = max(1, 4_000_000 // max(len(cols), 1))
        for i in range(0, len(c), step):
            dx = c[i : i + step, 0:1] - a[None, :, 0]
            dy = c[i : i + step, 1:2] - a[None, :, 1]
            out[i : i + step] = p0 - 5.0 * n * np.log10(dx * dx + dy * dy + np.float32(HEIGHT_M**2))
        return out

    def detection(self, mu: np.ndarray) -> np.ndarray:
        """Detection probability for predicted RSSI ``mu``."""
        z = np.clip((mu - self.r50) / self.s50, -30.0, 30.0)
        return (1.0 / (1.0 + np.exp(-z))).astype(np.float32)


def _fit_all(P: np.ndarray, r: np.ndarray, valid: np.ndarray, wt: np.ndarray | None = None, iters: int = 40) -> tuple[np.ndarray, ...]:
    """Every transmitter's (a, P0, n, robust residual sd) at once: ``P`` (m, k, 2) reading positions,
    ``r`` (m, k) dBm, ``valid`` (m, k) which entries are readings (rows padded to k), ``wt`` (m, k) their
    weights (the map's: age, label quality; default 1).

    Levenberg-Marquardt on iteratively reweighted least squares, batched over the transmitters (a 4 x 4
    system each): the residual e = P0 - 5 n log10(d^2) - r with d^2 = |p - a|^2 + h^2 has the Jacobian

        de/dP0 = 1,   de/dn = -5 log10(d^2),   de/da = 10 n (p - a) / (ln(10) d^2),

    and soft-L1 weights w = 1 / sqrt(1 + (e / f)^2), f = 4 dB (the robust loss's IRLS weights; Triggs et
    al., Bundle adjustment, 2000, sec. 3.3). Bounds are kept by clipping each step's result."""
    m = len(r)
    vf = valid.astype(np.float64) * (1.0 if wt is None else wt)
    cnt = valid.sum(1)
    # start: at the strongest readings, n = 2.5, P0 from the median reading's distance
    rr = np.where(valid, r, -np.inf)
    top = np.argsort(-rr, axis=1)[:, :3]
    a = np.take_along_axis(P, top[:, :, None], axis=1).mean(1)
    n = np.full(m, 2.5)
    d2 = ((P - a[:, None, :]) ** 2).sum(-1) + HEIGHT_M**2
    p0 = np.nanmedian(np.where(valid, r + 5.0 * n[:, None] * np.log10(d2), np.nan), axis=1)
    lo_a = np.where(valid[:, :, None], P, np.inf).min(1) - 30.0
    hi_a = np.where(valid[:, :, None], P, -np.inf).max(1) + 30.0
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
    ev = np.where(valid, e, np.nan)
    med = np.nanmedian(ev, axis=1)
    mad = np.nanmedian(np.abs(ev - med[:, None]), axis=1)
    # the residuals of a 4-parameter fit understate its spread: scale by sqrt(k / (k - 4))
    sd = 1.4826 * mad * np.sqrt(cnt / np.maximum(cnt - 4.0, 1.0))
    # a fit whose position ended at the edge of its search box did not find the transmitter. An exponent
    # at its bound is kept: the bounds are the physical range (N_BOUNDS), and 30 % of site1's fits end at
    # 1.5 (far away only the strong readings are heard, which flattens the fitted fall-off); dropping
    # them (40 % of the transmitters with the upper bound) gave the cell likelihood 7.24 m on routes held
    # out whole against 6.89 m keeping them (eval fingerprint)
    at_bound = (a <= lo_a + 1e-6).any(1) | (a >= hi_a - 1e-6).any(1)
    return a, p0, n, np.maximum(sd, MIN_RESID_SD), ~at_bound


def fit_path_loss(
    pos: np.ndarray, r_scan: np.ndarray, r_col: np.ndarray, r_val: np.ndarray, m: int, weights: np.ndarray | None = None
) -> PathLossModel:
    """Fit the model (module docstring) to one floor's readings: ``pos`` (S, 2) labelled scan positions,
    readings (scan ``r_scan``, transmitter column ``r_col`` in 0..m-1, value ``r_val`` dBm), ``weights``
    (S,) per scan (default 1). A transmitter is fitted (``ok``) with at least :data:`MIN_READINGS`
    finite readings spanning :data:`MIN_SPAN_M`, when its fit ends inside its bounds and finite."""
    pos = np.asarray(pos, float).reshape(-1, 2)
    r_scan, r_col, r_val = np.asarray(r_scan, np.int64), np.asarray(r_col, np.int64), np.asarray(r_val, float)
    good = np.isfinite(r_val) & np.isfinite(pos[r_scan]).all(1)
    r_scan, r_col, r_val = r_scan[good], r_col[good], r_val[good]
    ws = np.ones(len(pos)) if weights is None else np.asarray(weights, float).reshape(-1)
    a = np.zeros((m, 2))
    p0 = np.full(m, -200.0)
    n = np.full(m, 2.0)
    sd = np.full(m, 10.0)
    ok = np.zeros(m, bool)
    order = np.argsort(r_col, kind="stable")
    bounds = np.searchsorted(r_col[order], np.arange(m + 1))
    fit = []
    for j in range(m):
        sel = order[bounds[j] : bounds[j + 1]]
        if len(sel) < MIN_READINGS:
            continue
        q = pos[r_scan[sel]]
        if np.hypot(*np.ptp(q, axis=0)) < MIN_SPAN_M:
            continue
        fit.append(j)
    if fit:
        k = min(MAX_READINGS, max(int(bounds[j + 1] - bounds[j]) for j in fit))
        Pp = np.zeros((len(fit), k, 2))
        rp = np.zeros((len(fit), k))
        vp = np.zeros((len(fit), k), bool)
        wp = np.zeros((len(fit), k))
        for i, j in enumerate(fit):
            sel = order[bounds[j] : bounds[j + 1]]
            if len(sel) > k:  # evenly thinned: four parameters need far fewer readings than a busy floor has
                sel = sel[np.linspace(0, len(sel) - 1, k).astype(np.int64)]
            Pp[i, : len(sel)] = pos[r_scan[sel]]
            rp[i, : len(sel)] = r_val[sel]
            vp[i, : len(sel)] = True
            wp[i, : len(sel)] = ws[r_scan[sel]]
        fa, fp0, fn, fsd, inside = _fit_all(Pp, rp, vp, wp)
        fine = inside & np.isfinite(fa).all(1) & np.isfinite(fp0) & np.isfinite(fn) & np.isfinite(fsd)
        idx = np.asarray(fit)[fine]
        a[idx], p0[idx], n[idx], sd[idx], ok[idx] = fa[fine], fp0[fine], fn[fine], fsd[fine], True
    model = PathLossModel(a, p0, n, sd, ok, R50_PRIOR, S50_PRIOR)
    model.r50, model.s50 = _fit_detection(model, pos, r_scan, r_col, m)
    return model


def _fit_detection(model: PathLossModel, pos: np.ndarray, r_scan: np.ndarray, r_col: np.ndarray, m: int) -> tuple[float, float]:
    """Logistic regression of detected (0/1) on the predicted RSSI over the (scan, fitted transmitter)
    pairs (scans evenly thinned to :data:`MAX_PAIRS` pairs): P = sigmoid(b0 + b1 mu) -> r50 = -b0 / b1,
    s = 1 / b1, by damped Newton steps with a weak ridge; kept within :data:`R50_BOUNDS` and
    :data:`S50_BOUNDS`, and the a-priori law when the pairs are all heard, all missed or fit no law."""
    cols = np.flatnonzero(model.ok)
    if len(cols) == 0 or len(pos) == 0:
        return R50_PRIOR, S50_PRIOR
    rows = np.arange(len(pos))
    if len(rows) * len(cols) > MAX_PAIRS:
        rows = rows[np.linspace(0, len(rows) - 1, max(1, MAX_PAIRS // len(cols))).astype(np.int64)]
    col_of = np.full(m, -1, np.int64)
    col_of[cols] = np.arange(len(cols))
    row_of = np.full(len(pos), -1, np.int64)
    row_of[rows] = np.arange(len(rows))
    det = np.zeros((len(rows), len(cols)), bool)
    hit = (row_of[r_scan] >= 0) & (col_of[r_col] >= 0)
    det[row_of[r_scan[hit]], col_of[r_col[hit]]] = True
    y = det.ravel().astype(np.float64)
    if y.min() == y.max():
        return R50_PRIOR, S50_PRIOR
    mu = model.mean(pos[rows], cols).astype(np.float64).ravel()
    X = np.column_stack([np.ones_like(mu), (mu + 80.0) / 10.0])  # scaled for conditioning

    def nll(w):
        z = X @ w
        return float(np.sum(np.logaddexp(0.0, z) - y * z) + 0.5e-6 * (w @ w))

    w = np.zeros(2)
    f = nll(w)
    for _ in range(50):
        z = np.clip(X @ w, -30, 30)
        pr = 1.0 / (1.0 + np.exp(-z))
        g = X.T @ (y - pr) - 1e-6 * w
        H = (X * (pr * (1 - pr))[:, None]).T @ X + 1e-6 * np.eye(2)
        step = np.linalg.solve(H, g)
        t = 1.0
        while t > 1e-4 and nll(w + t * step) > f:  # halve the step until the likelihood rises
            t *= 0.5
        w = w + t * step
        f = nll(w)
        if np.abs(t * step).max() < 1e-8:
            break
    b1 = w[1] / 10.0
    b0 = w[0] + w[1] * 8.0
    if not (b1 > 0 and math.isfinite(b0) and math.isfinite(b1)):
        return R50_PRIOR, S50_PRIOR
    return float(np.clip(-b0 / b1, *R50_BOUNDS)), float(np.clip(1.0 / b1, *S50_BOUNDS))

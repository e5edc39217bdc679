"""GTSAM backend of :func:`.solve.solve` (``SolveOptions(backend="gtsam")``; pip ``gtsam``, extra ``slam``).

Formulation (the same factors as the scipy backend, slam.md 4.2-4.6):

* every node p_i and nuisance n_k = (a_k, b_k) is a GTSAM ``Point2`` (a vector space: local
  coordinates are differences), keys i and N + k;
* odometry W (p_j - p_i - M(D) n_k), M(D) = [D, perp(D)], is linear in three variables, which no
  built-in factor expresses: it is a ``JacobianFactor`` (blocks -W, W, -W M(D), b = 0) wrapped in a
  ``LinearContainerFactor`` linearised at zero, so its error is exactly 1/2 |W r|^2 at any x;
* position priors and nuisance priors are ``PriorFactorPoint2``, nuisance links and loops are
  ``BetweenFactorPoint2`` (error p_i - p_j - offset with the keys (j, i)); noise models are
  ``Gaussian.SqrtInformation(W)``, wrapped in ``Robust`` with GTSAM's own m-estimators: GemanMcClure(c),
  Cauchy(c), Huber(c), DCS(Phi = c^2), whose weights equal :func:`.factors.kernel_weight`;
* walkable-field factors are ``CustomFactor`` (a Python callback: fine for floors of a few thousand
  points, slow at 10^5);
* GNC: the Geman-McClure loops are rebuilt with width mu c for each mu of ``gnc_widths`` (the scipy
  backend's schedule, so both reach the same stationary point), each stage a Gauss-Newton run
  (GN on a robust noise model re-weights at every linearisation: IRLS);
* held variables (``free_nodes``/``free_nuisances``): only factors touching a free variable are built,
  and each held variable they reach gets a prior of sd 1e-6 m at its held value (GTSAM's LM/GN take no
  hard equality), so held values move by < 1e-6 m; the returned state keeps them exactly.
"""

from __future__ import annotations

import numpy as np

from ..errors import require
from .factors import FactorGraph, field_residual
from .solve import _settled

_HOLD_SIGMA = 1e-6


def _robust(gtsam, W: np.ndarray, code: int, c: float):
    base = gtsam.noiseModel.Gaussian.SqrtInformation(W)
    if code == 0:
        return base
    m = gtsam.noiseModel.mEstimator
    est = {1: lambda: m.GemanMcClure.Create(c), 2: lambda: m.Cauchy.Create(c), 3: lambda: m.Huber.Create(c), 4: lambda: m.DCS.Create(c * c)}[code]()
    return gtsam.noiseModel.Robust.Create(est, base)


def _field_factor(gtsam, grp, a: int, b: int, f: float):
    noise = gtsam.noiseModel.Isotropic.Sigma(1, grp.sigma)

    def error(this, values, H):
        pa, pb = values.atPoint2(a), values.atPoint2(b)
        q = (1.0 - f) * pa + f * pb
        e, J = field_residual(q[None, :], grp.field, grp.margin)
        if H is not None:
            if a == b:
                H[0] = J.reshape(1, 2)
            else:
                H[0] = (1.0 - f) * J.reshape(1, 2)
                H[1] = f * J.reshape(1, 2)
        return e

    keys = [a] if a == b else [a, b]
    return gtsam.CustomFactor(noise, keys, error)


def optimize(graph: FactorGraph, options, x: np.ndarray, free_var: np.ndarray) -> tuple[np.ndarray, int, bool]:
    """Optimise the graph with GTSAM from the state x; returns (x, iterations, converged)."""
    gtsam = require("gtsam", "slam", "the GTSAM backend of the crowd-SLAM solver")
    g = graph
    N = g.n_nodes
    fn, fk = free_var[:N], free_var[N:]
    X = x.reshape(-1, 2)
    base = gtsam.NonlinearFactorGraph()
    touched = free_var.copy()
    zero = gtsam.Values()

    o = g.odometry
    sel = np.flatnonzero(fn[o["i"]] | fn[o["j"]] | fk[o["k"]])
    if sel.size:
        ii, jj, kk = o["i"][sel], o["j"][sel], N + o["k"][sel]
        for key in np.unique(np.concatenate([ii, jj, kk])):
            zero.insert(int(key), np.zeros(2))
        touched[ii] = touched[jj] = touched[kk] = True
        W = o["W"][sel]
        D = o["delta"][sel]
        M = np.stack([np.stack([D[:, 0], -D[:, 1]], -1), np.stack([D[:, 1], D[:, 0]], -1)], axis=1)
        WM = W @ M
        unit = gtsam.noiseModel.Unit.Create(2)
        z2 = np.zeros(2)
        for t in range(sel.size):
            jf = gtsam.JacobianFactor(int(ii[t]), -W[t], int(jj[t]), W[t], int(kk[t]), -WM[t], z2, unit)
            base.add(gtsam.LinearContainerFactor(jf, zero))
    q = g.nuisance_priors
    for t in np.flatnonzero(fk[q["k"]]):
        base.add(gtsam.PriorFactorPoint2(int(N + q["k"][t]), q["mean"][t], gtsam.noiseModel.Gaussian.SqrtInformation(q["W"][t])))
    q = g.nuisance_links
    for t in np.flatnonzero(fk[q["k"]] | fk[q["l"]]):
        k, l = int(N + q["k"][t]), int(N + q["l"][t])
        touched[k] = touched[l] = True
        base.add(gtsam.BetweenFactorPoint2(k, l, np.zeros(2), gtsam.noiseModel.Gaussian.SqrtInformation(q["W"][t])))
    q = g.priors
    for t in np.flatnonzero(fn[q["i"]]):
        base.add(gtsam.PriorFactorPoint2(int(q["i"][t]), q["z"][t], _robust(gtsam, q["W"][t], int(q["kcode"][t]), float(q["kc"][t]))))
    for grp in g.fields:
        for t in np.flatnonzero(fn[grp.ia] | fn[grp.ib]):
            a, b = int(grp.ia[t]), int(grp.ib[t])
            touched[a] = touched[b] = True
            base.add(_field_factor(gtsam, grp, a, b, float(grp.f[t])))
    # gauge: weak prior on every free variable at its start (as the scipy backend)
    gauge = gtsam.noiseModel.Isotropic.Sigma(2, options.gauge_sigma)
    for v in np.flatnonzero(free_var):
        base.add(gtsam.PriorFactorPoint2(int(v), X[v], gauge))

    q = g.loops
    lsel = np.flatnonzero(fn[q["i"]] | fn[q["j"]])
    touched[q["i"][lsel]] = touched[q["j"][lsel]] = True
    hold = gtsam.noiseModel.Isotropic.Sigma(2, _HOLD_SIGMA)
    for v in np.flatnonzero(touched & ~free_var):
        base.add(gtsam.PriorFactorPoint2(int(v), X[v], hold))

    values = gtsam.Values()
    for v in np.flatnonzero(touched):
        values.insert(int(v), X[v].copy())

    codes = q["kcode"][lsel]
    widths = tuple(options.gnc_widths) if (codes == 1).any() else (1.0,)
    if widths[-1] != 1.0:
        widths = (*widths, 1.0)
    iterations, converged = 0, False
    keys = np.flatnonzero(touched)  # extractPoint2 returns the values in key order
    current = X[keys].copy()
    for s, mu in enumerate(widths):
        fg = gtsam.NonlinearFactorGraph()
        fg.push_back(base)  # shares the factors (clone() refuses CustomFactor)
        for t in lsel:
            c = float(q["kc"][t]) * (mu if q["kcode"][t] == 1 else 1.0)
            fg.add(gtsam.BetweenFactorPoint2(int(q["j"][t]), int(q["i"][t]), q["offset"][t], _robust(gtsam, q["W"][t], int(q["kcode"][t]), c)))
        opt = gtsam.GaussNewtonOptimizer(fg, values, gtsam.GaussNewtonParams())
        # one IRLS step per GNC width (as the scipy backend), then at mu = 1 until the largest
        # step has settled (the scipy backend's test)
        last = s == len(widths) - 1
        while iterations < options.max_iters:
            opt.iterate()
            iterations += 1
            new = gtsam.utilities.extractPoint2(opt.values())
            settled = _settled((new - current)[free_var[keys]], options.tol)
            current = new
            if not last:
                break
            if settled:
                converged = True
                break
        values = opt.values()
    out = x.copy().reshape(-1, 2)
    f = free_var[keys]
    out[keys[f]] = current[f]  # held variables keep their values exactly
    return out.ravel(), iterations, converged

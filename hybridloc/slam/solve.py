"""Robust batch solve of a :class:`~.factors.FactorGraph` (slam.md 4.6): GNC-annealed IRLS on sparse
whitened Gauss-Newton systems, with scipy (default) or GTSAM (:mod:`.solve_gtsam`).

State x = (p_0 .. p_{N-1}, n_0 .. n_{K-1}) in R^{2N + 2K}. Every factor e has a whitened residual
r_e(x) = W_e h_e(x) - c_e; all are linear in x except the walkable field, linearised at the current
x_t each iteration (Gauss-Newton):

    r_field(x) ~= [e(q_t) + grad d(q_t) . (q(x) - q_t)] / sigma,  q(x) = (1 - f) p_a + f p_b  (slam.md 4.5)

so that stacking the rows gives r(x) ~= A x - b. One IRLS step (Zhang 1997; slam.md 4.6 step 2) with
one weight w_e per factor (not per scalar row: a 2-D loop is kept or dropped whole, slam.md 2.2)

    w_e = kernel(|r_e(x_t)|; mu_t c_e)           (1 for odometry, nuisance and field factors)
    (A^T Wt A) x_{t+1} = A^T Wt b,  Wt = diag(w per row)

is solved by sparse LU of the symmetric positive definite normal matrix H = A^T Wt A with the
fill-reducing ordering MMD on A^T + A (``splu(..., permc_spec="MMD_AT_PLUS_A")``, slam.md 3.6:
1.4 s at 10^5 nodes for 6 iterations). Geman-McClure kernels are annealed by graduated non-convexity
(Yang et al. 2020): the width multiplier mu runs through ``SolveOptions.gnc_widths`` (one IRLS step
per width, wide = nearly quadratic first), then IRLS continues at mu = 1 until the step is below ``tol``.

Gauge: a component with no absolute factor leaves H singular. Every free node and nuisance gets a
very weak prior at its starting value, sd ``SolveOptions.gauge_sigma`` (1 km): it fixes the gauge of
a relative-only component (its marginal covariance then reads ~1e6 m^2: the pipeline flags it) and
moves an anchored solution by ~(sigma_factor / gauge_sigma)^2 of its start error (1e-8 relative).

Held variables (``free_nodes`` / ``free_nuisances``): their columns move to the right-hand side,
b <- b - A_held x_held, and only factors touching a free variable are assembled, so adding one walk to
a solved floor costs a system of that walk's size.

Marginals: Cov(p_i) = (H^-1)_{ii} (the 2x2 block), by solving H X = E_i with the last factorisation
(batched right-hand sides). At convergence x moved by < tol in the last step, so H is the final one.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..errors import require
from .factors import FactorGraph, field_residual, kernel_weight


@dataclass
class SolveOptions:
    # scipy or gtsam. The default is chosen by benchmarks/bench_slam.py (the more accurate; the faster
    # where they tie within 5 %): see BACKEND_CHOICE below for the figures.
    backend: str = "scipy"
    #: annealing schedule of the Geman-McClure widths, multipliers of Kernel.c (wide first, ends at 1)
    gnc_widths: tuple = (16.0, 8.0, 4.0, 2.0, 1.0)
    #: total IRLS / Gauss-Newton iterations (the GNC stages included)
    max_iters: int = 30
    #: convergence: the largest change of any coordinate in the last step, m (positions) / unitless (a, b)
    tol: float = 1e-2
    #: sd of the gauge prior on every free variable at its starting value (m for nodes)
    gauge_sigma: float = 1e3
    #: sparse factorisation of the scipy backend: "auto" (CHOLMOD via cholespy when installed), "superlu", "cholmod"
    linear_solver: str = "auto"


#: the default backend's reason, with the bench_slam figures (written by the benchmark's author)
BACKEND_CHOICE = "scipy: see benchmarks/bench_slam.py"


@dataclass
class Solution:
    pos: np.ndarray  # (N,2) node positions, site frame, m
    nuisance: np.ndarray  # (K,2) (a, b) per walk segment
    loop_weight: np.ndarray  # (L,) final robust weight in [0, 1] of each loop (audit trail)
    prior_weight: np.ndarray  # (P,) final robust weight of each position prior (1 without kernel)
    iterations: int
    seconds: float
    converged: bool
    backend: str = "scipy"
    _marg: _Marginals | None = field(default=None, repr=False)

    def marginals(self, nodes) -> np.ndarray:
        """Position covariance blocks (m,2,2) of ``nodes``, (H^-1)_ii of the final information matrix
        (held nodes: zeros, they are known)."""
        if self._marg is None:
            raise ValueError("this solution has no information matrix")
        return self._marg.blocks(np.atleast_1d(np.asarray(nodes, dtype=np.int64)))


class _Marginals:
    def __init__(self, lu, colmap: np.ndarray, n_free: int):
        self.lu, self.colmap, self.n_free = lu, colmap, n_free

    def blocks(self, nodes: np.ndarray, max_doubles: float = 2e7) -> np.ndarray:
        out = np.zeros((nodes.size, 2, 2))
        c0 = self.colmap[2 * nodes]
        idx = np.flatnonzero(c0 >= 0)
        chunk = max(1, int(max_doubles // max(self.n_free, 1) // 2))
        for s in range(0, idx.size, chunk):
            sel = idx[s : s + chunk]
            cols = np.stack([c0[sel], c0[sel] + 1], axis=1).ravel()
            E = np.zeros((self.n_free, cols.size))
            E[cols, np.arange(cols.size)] = 1.0
            X = self.lu.solve(E)  # H X = E: the columns of H^-1 of these nodes
            Xb = X[cols].reshape(sel.size, 2, sel.size, 2)
            ar = np.arange(sel.size)
            out[sel] = Xb[ar, :, ar, :]
        return out


def _triplets(row0: int, nr: int, starts: list[np.ndarray], blocks: list[np.ndarray]):
    """COO entries of m factors with nr rows each: block (m, nr, 2) on the two columns starting at starts[b] (m,)."""
    rows, cols, vals = [], [], []
    for st, B in zip(starts, blocks):
        m = st.size
        rr = row0 + nr * np.arange(m)[:, None, None] + np.arange(nr)[None, :, None]
        cc = st[:, None, None] + np.arange(2)[None, None, :]
        rows.append(np.broadcast_to(rr, (m, nr, 2)).ravel())
        cols.append(np.broadcast_to(cc, (m, nr, 2)).ravel())
        vals.append(B.reshape(m, nr, 2).ravel())
    return rows, cols, vals


def _nuisance_matrix(D: np.ndarray) -> np.ndarray:
    """M(D) = [D, perp(D)] (m,2,2), so that a D + b perp(D) = M(D) (a, b)."""
    return np.stack([np.stack([D[:, 0], -D[:, 1]], -1), np.stack([D[:, 1], D[:, 0]], -1)], axis=1)


def robust_weights(graph: FactorGraph, x: np.ndarray, loop_sel: np.ndarray, prior_sel: np.ndarray, mu: float = 1.0):
    """IRLS weights (w_loop, w_prior) of the selected loops and position priors at the state x, with
    r = |W e| their whitened residual norms; Geman-McClure widths are multiplied by the GNC factor mu."""
    P = x[: 2 * graph.n_nodes].reshape(-1, 2)
    out = []
    for q, s, e in (
        (graph.loops, loop_sel, lambda q, s: P[q["i"][s]] - P[q["j"][s]] - q["offset"][s]),
        (graph.priors, prior_sel, lambda q, s: P[q["i"][s]] - q["z"][s]),
    ):
        r = np.linalg.norm(np.einsum("mab,mb->ma", q["W"][s], e(q, s)), axis=1)
        code, c = q["kcode"][s], q["kc"][s]
        out.append(kernel_weight(code, np.where(code == 1, c * mu, c), r))
    return out[0], out[1]


class _Cholmod:
    """H = L L^T by CHOLMOD (pip ``cholespy``: AMD ordering, supernodal): same ``solve`` as SuperLU's."""

    def __init__(self, H: sp.spmatrix):
        cholespy = require("cholespy", "slam", "CHOLMOD for the crowd-SLAM solver")
        C = H.tocoo()
        self.n = H.shape[0]
        self.f = cholespy.CholeskySolverD(self.n, C.row.astype(np.int32), C.col.astype(np.int32), C.data.astype(np.float64), cholespy.MatrixType.COO)

    def solve(self, b: np.ndarray) -> np.ndarray:
        b = np.ascontiguousarray(b, dtype=np.float64)
        x = np.zeros_like(b)
        self.f.solve(b, x)
        return x


def _have_cholespy() -> bool:
    import importlib.util

    return importlib.util.find_spec("cholespy") is not None


def factor_spd(H: sp.spmatrix, linear_solver: str = "auto"):
    """Factorise the symmetric positive definite normal matrix H; the result has ``solve(b)``.

    * ``superlu``: ``splu(H, permc_spec="MMD_AT_PLUS_A")`` in symmetric mode with diagonal pivots, so the
      minimum-degree ordering of H + H^T is kept on both sides (a Cholesky-like LU; threshold pivoting
      off the diagonal multiplies the fill by ~20 on these graphs). scipy's SuperLU runs on reference
      BLAS: dense separators of crowded floors are its cost (24 s for one factorisation at 10^5 nodes
      in bench_slam's two-pass world);
    * ``cholmod``: CHOLMOD's supernodal Cholesky (pip ``cholespy``, extra ``slam``): 3.6 s there;
    * ``auto``: cholmod when cholespy is installed, else superlu.
    """
    if linear_solver == "cholmod" or (linear_solver == "auto" and _have_cholespy()):
        return _Cholmod(H)
    return splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))


class _Problem:
    """The whitened linear(ised) system of the factors that touch a free variable."""

    def __init__(self, graph: FactorGraph, x0: np.ndarray, free_var: np.ndarray, options: SolveOptions):
        self.g, self.opt = graph, options
        N, K = graph.n_nodes, graph.n_nuisances
        self.N, self.K = N, K
        self.x0 = x0
        # column map of the full state -> free columns (-1: held)
        free_col = np.repeat(free_var, 2)
        self.colmap = np.full(2 * (N + K), -1, dtype=np.int64)
        self.colmap[free_col] = np.arange(int(free_col.sum()))
        self.n_free = int(free_col.sum())
        self.free_var = free_var
        fn, fk = free_var[:N], free_var[N:]
        g = graph
        R, C, V, B = [], [], [], []
        row = 0

        def add(nr, starts, blocks, b):
            nonlocal row
            r, c, v = _triplets(row, nr, starts, blocks)
            R.extend(r), C.extend(c), V.extend(v), B.append(b.reshape(-1))
            row += b.size

        # odometry: W (p_j - p_i - M(D) n_k) = 0  (slam.md 4.2)
        o = g.odometry
        s = fn[o["i"]] | fn[o["j"]] | fk[o["k"]]
        if s.any():
            W = o["W"][s]
            add(2, [2 * o["i"][s], 2 * o["j"][s], 2 * (N + o["k"][s])], [-W, W, -W @ _nuisance_matrix(o["delta"][s])], np.zeros((s.sum(), 2)))
        # nuisance prior: W (n_k - mean)
        q = g.nuisance_priors
        s = fk[q["k"]]
        if s.any():
            W = q["W"][s]
            add(2, [2 * (N + q["k"][s])], [W], np.einsum("mab,mb->ma", W, q["mean"][s]))
        # nuisance link: W (n_l - n_k)
        q = g.nuisance_links
        s = fk[q["k"]] | fk[q["l"]]
        if s.any():
            W = q["W"][s]
            add(2, [2 * (N + q["l"][s]), 2 * (N + q["k"][s])], [W, -W], np.zeros((s.sum(), 2)))
        # position priors (robust): W (p_i - z)
        q = g.priors
        self.prior_sel = np.flatnonzero(fn[q["i"]])
        self.prior_row0 = row
        if self.prior_sel.size:
            W = q["W"][self.prior_sel]
            add(2, [2 * q["i"][self.prior_sel]], [W], np.einsum("mab,mb->ma", W, q["z"][self.prior_sel]))
        # loops (robust): W (p_i - p_j - offset)
        q = g.loops
        self.loop_sel = np.flatnonzero(fn[q["i"]] | fn[q["j"]])
        self.loop_row0 = row
        if self.loop_sel.size:
            W = q["W"][self.loop_sel]
            add(2, [2 * q["i"][self.loop_sel], 2 * q["j"][self.loop_sel]], [W, -W], np.einsum("mab,mb->ma", W, q["offset"][self.loop_sel]))
        # gauge: (x_v - x0_v) / gauge_sigma on every free variable
        v = np.flatnonzero(free_var)
        eye = np.broadcast_to(np.eye(2) / options.gauge_sigma, (v.size, 2, 2))
        add(2, [2 * v], [eye], x0.reshape(-1, 2)[v] / options.gauge_sigma)
        self.n_rows = row
        self.A_free, self.b = self._split(np.concatenate(R), np.concatenate(C), np.concatenate(V), np.concatenate(B), row)
        # field factors touching a free node
        self.fields = []
        for grp in g.fields:
            s = fn[grp.ia] | fn[grp.ib]
            if s.any():
                self.fields.append((grp, s))

    def _split(self, r, c, v, b, n_rows):
        """Free columns -> sparse A; held columns -> b <- b - A_held x_held."""
        nc = self.colmap[c]
        free = nc >= 0
        A = sp.csr_matrix((v[free], (r[free], nc[free])), shape=(n_rows, self.n_free))
        held = ~free
        b = b - np.bincount(r[held], weights=v[held] * self.x0[c[held]], minlength=n_rows)
        return A, b

    def weights(self, x: np.ndarray, mu: float):
        return robust_weights(self.g, x, self.loop_sel, self.prior_sel, mu)

    def field_rows(self, x: np.ndarray):
        """Gauss-Newton rows of the walkable factors at x: (g/sigma) . q(x) = (g . q_t - e_t) / sigma (slam.md 4.5)."""
        if not self.fields:
            return None, None
        P = x[: 2 * self.N].reshape(-1, 2)
        R, C, V, B = [], [], [], []
        row = 0
        for grp, s in self.fields:
            ia, ib, f = grp.ia[s], grp.ib[s], grp.f[s]
            qt = (1.0 - f)[:, None] * P[ia] + f[:, None] * P[ib]
            e, J = field_residual(qt, grp.field, grp.margin)
            Js = J / grp.sigma
            r, c, v = _triplets(row, 1, [2 * ia, 2 * ib], [(1.0 - f)[:, None] * Js, f[:, None] * Js])
            R.extend(r), C.extend(c), V.extend(v)
            B.append(np.einsum("ma,ma->m", Js, qt) - e / grp.sigma)
            row += ia.size
        return self._split(np.concatenate(R), np.concatenate(C), np.concatenate(V), np.concatenate(B), row)

    def row_weights(self, w_loop, w_prior) -> np.ndarray:
        w = np.ones(self.n_rows)
        w[self.prior_row0 : self.prior_row0 + 2 * w_prior.size] = np.repeat(w_prior, 2)
        w[self.loop_row0 : self.loop_row0 + 2 * w_loop.size] = np.repeat(w_loop, 2)
        return w

    def factorize(self, x: np.ndarray, mu: float):
        """H = A^T Wt A and A^T Wt b at the linearisation point x; returns (lu, rhs, w_loop, w_prior)."""
        w_loop, w_prior = self.weights(x, mu)
        w = self.row_weights(w_loop, w_prior)
        A, b = self.A_free, self.b
        AtW = (A.T @ sp.diags(w)).tocsr()
        H = AtW @ A
        rhs = AtW @ b
        Af, bf = self.field_rows(x)
        if Af is not None:
            H = H + (Af.T @ Af)
            rhs = rhs + Af.T @ bf
        lu = factor_spd(H, self.opt.linear_solver)
        return lu, rhs, w_loop, w_prior

    def scatter(self, x: np.ndarray, x_free: np.ndarray) -> np.ndarray:
        out = x.copy()
        cols = np.flatnonzero(self.colmap >= 0)
        out[cols] = x_free[self.colmap[cols]]
        return out


def _has_nonlinear(problem: _Problem) -> tuple[bool, bool]:
    g = problem.g
    codes = np.concatenate([g.loops["kcode"][problem.loop_sel], g.priors["kcode"][problem.prior_sel]])
    return bool((codes == 1).any()), bool((codes > 0).any() or problem.fields)


def _start(graph: FactorGraph, x0: Solution | None) -> np.ndarray:
    """Starting state: x0's values where it has them (new nodes / nuisances: their initial values)."""
    pos = graph.node_init.copy()
    nuis = graph.nuisance_init.copy()
    if x0 is not None:
        n, k = min(len(x0.pos), len(pos)), min(len(x0.nuisance), len(nuis))
        pos[:n], nuis[:k] = x0.pos[:n], x0.nuisance[:k]
    return np.concatenate([pos.ravel(), nuis.ravel()])


def _free_mask(graph: FactorGraph, free_nodes, free_nuisances) -> np.ndarray:
    N, K = graph.n_nodes, graph.n_nuisances
    if free_nodes is None and free_nuisances is None:
        return np.ones(N + K, dtype=bool)
    m = np.zeros(N + K, dtype=bool)
    if free_nodes is not None:
        m[np.asarray(free_nodes, dtype=np.int64)] = True
    if free_nuisances is not None:
        m[N + np.asarray(free_nuisances, dtype=np.int64)] = True
    return m


def _finish(graph, problem, x, it, converged, t0, backend, lu=None) -> Solution:
    N = graph.n_nodes
    # final weights of every loop and prior at x (held ones too: their residual is what it is)
    w_loop, w_prior = robust_weights(graph, x, np.arange(graph.n_loops), np.arange(graph.n_priors), 1.0)
    seconds = time.perf_counter() - t0
    if lu is None:
        lu = problem.factorize(x, 1.0)[0]
    return Solution(
        pos=x[: 2 * N].reshape(-1, 2).copy(),
        nuisance=x[2 * N :].reshape(-1, 2).copy(),
        loop_weight=w_loop,
        prior_weight=w_prior,
        iterations=it,
        seconds=seconds,
        converged=converged,
        backend=backend,
        _marg=_Marginals(lu, problem.colmap, problem.n_free),
    )


def solve(graph: FactorGraph, options: SolveOptions | None = None, x0: Solution | None = None, free_nodes=None, free_nuisances=None) -> Solution:
    """Robust MAP estimate of the graph (module docstring). ``free_*`` None: everything free; otherwise
    only these move and every other variable is held at x0 (or its initial value)."""
    options = options or SolveOptions()
    t0 = time.perf_counter()
    x = _start(graph, x0)
    free_var = _free_mask(graph, free_nodes, free_nuisances)
    problem = _Problem(graph, x, free_var, options)
    if options.backend == "gtsam":
        from .solve_gtsam import optimize

        x, it, converged = optimize(graph, options, x, free_var)
        return _finish(graph, problem, x, it, converged, t0, "gtsam")
    if options.backend != "scipy":
        raise ValueError(f"unknown backend {options.backend!r} (scipy or gtsam)")
    has_gm, nonlinear = _has_nonlinear(problem)
    widths = tuple(options.gnc_widths) if has_gm else (1.0,)
    if widths[-1] != 1.0:
        widths = (*widths, 1.0)
    converged = False
    lu = None
    it = 0
    if problem.n_free == 0:
        return _finish(graph, problem, x, 0, True, t0, "scipy")
    for it in range(1, options.max_iters + 1):
        mu = widths[min(it - 1, len(widths) - 1)]
        lu, rhs, _, _ = problem.factorize(x, mu)
        x_new = problem.scatter(x, lu.solve(rhs))
        step = float(np.max(np.abs(x_new - x)))
        x = x_new
        if not nonlinear or (it >= len(widths) and step < options.tol):
            converged = True
            break
    return _finish(graph, problem, x, it, converged, t0, "scipy", lu)

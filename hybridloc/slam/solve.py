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

IRLS tail: once mu = 1 the weights change little per step, so the last factorisation preconditions
conjugate gradients on the new H (a few triangular solves instead of a factorisation; re-factorised
when CG stalls within 20 steps).

Marginals: Cov(p_i) = (H^-1)_{ii} (the 2x2 block) from the factorisation of H at the final state (the
last one when it was made there; else made on the first call): read off the selected inverse of its
sparse factor (:mod:`._selinv`, Takahashi's recurrences: the entries of H^-1 on the factor's pattern,
which holds every node's block), or by solving H X = E_i (batched right-hand sides) where that factor
is not SuperLU's in the nested-dissection order (CHOLMOD, the MMD order).
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator, cg, splu

from ..errors import require
from .factors import FactorGraph, field_residual, kernel_rho, kernel_weight


@dataclass
class SolveOptions:
    # scipy or gtsam, chosen by benchmarks/bench_slam.py (the more accurate; the faster where they tie
    # within 5 %). Both reach the same answer on its graphs (node RMSE 1.639 m both, wrong-loop p95
    # weight 0.054 both, 10^5 nodes, 30 % wrong loops 5-20 m, 27 iterations each), so speed decides:
    # scipy 32.5 s vs GTSAM 42.4 s there (another run: 34.6 vs 51.2), 18.2 vs 19.6 s at 5*10^4,
    # 5.2 vs 6.3 s at 2.5*10^4, 2.1 vs 3.3 s at 10^4; random long-range wrong loops at 2*10^4 nodes:
    # 14.6 vs 14.4 s (a tie); adding one walk 0.023 s both. Neither meets the 5 s at 10^5 nodes.
    backend: str = "scipy"
    #: annealing schedule of the Geman-McClure widths, multipliers of Kernel.c (wide first, ends at 1)
    gnc_widths: tuple = (16.0, 8.0, 4.0, 2.0, 1.0)
    #: total IRLS / Gauss-Newton iterations (the GNC stages included)
    max_iters: int = 30
    #: convergence: the largest change of any coordinate in the last step, m (positions) / unitless (a, b),
    #: below tol, or its RMS below tol / 10 (see _settled); 5 cm: a twentieth of the smallest loop sd (~1 m)
    tol: float = 5e-2
    #: sd of the gauge prior on every free variable at its starting value (m for nodes)
    gauge_sigma: float = 1e3
    #: sparse factorisation of the scipy backend: "superlu" (in nested-dissection order) or "cholmod" (pip cholespy)
    linear_solver: str = "superlu"
    #: fill-reducing order for superlu: "nd" (geometric nested dissection on the start positions) or "mmd"
    ordering: str = "nd"
    #: IRLS tail (mu = 1): solve with conjugate gradients preconditioned by the last factorisation
    reuse_factor: bool = True
    #: with walkable-field factors, backtrack each Gauss-Newton step until the robust objective falls
    #: (:func:`_backtrack`). Off by default, measured: site1's floor solves with the field then settle
    #: (one F1 batch: 3 of 5 field solves in 24-28 iterations, where none did in 30), but eval slam F = 0.1
    #: is better on one floor of three and worse over all (corrected crowd walks mean 12.41 -> 13.17 m,
    #: median 9.20 -> 10.05; fused test clients 17.37 -> 17.69 m; F1 10.22 -> 9.85 m, F2 11.46 -> 15.46 m
    #: with coverage 37.8 -> 45.6 %, F3 14.84 -> 14.94 m): the undamped steps' jumps carry walks out of
    #: the shops they were drawn into, which a descent method does not. An earlier session's line search
    #: measured the same way on a batch re-solve of an eval crowd database (8.46 m against 8.21 m,
    #: docs/slam.md "Why the solves do not settle")
    line_search: bool = False


#: why the default backend is scipy (bench_slam, 2-core machine shared with other jobs, 2026-12):
#: 10^5 nodes, 28,571 loops (30 % wrong, 5-20 m), one crowd pass per corridor: scipy 32.5-34.6 s, GTSAM 42.4-51.2 s,
#: identical node RMSE (1.639 m) and loop weights. Both spend ~1.3-1.9 s per iteration and need ~27
#: GNC + IRLS iterations (the IRLS tail at mu = 1 converges linearly), so the issue's 5 s goal is missed
#: by both; the wrong-loop p95 weight goal (< 0.1) is met (0.054).
BACKEND_CHOICE = "scipy"


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
    #: largest change of a free coordinate in the last iteration (m for positions; NaN when unknown:
    #: the GTSAM backend): with ``converged`` False, how far from settled the solve stopped
    last_step: float = 0.0
    _marg: _Marginals | None = field(default=None, repr=False)

    def marginals(self, nodes) -> np.ndarray:
        """Position covariance blocks (m,2,2) of ``nodes``, (H^-1)_ii of the final information matrix
        (held nodes: zeros, they are known)."""
        if self._marg is None:
            raise ValueError("this solution has no information matrix")
        return self._marg.blocks(np.atleast_1d(np.asarray(nodes, dtype=np.int64)))


class _Marginals:
    """Blocks of H^-1 at the final state: the last factorisation when it was made there, else one made
    on the first call (the IRLS tail re-uses an older factorisation as a preconditioner only)."""

    def __init__(self, problem: _Problem, x: np.ndarray, lu=None):
        self.problem, self.x, self._lu = problem, x, lu
        self.colmap, self.n_free = problem.colmap, problem.n_free
        self._z: tuple | None = None  # the selected inverse of the factor, made on the first call

    @property
    def lu(self):
        if self._lu is None:
            self._lu = self.problem.factorize(self.x, 1.0)[0]
        return self._lu

    def blocks(self, nodes: np.ndarray, max_doubles: float = 2e7) -> np.ndarray:
        out = np.zeros((nodes.size, 2, 2))
        c0 = self.colmap[2 * nodes]
        idx = np.flatnonzero(c0 >= 0)
        if idx.size and isinstance(self.lu, _PermutedLU):
            idx = self._selected(c0, idx, out)
        self._dense(c0, idx, out, max_doubles)
        return out

    def _selected(self, c0: np.ndarray, idx: np.ndarray, out: np.ndarray) -> np.ndarray:
        """The blocks of nodes ``idx`` read from the selected inverse of the factor (:mod:`._selinv`),
        written into ``out``; returns the nodes it could not read (the dense solve's), all of them when
        SuperLU pivoted off the diagonal or the pattern misses an entry."""
        from ._selinv import gather, selected_inverse  # Numba imported on first use

        lu = self.lu
        pinv = lu.pinv
        if self._z is None:
            n = self.n_free
            natural = np.array_equal(lu.lu.perm_r, np.arange(n)) and np.array_equal(lu.lu.perm_c, np.arange(n))
            # every free node's x-y entry on the pattern (the held nodes' columns are -1)
            cx = self.colmap[0 : 2 * self.problem.N : 2]
            cx = cx[cx >= 0]
            pairs = (pinv[cx + 1], pinv[cx])
            self._z = selected_inverse(lu.lu.L, lu.lu.U, pairs) if natural else (None, None, None, False)
        indptr, indices, z, ok = self._z
        if not ok:
            return idx
        px, py = pinv[c0[idx]], pinv[c0[idx] + 1]
        vals, found = gather(indptr, indices, z, np.concatenate([px, py, px]), np.concatenate([px, py, py]))
        m = idx.size
        got = found[:m] & found[m : 2 * m] & found[2 * m :]
        xx, yy, xy = vals[:m], vals[m : 2 * m], vals[2 * m :]
        sel = idx[got]
        out[sel, 0, 0], out[sel, 1, 1] = xx[got], yy[got]
        out[sel, 0, 1] = out[sel, 1, 0] = xy[got]
        return idx[~got]

    def _dense(self, c0: np.ndarray, idx: np.ndarray, out: np.ndarray, max_doubles: float) -> None:
        """The blocks of nodes ``idx`` by solving H X = E for their identity columns, in chunks."""
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


class _PermutedLU:
    """SuperLU of P H P^T in the natural order (the permutation is a fill-reducing order computed once)."""

    def __init__(self, H: sp.spmatrix, perm: np.ndarray):
        self.perm = perm
        Hp = H.tocsr()[perm][:, perm].tocsc()
        self.lu = splu(Hp, permc_spec="NATURAL", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))

    def solve(self, b: np.ndarray) -> np.ndarray:
        x = np.empty_like(b, dtype=float)
        x[self.perm] = self.lu.solve(np.ascontiguousarray(b[self.perm]))
        return x

    @functools.cached_property
    def pinv(self) -> np.ndarray:
        """The inverse permutation: column c of H is column pinv[c] of the factor."""
        out = np.empty_like(self.perm)
        out[self.perm] = np.arange(self.perm.size)
        return out


def factor_spd(H: sp.spmatrix, linear_solver: str = "superlu", perm: np.ndarray | None = None):
    """Factorise the symmetric positive definite normal matrix H; the result has ``solve(b)``.

    * ``superlu`` with ``perm`` (the default path, :func:`nested_dissection` order): SuperLU of P H P^T
      in symmetric mode with diagonal pivots, i.e. a Cholesky-like LU in the given order;
    * ``superlu`` without ``perm``: ``splu(H, permc_spec="MMD_AT_PLUS_A")`` in symmetric mode (threshold
      pivoting off the diagonal would undo the ordering: ~20x the fill on these graphs);
    * ``cholmod``: CHOLMOD (pip ``cholespy``, extra ``slam``) with its own AMD ordering.
    Measured at 10^5 nodes in :func:`nested_dissection`'s docstring; scipy's SuperLU runs on reference
    BLAS, so the ordering matters more than the library.
    """
    if linear_solver == "cholmod":
        return _Cholmod(H)
    if linear_solver != "superlu":
        raise ValueError(f"unknown linear solver {linear_solver!r} (superlu or cholmod)")
    if perm is not None:
        return _PermutedLU(H, perm)
    return splu(H.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=dict(SymmetricMode=True))


def nested_dissection(xy: np.ndarray, rows: np.ndarray, cols: np.ndarray, leaf: int = 64) -> np.ndarray:
    """Fill-reducing elimination order of a graph whose vertices have positions ``xy`` (m,2) and edges
    (rows, cols) (George 1973, geometric nested dissection): split the vertices at the median of their
    wider coordinate, take the vertices of one half adjacent to the other as the separator, order the
    two halves recursively and the separator last. Crowd graphs are local (odometry, loops of a few to
    tens of metres), so separators stay small where minimum degree orderings leave large dense fronts
    (bench_slam at 10^5 nodes, one walk per corridor: SuperLU's own MMD ordering 2.0 s and 3.6 M
    entries, CHOLMOD/AMD 3.2 s, this ordering 1.0 s; two walks per corridor: 24 s, 3.6 s and 2.4 s). Returns the order
    (a permutation of range(m))."""
    m = xy.shape[0]
    keep = rows != cols
    u, v = rows[keep], cols[keep]
    order = np.empty(m, dtype=np.int64)
    pos = 0
    side = np.zeros(m, dtype=np.int8)
    work = [("sub", np.arange(m), u, v)]
    while work:
        kind, idx, eu, ev = work.pop()
        if kind == "sep":
            order[pos : pos + idx.size] = idx
            pos += idx.size
            continue
        if idx.size <= leaf:
            order[pos : pos + idx.size] = idx
            pos += idx.size
            continue
        p = xy[idx]
        ax = int(np.argmax(p.max(0) - p.min(0)))
        med = np.median(p[:, ax])
        left = p[:, ax] <= med
        if left.all() or not left.any():
            left = np.zeros(idx.size, dtype=bool)
            left[: idx.size // 2] = True
        side[idx] = np.where(left, 0, 1)
        cross = side[eu] != side[ev]
        # separator: the endpoints in the smaller boundary
        bl = np.unique(np.where(side[eu[cross]] == 0, eu[cross], ev[cross]))
        br = np.unique(np.where(side[eu[cross]] == 1, eu[cross], ev[cross]))
        sep = bl if bl.size <= br.size else br
        side[sep] = 2
        in_l = side[idx] == 0
        in_r = side[idx] == 1
        el = (side[eu] == 0) & (side[ev] == 0)
        er = (side[eu] == 1) & (side[ev] == 1)
        # post-order: halves first, separator last (pushed first: the stack pops it last)
        work.append(("sep", sep, None, None))
        work.append(("sub", idx[in_r], eu[er], ev[er]))
        work.append(("sub", idx[in_l], eu[el], ev[el]))
    return order


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
        self.free_cols = np.flatnonzero(self.colmap >= 0)  # the state's free coordinates, in column order
        self.free_var = free_var
        self.perm: np.ndarray | None = None
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

    def objective(self, x: np.ndarray, mu: float) -> float:
        """The robust objective the iterations minimise at GNC width factor mu: 1/2 |r|^2 of every plain
        row, rho(|r_e|) of every robust prior and loop (:func:`~.factors.kernel_rho`, whose IRLS weights
        these are) and 1/2 (e / sigma)^2 of every walkable-field factor at q(x) itself (not linearised)."""
        res = self.A_free @ x[self.free_cols] - self.b
        lo, hi = self.prior_row0, self.loop_row0 + 2 * self.loop_sel.size
        total = 0.5 * float(res[:lo] @ res[:lo]) + 0.5 * float(res[hi:] @ res[hi:])
        g = self.g
        for q, sel, r0 in ((g.priors, self.prior_sel, self.prior_row0), (g.loops, self.loop_sel, self.loop_row0)):
            if sel.size:
                rr = res[r0 : r0 + 2 * sel.size].reshape(-1, 2)
                code, c = q["kcode"][sel], q["kc"][sel]
                total += float(kernel_rho(code, np.where(code == 1, c * mu, c), np.hypot(rr[:, 0], rr[:, 1])).sum())
        P = x[: 2 * self.N].reshape(-1, 2)
        for grp, s in self.fields:
            f = grp.f[s]
            qt = (1.0 - f)[:, None] * P[grp.ia[s]] + f[:, None] * P[grp.ib[s]]
            e = field_residual(qt, grp.field, grp.margin)[0] / grp.sigma
            total += 0.5 * float(e @ e)
        return total

    def row_weights(self, w_loop, w_prior) -> np.ndarray:
        w = np.ones(self.n_rows)
        w[self.prior_row0 : self.prior_row0 + 2 * w_prior.size] = np.repeat(w_prior, 2)
        w[self.loop_row0 : self.loop_row0 + 2 * w_loop.size] = np.repeat(w_loop, 2)
        return w

    def factorize(self, x: np.ndarray, mu: float):
        """Factorisation of H at x and the right-hand side: (factor, rhs, H)."""
        H, rhs = self.system(x, mu)
        if self.perm is None and self.opt.linear_solver == "superlu" and self.opt.ordering == "nd":
            self.perm = self.order(H, x)
        return factor_spd(H, self.opt.linear_solver, self.perm), rhs, H

    def order(self, H: sp.spmatrix, x: np.ndarray) -> np.ndarray:
        """Nested-dissection order of the free columns (the pattern of H does not change between
        iterations: computed once). Vertices: free variables at their positions (a nuisance at the mean
        of its odometry nodes); edges: the 2x2 blocks of H."""
        N, K = self.N, self.K
        xy = x.reshape(-1, 2).copy()
        o = self.g.odometry
        cnt = np.bincount(o["k"], minlength=K)
        for a in range(2):
            xy[N:, a] = np.bincount(o["k"], weights=xy[o["i"], a], minlength=K) / np.maximum(cnt, 1)
        free = np.flatnonzero(self.free_var)
        C = H.tocoo()
        order = nested_dissection(xy[free], C.row // 2, C.col // 2)
        return np.stack([2 * order, 2 * order + 1], 1).ravel()

    def system(self, x: np.ndarray, mu: float):
        """H = A^T Wt A and A^T Wt b at the linearisation point x."""
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
        return H, rhs

    def scatter(self, x: np.ndarray, x_free: np.ndarray) -> np.ndarray:
        out = x.copy()
        cols = self.free_cols
        out[cols] = x_free[self.colmap[cols]]
        return out


def _settled(dx: np.ndarray, tol: float) -> bool:
    """Convergence test of an IRLS step: every coordinate moved < tol, or the RMS move is < tol / 10
    (on 10^5 nodes a few loops near their kernel width creep for many steps while the rest has
    settled: IRLS converges only linearly there, and the max alone would wait for the slowest)."""
    if dx.size == 0:
        return True
    return bool(np.max(np.abs(dx)) < tol or np.sqrt(np.mean(dx * dx)) < 0.1 * tol)


#: step halvings :func:`_backtrack` tries before it keeps the state (2^-8 of a step: a few mm of a metre)
MAX_HALVINGS = 8


def _backtrack(problem: _Problem, x: np.ndarray, x_new: np.ndarray, mu: float) -> tuple[np.ndarray, bool]:
    """The Gauss-Newton step x -> x_new shortened by halving until the robust objective (at the same
    GNC width) is no larger than at x (Armijo's rule with constant 0, Nocedal & Wright 3.1). The IRLS
    part of a step never raises it (majorise-minimise); the walkable-field rows do: each is linearised
    as e + g.(q - q_t), which keeps pulling past the margin where the hinge is flat, and the distance
    field's gradient turns at the ridges inside obstacles, so undamped steps cycle (site1's floor
    solves with the field stopped at 30 iterations with 0.3-0.5 m RMS steps). No decrease within
    :data:`MAX_HALVINGS` halvings: (x, False), and the solve stops there unsettled (the field's kinks can
    leave a point where the Gauss-Newton direction is no descent direction at all)."""
    f0 = problem.objective(x, mu)
    step = x_new - x
    t = 1.0
    for _ in range(MAX_HALVINGS + 1):
        cand = x + t * step
        if problem.objective(cand, mu) <= f0:
            return cand, True
        t *= 0.5
    return x, False


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


def _finish(graph, problem, x, it, converged, t0, backend, lu=None, last_step: float = 0.0) -> Solution:
    N = graph.n_nodes
    # final weights of every loop and prior at x (held ones too: their residual is what it is)
    w_loop, w_prior = robust_weights(graph, x, np.arange(graph.n_loops), np.arange(graph.n_priors), 1.0)
    seconds = time.perf_counter() - t0
    return Solution(
        pos=x[: 2 * N].reshape(-1, 2).copy(),
        nuisance=x[2 * N :].reshape(-1, 2).copy(),
        loop_weight=w_loop,
        prior_weight=w_prior,
        iterations=it,
        seconds=seconds,
        converged=converged,
        backend=backend,
        last_step=last_step,
        _marg=_Marginals(problem, x, lu),
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
        return _finish(graph, problem, x, it, converged, t0, "gtsam", last_step=float("nan"))
    if options.backend != "scipy":
        raise ValueError(f"unknown backend {options.backend!r} (scipy or gtsam)")
    has_gm, nonlinear = _has_nonlinear(problem)
    widths = tuple(options.gnc_widths) if has_gm else (1.0,)
    if widths[-1] != 1.0:
        widths = (*widths, 1.0)
    converged = False
    lu = None
    it = 0
    last_fresh = True
    if problem.n_free == 0:
        return _finish(graph, problem, x, 0, True, t0, "scipy")
    x_free = None
    last_step = 0.0
    search = options.line_search and bool(problem.fields)
    for it in range(1, options.max_iters + 1):
        mu = widths[min(it - 1, len(widths) - 1)]
        fresh = True
        if lu is not None and it > len(widths) and options.reuse_factor:
            # IRLS tail at mu = 1: the weights change little from one step to the next, so the last
            # factorisation of H is a near-exact preconditioner of the new H: a few CG steps replace a
            # factorisation (re-factorise only when CG stalls)
            H, rhs = problem.system(x, mu)
            M = LinearOperator(H.shape, matvec=lu.solve, dtype=float)
            # solve for the step d = x - x_prev (H d = rhs - H x_prev): CG's relative tolerance then
            # applies to the step, not to x, so a small last step is still solved to 1e-6 of itself
            dx, info = cg(H, rhs - H @ x_free, rtol=1e-6, maxiter=10, M=M)
            if info == 0:
                x_free, fresh = x_free + dx, False
        if fresh:
            lu, rhs, _ = problem.factorize(x, mu)
            x_free = lu.solve(rhs)
        x_new = problem.scatter(x, x_free)
        if search:
            x_new, descended = _backtrack(problem, x, x_new, mu)
            if not descended:  # no step lowers the objective: stop here, not settled
                break
            x_free = x_new[problem.free_cols]
        move = (x_new - x)[problem.free_cols]
        last_step = float(np.max(np.abs(move))) if move.size else 0.0
        step = _settled(move, options.tol)
        x = x_new
        last_fresh = fresh
        if not nonlinear or (it >= len(widths) and step):
            converged = True
            break
    if not last_fresh:
        lu = None  # made at an earlier state: the marginals re-factorise at x when asked
    return _finish(graph, problem, x, it, converged, t0, "scipy", lu, last_step)

"""The crowd-SLAM factor graph: 2-D node positions and per-segment walk nuisances (slam.md 4.2, 4.5, 4.6).

Unknowns: a position ``p_i`` (site frame, m) per node and a nuisance ``n_k = (a_k, b_k)`` per walk segment,
``a = s cos(beta)``, ``b = s sin(beta)`` (step-length scale s, heading bias beta). With ``T(n) D = a D + b perp(D)``,
``perp(D) = (-D_y, D_x)``, the factors are (every residual whitened by ``W``, ``W^T W = cov^-1``):

=================  ==============================================  ==========  ============
factor             residual r                                       linear?     kernel
=================  ==============================================  ==========  ============
odometry i->j, k   p_j - p_i - (a_k D + b_k perp(D))                 yes         none
nuisance prior     n_k - mean                                        yes         none
nuisance link      n_l - n_k                                         yes         none
position prior     p_i - z                                           yes         optional
loop               p_i - p_j - offset                                yes         GNC-GM default
field (node/edge)  max(0, d(q) - margin) / sigma, q = (1-f)p_i+f p_j  no (GN)     none
=================  ==============================================  ==========  ============

Storage is by arrays (one row per factor, appended in chunks and concatenated once), so a graph of
10^5 nodes is built with a few bulk calls (``add_odometry_many``, ``add_loops_many`` ...) and no Python
loop per factor. The single-factor adders are thin wrappers of the bulk ones.

The models (:class:`OdometryModel`, :class:`FieldModel`, :class:`EdgeFieldModel`) are the small classes
(``evaluate``, ``jacobian``, ``covariance``) of one factor, used by the tests to check the analytic
Jacobians against finite differences; the solver evaluates the same formulas vectorised
(:func:`odometry_residual`, :func:`field_residual`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ..estimation.models import MeasurementModel

#: kernel kinds and their integer codes in the factor arrays (0: plain least squares)
KERNEL_CODES = {"gm": 1, "cauchy": 2, "huber": 3, "dcs": 4}


@dataclass(frozen=True)
class Kernel:
    """Robust kernel on a factor's whitened residual norm r = sqrt(chi2), one weight per factor (not per
    scalar residual: a 2-D loop is kept or dropped whole, slam.md 2.2). IRLS weights, c the width:

    * ``gm``     Geman-McClure, w = (c^2 / (c^2 + r^2))^2, annealed by GNC (the width is multiplied by
      :attr:`SolveOptions.gnc_widths`, from wide = nearly convex to c);
    * ``cauchy`` w = 1 / (1 + r^2 / c^2);
    * ``huber``  w = min(1, c / r);
    * ``dcs``    dynamic covariance scaling (Agarwal 2013) with Phi = c^2: s = min(1, 2 Phi / (Phi + r^2)), w = s^2.
    """

    kind: str
    c: float = 1.0

    def __post_init__(self):
        if self.kind not in KERNEL_CODES:
            raise ValueError(f"unknown kernel kind {self.kind!r} (one of {sorted(KERNEL_CODES)})")
        if not self.c > 0:
            raise ValueError("kernel width c must be > 0")

    def weight(self, r) -> np.ndarray:
        return kernel_weight(np.full(np.shape(r), KERNEL_CODES[self.kind]), np.full(np.shape(r), self.c), np.asarray(r, dtype=float))


def kernel_weight(code: np.ndarray, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Vectorised IRLS weight of each factor: code (see :data:`KERNEL_CODES`, 0 = weight 1), width c, r = sqrt(chi2)."""
    r2 = r * r
    c2 = c * c
    w = np.ones_like(r2)
    gm = code == 1
    w[gm] = (c2[gm] / (c2[gm] + r2[gm])) ** 2
    ca = code == 2
    w[ca] = 1.0 / (1.0 + r2[ca] / c2[ca])
    hu = (code == 3) & (r > c)
    w[hu] = c[hu] / r[hu]
    dc = code == 4
    s = np.minimum(1.0, 2.0 * c2[dc] / (c2[dc] + r2[dc]))
    w[dc] = s * s
    return w


def kernel_rho(code: np.ndarray, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The robust cost rho(r) whose IRLS weight is :func:`kernel_weight` (w = rho'(r) / r, rho(0) = 0;
    plain least squares rho = r^2 / 2), so that IRLS is the half-quadratic majorise-minimise of
    sum rho (Zhang 1997): with s = r^2 and dro/ds = w / 2,

    * GM      rho = c^2 s / (2 (c^2 + s))
    * Cauchy  rho = c^2 / 2 ln(1 + s / c^2)
    * Huber   rho = s / 2 for r <= c, c r - c^2 / 2 beyond
    * DCS     rho = s / 2 for s <= Phi, 3 Phi / 2 - 2 Phi^2 / (Phi + s) beyond (Phi = c^2)."""
    r = np.asarray(r, dtype=float)
    s = r * r
    c2 = c * c
    out = 0.5 * s
    gm = code == 1
    out[gm] = c2[gm] * s[gm] / (2.0 * (c2[gm] + s[gm]))
    ca = code == 2
    out[ca] = 0.5 * c2[ca] * np.log1p(s[ca] / c2[ca])
    hu = (code == 3) & (r > c)
    out[hu] = c[hu] * r[hu] - 0.5 * c2[hu]
    dc = (code == 4) & (s > c2)
    out[dc] = 1.5 * c2[dc] - 2.0 * c2[dc] ** 2 / (c2[dc] + s[dc])
    return out


class ScalarField(Protocol):
    """The floor plan's walkable field: p (m,2) -> distance outside the walkable area d (m,) (0 inside), m,
    and its gradient (m,2)."""

    def __call__(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def sqrt_information(cov) -> np.ndarray:
    """Whitening matrices W (..., 2, 2) with W^T W = cov^-1: W = L^-1 for cov = L L^T (Cholesky).

    Then ``W r`` has identity covariance, and ``|W r|^2`` is the factor's chi2."""
    cov = np.asarray(cov, dtype=float)
    L = np.linalg.cholesky(cov)
    return np.linalg.inv(L)


def perp(D: np.ndarray) -> np.ndarray:
    """perp(D) = (-D_y, D_x): D turned by +90 degrees."""
    D = np.asarray(D, dtype=float)
    return np.stack([-D[..., 1], D[..., 0]], axis=-1)


def odometry_residual(p_i: np.ndarray, p_j: np.ndarray, n: np.ndarray, D: np.ndarray) -> np.ndarray:
    """r = p_j - p_i - (a D + b perp(D)) (slam.md 4.2), rows of (m,2); n = (a, b) per row."""
    return p_j - p_i - (n[..., :1] * D + n[..., 1:2] * perp(D))


def field_residual(q: np.ndarray, field: ScalarField, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Unwhitened field residual e(q) = max(0, d(q) - margin) and de/dq (m,2) (zero where e = 0: inside
    the margin the factor is flat), slam.md 4.5."""
    d, g = field(np.asarray(q, dtype=float).reshape(-1, 2))
    d = np.asarray(d, dtype=float)
    active = d > margin
    e = np.where(active, d - margin, 0.0)
    J = np.where(active[:, None], np.asarray(g, dtype=float), 0.0)
    return e, J


class OdometryModel(MeasurementModel):
    """Odometry i -> j of a walk in segment k, as a model of x = (p_i, p_j, a_k, b_k) (6,):
    h(x) = p_j - p_i - (a D + b perp(D)) ~ N(0, S), S the covariance of the dead-reckoned D."""

    kind = "odometry"

    def __init__(self, delta, cov):
        self.D = np.asarray(delta, dtype=float).reshape(2)
        self.S = np.asarray(cov, dtype=float).reshape(2, 2)

    def evaluate(self, x) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        return odometry_residual(x[0:2], x[2:4], x[4:6], self.D)

    def jacobian(self, x) -> np.ndarray:
        # dr/dp_i = -I, dr/dp_j = I, dr/da = -D, dr/db = -perp(D)
        return np.hstack([-np.eye(2), np.eye(2), -self.D[:, None], -perp(self.D)[:, None]])

    def covariance(self, x=None) -> np.ndarray:
        return self.S


class FieldModel(MeasurementModel):
    """Walkable factor on one node, x = p (2,): h = max(0, d(p) - margin) ~ N(0, sigma^2) (slam.md 4.5)."""

    kind = "field"

    def __init__(self, field: ScalarField, sigma: float, margin: float = 0.0):
        self.field, self.sigma, self.margin = field, float(sigma), float(margin)

    def evaluate(self, x) -> np.ndarray:
        return field_residual(np.asarray(x, dtype=float)[None, :], self.field, self.margin)[0]

    def jacobian(self, x) -> np.ndarray:
        return field_residual(np.asarray(x, dtype=float)[None, :], self.field, self.margin)[1]

    def covariance(self, x=None) -> np.ndarray:
        return np.array([[self.sigma**2]])


class EdgeFieldModel(FieldModel):
    """Walkable factor on the point q = (1 - f) p_i + f p_j of an odometry edge, x = (p_i, p_j) (4,):
    h = max(0, d(q) - margin), dh/dp_i = (1 - f) grad d(q), dh/dp_j = f grad d(q)."""

    kind = "edge_field"

    def __init__(self, field: ScalarField, sigma: float, margin: float = 0.0, fraction: float = 0.5):
        super().__init__(field, sigma, margin)
        self.f = float(fraction)

    def _q(self, x):
        x = np.asarray(x, dtype=float)
        return ((1.0 - self.f) * x[0:2] + self.f * x[2:4])[None, :]

    def evaluate(self, x) -> np.ndarray:
        return field_residual(self._q(x), self.field, self.margin)[0]

    def jacobian(self, x) -> np.ndarray:
        g = field_residual(self._q(x), self.field, self.margin)[1]
        return np.hstack([(1.0 - self.f) * g, self.f * g])


@dataclass
class FieldGroup:
    """Field factors sharing one field: point q = (1 - f) p_ia + f p_ib (a node factor has ia = ib, f = 0)."""

    field: ScalarField
    ia: np.ndarray
    ib: np.ndarray
    f: np.ndarray
    sigma: float
    margin: float


def _ids(x, n_max: int, what: str) -> np.ndarray:
    a = np.atleast_1d(np.asarray(x, dtype=np.int64))
    if a.size and (a.min() < 0 or a.max() >= n_max):
        raise IndexError(f"{what} id out of range [0, {n_max})")
    return a


def _vec2(x, m: int) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    return np.broadcast_to(a, (m, 2)).copy() if a.ndim <= 1 else a.reshape(m, 2)


def _cov2(x, m: int) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim == 0:  # a scalar is a variance: cov = var * I
        a = a * np.eye(2)
    return np.broadcast_to(a, (m, 2, 2)).copy() if a.ndim == 2 else a.reshape(m, 2, 2)


def _kernel_arrays(kernel, m: int) -> tuple[np.ndarray, np.ndarray]:
    if kernel is None:
        return np.zeros(m, dtype=np.int8), np.ones(m)
    return np.full(m, KERNEL_CODES[kernel.kind], dtype=np.int8), np.full(m, float(kernel.c))


class _Table:
    """Columns appended in chunks, concatenated on first read after a change."""

    def __init__(self, **cols):
        self._chunks: dict[str, list[np.ndarray]] = {k: [np.zeros((0, *shape), dtype=dt)] for k, (shape, dt) in cols.items()}
        self._cache: dict[str, np.ndarray] = {}
        self.n = 0

    def append(self, **cols) -> np.ndarray:
        m = len(next(iter(cols.values())))
        for k, v in cols.items():
            self._chunks[k].append(np.asarray(v))
        self._cache.clear()
        ids = np.arange(self.n, self.n + m)
        self.n += m
        return ids

    def __getitem__(self, k) -> np.ndarray:
        if k not in self._cache:
            arr = np.concatenate(self._chunks[k])
            self._chunks[k] = [arr]
            self._cache[k] = arr
        return self._cache[k]


class FactorGraph:
    """Nodes (2-D positions), walk-segment nuisances (a, b) and their factors, held in arrays."""

    def __init__(self):
        self._nodes = _Table(init=((2,), float))
        self._nuis = _Table(init=((2,), float))
        self.odometry = _Table(i=((), np.int64), j=((), np.int64), k=((), np.int64), delta=((2,), float), W=((2, 2), float))
        self.nuisance_priors = _Table(k=((), np.int64), mean=((2,), float), W=((2, 2), float))
        self.nuisance_links = _Table(k=((), np.int64), l=((), np.int64), W=((2, 2), float))
        self.priors = _Table(i=((), np.int64), z=((2,), float), W=((2, 2), float), kcode=((), np.int8), kc=((), float), cov=((2, 2), float))
        self.loops = _Table(
            i=((), np.int64),
            j=((), np.int64),
            offset=((2,), float),
            W=((2, 2), float),
            kcode=((), np.int8),
            kc=((), float),
            cov=((2, 2), float),
        )
        self.fields: list[FieldGroup] = []

    # -- sizes ---------------------------------------------------------------------------------
    @property
    def n_nodes(self) -> int:
        return self._nodes.n

    @property
    def n_nuisances(self) -> int:
        return self._nuis.n

    @property
    def n_loops(self) -> int:
        return self.loops.n

    @property
    def n_priors(self) -> int:
        return self.priors.n

    @property
    def node_init(self) -> np.ndarray:
        return self._nodes["init"]

    @property
    def nuisance_init(self) -> np.ndarray:
        return self._nuis["init"]

    # -- variables -----------------------------------------------------------------------------
    def add_nodes(self, init: np.ndarray) -> np.ndarray:
        """Add nodes at their initial positions (n,2), m; returns their ids."""
        init = np.asarray(init, dtype=float).reshape(-1, 2)
        return self._nodes.append(init=init)

    def add_nuisance(self, init=(1.0, 0.0)) -> int:
        """Add one walk-segment nuisance (a, b) with its initial value; returns its id."""
        return int(self.add_nuisances(np.asarray(init, dtype=float)[None, :])[0])

    def add_nuisances(self, init: np.ndarray) -> np.ndarray:
        return self._nuis.append(init=np.asarray(init, dtype=float).reshape(-1, 2))

    # -- factors (bulk) ------------------------------------------------------------------------
    def add_odometry_many(self, i, j, delta, cov, k) -> np.ndarray:
        """Odometry rows i -> j in segments k: D (m,2) dead-reckoned displacement, cov (m,2,2) or (2,2)."""
        i = _ids(i, self.n_nodes, "node")
        m = i.size
        j = _ids(np.broadcast_to(j, (m,)), self.n_nodes, "node")
        k = _ids(np.broadcast_to(k, (m,)), self.n_nuisances, "nuisance")
        return self.odometry.append(i=i, j=j, k=k, delta=_vec2(delta, m), W=sqrt_information(_cov2(cov, m)))

    def add_nuisance_priors_many(self, k, mean, cov) -> np.ndarray:
        k = _ids(k, self.n_nuisances, "nuisance")
        m = k.size
        return self.nuisance_priors.append(k=k, mean=_vec2(mean, m), W=sqrt_information(_cov2(cov, m)))

    def add_nuisance_links_many(self, k, l, cov) -> np.ndarray:
        k = _ids(k, self.n_nuisances, "nuisance")
        m = k.size
        l = _ids(np.broadcast_to(l, (m,)), self.n_nuisances, "nuisance")
        return self.nuisance_links.append(k=k, l=l, W=sqrt_information(_cov2(cov, m)))

    def add_position_priors_many(self, i, z, cov, kernel: Kernel | None = None) -> np.ndarray:
        i = _ids(i, self.n_nodes, "node")
        m = i.size
        cov = _cov2(cov, m)
        kcode, kc = _kernel_arrays(kernel, m)
        return self.priors.append(i=i, z=_vec2(z, m), W=sqrt_information(cov), kcode=kcode, kc=kc, cov=cov)

    def add_loops_many(self, i, j, cov, offset=(0.0, 0.0), kernel: Kernel | None = Kernel("gm", 1.0)) -> np.ndarray:
        """Loops p_i - p_j - offset ~ N(0, cov) under a robust kernel (one weight per loop)."""
        i = _ids(i, self.n_nodes, "node")
        m = i.size
        j = _ids(np.broadcast_to(j, (m,)), self.n_nodes, "node")
        cov = _cov2(cov, m)
        kcode, kc = _kernel_arrays(kernel, m)
        return self.loops.append(i=i, j=j, offset=_vec2(offset, m), W=sqrt_information(cov), kcode=kcode, kc=kc, cov=cov)

    # -- factors (single: the spec's API) --------------------------------------------------------
    def add_odometry(self, i, j, delta, cov, k) -> int:
        return int(self.add_odometry_many([i], [j], np.reshape(delta, (1, 2)), np.reshape(cov, (1, 2, 2)), [k])[0])

    def add_nuisance_prior(self, k, mean=(1.0, 0.0), cov=((0.1**2, 0.0), (0.0, 0.14**2))) -> int:
        """(a, b)_k ~ N(mean, cov); the default is slam.md 3.1: scale sd 0.1, heading bias sd 0.14 (~8 deg)."""
        return int(self.add_nuisance_priors_many([k], np.reshape(mean, (1, 2)), np.reshape(cov, (1, 2, 2)))[0])

    def add_nuisance_link(self, k, l, cov) -> int:
        return int(self.add_nuisance_links_many([k], [l], np.reshape(cov, (1, 2, 2)))[0])

    def add_position_prior(self, i, z, cov, kernel: Kernel | None = None) -> int:
        return int(self.add_position_priors_many([i], np.reshape(z, (1, 2)), np.reshape(cov, (1, 2, 2)), kernel)[0])

    def add_loop(self, i, j, cov, offset=(0.0, 0.0), kernel: Kernel | None = Kernel("gm", 1.0)) -> int:
        return int(self.add_loops_many([i], [j], np.reshape(cov, (1, 2, 2)), np.reshape(offset, (1, 2)), kernel)[0])

    def add_field(self, nodes, field: ScalarField, sigma, margin=0.0) -> None:
        """Walkable factor max(0, d(p_i) - margin) / sigma on each node."""
        nodes = _ids(nodes, self.n_nodes, "node")
        self.fields.append(FieldGroup(field, nodes, nodes, np.zeros(nodes.size), float(sigma), float(margin)))

    def add_edge_field(self, i, j, field: ScalarField, sigma, margin=0.0, fractions=(1 / 3, 2 / 3)) -> None:
        """Walkable factors at the points (1 - f) p_i + f p_j, f in ``fractions``, of each edge i -> j."""
        i = _ids(i, self.n_nodes, "node")
        j = _ids(np.broadcast_to(j, i.shape), self.n_nodes, "node")
        fr = np.asarray(fractions, dtype=float)
        self.fields.append(FieldGroup(field, np.repeat(i, fr.size), np.repeat(j, fr.size), np.tile(fr, i.size), float(sigma), float(margin)))

"""Finite-difference Jacobians: the default of :meth:`.models.MeasurementModel.jacobian` and the
oracle every analytic Jacobian is tested against (as navlie's ``jacobian_fd`` and its model tests).

The derivative is taken with respect to the error state ``dx`` injected by the state's own ``plus``
(a plain vector: ``x + dx``), and through the model's ``residual``, so heading models are
differenced across +-pi without a 2 pi jump:

    H[:, i] = (r(h(x (+) eps e_i), h(x)) - r(h(x (+) -eps e_i), h(x))) / (2 eps)

with r(a, b) = a - b wrapped where the model says its components are angles. Central differences
have a truncation error of O(eps^2 h''') and a rounding error of O(u |h| / eps), u = 2.2e-16: with
eps = 1e-6 both sit near 1e-10 for the models here (values and curvatures of order 1-100).
"""

from __future__ import annotations

import numpy as np


def state_plus(x, dx: np.ndarray):
    """x (+) dx: the state's own ``plus`` when it has one (a manifold state), else vector addition."""
    plus = getattr(x, "plus", None)
    return plus(dx) if plus is not None else np.asarray(x, dtype=float) + dx


def state_dof(model, x) -> int:
    """Degrees of freedom of the error state: the model's ``state_dof``, else the state's ``dof``, else its size."""
    dof = getattr(model, "state_dof", None) or getattr(x, "dof", None)
    return int(dof) if dof else int(np.size(x))


def jacobian_fd(model, x, eps: float = 1e-6) -> np.ndarray:
    """dh/d(dx) by central differences through ``x (+) dx`` and the model's residual, shape (m, dof)."""
    z0 = np.asarray(model.evaluate(x), dtype=float)
    n = state_dof(model, x)
    H = np.zeros((z0.size, n))
    d = np.zeros(n)
    for i in range(n):
        d[i] = eps
        hp = model.residual(model.evaluate(state_plus(x, d)), z0)
        d[i] = -eps
        hm = model.residual(model.evaluate(state_plus(x, d)), z0)
        d[i] = 0.0
        H[:, i] = (np.asarray(hp, dtype=float) - np.asarray(hm, dtype=float)) / (2.0 * eps)
    return H


def jacobian_error(model, x, eps: float = 1e-6) -> float:
    """Largest absolute difference between the model's analytic Jacobian and :func:`jacobian_fd`."""
    return float(np.max(np.abs(np.asarray(model.jacobian(x), dtype=float) - jacobian_fd(model, x, eps)), initial=0.0))


def assert_jacobian(model, x, atol: float = 1e-6, rtol: float = 1e-4, eps: float = 1e-6) -> None:
    """Raise AssertionError when the analytic Jacobian departs from finite differences (navlie's
    tolerances: ``atol=1e-6, rtol=1e-4``, well above the ~1e-10 error of the differences)."""
    np.testing.assert_allclose(
        model.jacobian(x),
        jacobian_fd(model, x, eps),
        atol=atol,
        rtol=rtol,
        err_msg=f"{type(model).__name__}: analytic Jacobian differs from finite differences",
    )

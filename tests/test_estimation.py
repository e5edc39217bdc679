"""The one estimation core: every measurement model's Jacobian against finite differences, the gated
Joseph update by hand and by Monte Carlo, robust kernels, resamplers and the particle filter's log-weights."""

import math

import numpy as np
import pytest
from scipy.stats import chi2

from hybridloc.estimation import (
    RESAMPLERS,
    Cauchy,
    ChiSquareGate,
    Huber,
    LinearModel,
    Measurement,
    MeasurementModel,
    UpdateStats,
    assert_jacobian,
    correct,
    jacobian_fd,
    log_normalise,
    resampler,
)
from hybridloc.fusion import measurements as fm
from hybridloc.ins import measurements as im
from hybridloc.ins.strapdown import NominalState, quat_from_rotvec


# ---------------------------------------------------------------- Jacobians against finite differences
def _ins_state(rng):
    q = quat_from_rotvec(rng.normal(size=3))
    return NominalState(rng.normal(size=3), rng.normal(size=3), q / np.linalg.norm(q), 0.01 * rng.normal(size=3), 0.001 * rng.normal(size=3))


def _fusion_state(rng):
    return np.array([*rng.normal(0, 10, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0.7, 1.3)])


INS_MODELS = {
    "zupt": lambda rng: im.ZeroVelocity(),
    "zaru": lambda rng: im.ZeroAngularRate(rng.normal(0, 0.05, 3)),
    "heading-x": lambda rng: im.Heading(),
    "heading-tilted-axis": lambda rng: im.Heading(rng.normal(size=3)),
    "position-2d": lambda rng: im.PositionFix(np.eye(2)),
    "position-3d": lambda rng: im.PositionFix(np.eye(3)),
}
FUSION_MODELS = {
    "position": lambda rng: fm.PositionFix(np.eye(2)),
    "position-late": lambda rng: fm.PositionFix(np.eye(2), rng.normal(0, 3, 2)),
    "displacement": lambda rng: fm.StepDisplacement(rng.normal(0, 5, 2), np.eye(2)),
    "corridor": lambda rng: fm.CorridorHeading(rng.uniform(-3, 3), 0.1),
    "velocity": lambda rng: fm.Velocity(np.eye(2), "still"),
}


@pytest.mark.parametrize("name", sorted(INS_MODELS))
def test_ins_model_jacobians_match_finite_differences(name):
    rng = np.random.default_rng(11)
    for _ in range(10):
        assert_jacobian(INS_MODELS[name](rng), _ins_state(rng))


@pytest.mark.parametrize("name", sorted(FUSION_MODELS))
def test_fusion_model_jacobians_match_finite_differences(name):
    rng = np.random.default_rng(12)
    for _ in range(10):
        assert_jacobian(FUSION_MODELS[name](rng), _fusion_state(rng))


def test_kourogi_models_jacobians_match_finite_differences():
    rng = np.random.default_rng(13)
    for _ in range(10):
        assert_jacobian(fm.CloneStep(np.eye(4)), rng.normal(0, 5, 6))
        assert_jacobian(fm.Velocity(np.eye(2), "gps-velocity"), rng.normal(0, 5, 4))
        assert_jacobian(LinearModel(rng.normal(size=(3, 5)), np.eye(3)), rng.normal(size=5))


class _Range(MeasurementModel):
    """h = |p - a| with no analytic Jacobian: the default falls back to finite differences."""

    kind = "range"

    def __init__(self, anchor):
        self.a = np.asarray(anchor, float)

    def evaluate(self, x):
        return np.array([np.linalg.norm(x[:2] - self.a)])

    def covariance(self, x=None):
        return np.eye(1)


def test_default_jacobian_is_finite_differences_of_the_right_derivative():
    x = np.array([3.0, 4.0, 0.2])
    H = _Range([0.0, 0.0]).jacobian(x)
    # d|p|/dp = p / |p| = (0.6, 0.8); central differences err by O(eps^2) + O(u / eps) ~ 1e-10
    np.testing.assert_allclose(H, [[0.6, 0.8, 0.0]], atol=1e-8)


def test_finite_differences_wrap_angles_across_pi():
    # corrected heading at pi - 1e-7: +-1e-6 crosses the cut, an unwrapped difference would be ~2 pi / 2e-6
    x = np.array([0.0, 0.0, math.pi - 1e-7 - 0.5, 1.0])
    np.testing.assert_allclose(jacobian_fd(fm.CorridorHeading(0.5, 0.1), x), [[0.0, 0.0, 1.0, 0.0]], atol=1e-8)


def test_residual_wraps_angles_only_where_told():
    m = fm.CorridorHeading(0.0, 0.1)
    assert m.residual(np.array([math.pi - 0.01]), np.array([-math.pi + 0.01]))[0] == pytest.approx(-0.02, abs=1e-12)
    assert LinearModel(np.eye(1), np.eye(1)).residual(np.array([math.pi - 0.01]), np.array([-math.pi + 0.01]))[0] == pytest.approx(2 * math.pi - 0.02)


# ---------------------------------------------------------------- the gated update
def test_scalar_update_by_hand():
    """x = 0, P = 4, z = 1, R = 1: S = 5, K = 4/5, dx = 4/5, P+ = (1 - K)^2 4 + K^2 1 = 4/5, NIS = 1/5."""
    dx, P, info = correct(np.zeros(1), np.array([[4.0]]), np.array([1.0]), LinearModel(np.eye(1), np.eye(1)))
    assert info.accepted and info.S[0, 0] == pytest.approx(5.0) and info.nis == pytest.approx(0.2)
    assert dx[0] == pytest.approx(0.8) and P[0, 0] == pytest.approx(0.8)


def test_two_state_update_by_hand():
    """Position and velocity, P = diag(1, 1) with covariance 0.5; observe the position z = 2, R = 1:
    S = 2, K = (1/2, 1/4), dx = K z = (1, 1/2), P+ = P - K S K^T = [[1/2, 1/4], [1/4, 7/8]]."""
    P = np.array([[1.0, 0.5], [0.5, 1.0]])
    dx, P1, info = correct(np.zeros(2), P, np.array([2.0]), LinearModel([[1.0, 0.0]], [[1.0]]))
    np.testing.assert_allclose(dx, [1.0, 0.5], rtol=1e-15)
    np.testing.assert_allclose(P1, [[0.5, 0.25], [0.25, 0.875]], rtol=1e-15)
    assert info.nis == pytest.approx(2.0)  # 2^2 / 2


def test_update_leaves_its_inputs_alone_and_joseph_equals_the_standard_form():
    rng = np.random.default_rng(20)
    A = rng.normal(size=(5, 5))
    P = A @ A.T + np.eye(5)
    x = rng.normal(size=5)
    P0, x0 = P.copy(), x.copy()
    model = LinearModel(rng.normal(size=(3, 5)), np.diag([0.5, 1.0, 2.0]))
    dx, P1, info = correct(x, P, rng.normal(size=3), model)
    assert np.array_equal(P, P0) and np.array_equal(x, x0)
    K = P @ model.H.T @ np.linalg.inv(info.S)
    # with the optimal gain the Joseph form equals (I - K H) P, up to rounding (norm of P ~ 10, u ~ 2e-16)
    np.testing.assert_allclose(P1, (np.eye(5) - K @ model.H) @ P, atol=1e-12)


@pytest.mark.parametrize("n", [2, 4, 15])
def test_compiled_update_is_numpys_to_the_bit(n):
    """The update's compiled arithmetic (estimation/_compiled.py, asked for by the foot filter, taken for
    m <= 3 without a robust kernel) against its numpy reference, on random states, general and block-selecting models of 1-3
    components, gated and not: the same S, NIS, decision, dx and P+ to the last bit."""
    from hybridloc.estimation.update import _update_numpy

    rng = np.random.default_rng(n)
    n_rejected = 0
    for trial in range(300):
        A = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-3, 1, n)
        P = A @ A.T + 1e-9 * np.eye(n)
        m = int(rng.integers(1, min(3, n) + 1))
        R = np.diag(rng.uniform(0.01, 2.0, m))
        if trial % 2:
            start = int(rng.integers(0, n - m + 1))
            H = np.zeros((m, n))
            H[:, start : start + m] = np.eye(m)
            model = LinearModel(H, R)
            model.selects = slice(start, start + m)
        else:
            model = LinearModel(rng.normal(size=(m, n)), R)
        x, z = rng.normal(size=n), rng.normal(0, 3, m)
        gate = 0.99 if trial % 3 else None
        dx, P1, info = correct(x, P, z, model, gate, compiled=True)
        threshold = chi2.ppf(0.99, m) if gate else math.inf
        y = model.residual(z, model.evaluate(x))
        dx_ref, P_ref, ref = _update_numpy(P, model.H, model.R, y, model, threshold, info.kind, None)
        assert info.accepted == ref.accepted and info.nis == ref.nis and np.array_equal(info.S, ref.S)
        assert np.array_equal(dx, dx_ref) and np.array_equal(P1, P_ref)
        n_rejected += not info.accepted
    assert n_rejected > 0  # the gate was exercised


def test_update_with_a_covariance_that_is_not_positive_definite_takes_numpys_path():
    """S = H P H^T + R not positive definite: the closed-form inverse declines and numpy's inverse
    answers, as before the compiled path existed."""
    P = np.array([[1.0, 0.0], [0.0, -3.0]])
    dx, P1, info = correct(np.zeros(2), P, np.array([1.0, 1.0]), LinearModel(np.eye(2), np.eye(2)), compiled=True)
    np.testing.assert_allclose(info.S, [[2.0, 0.0], [0.0, -2.0]])
    assert info.nis == pytest.approx(0.5 - 0.5)


def test_joseph_form_stays_symmetric_positive_definite():
    """Hundreds of very precise updates (R = 1e-8) of an ill-conditioned covariance (1e-4 .. 1e4): the
    returned covariance is exactly symmetric and positive definite every time (the standard form
    (I - K H) P comes out asymmetric in the rounding at every one of these updates)."""
    rng = np.random.default_rng(21)
    P = np.diag([1e4, 1e-4, 1.0, 1e2])
    x = np.zeros(4)
    for _ in range(500):
        H = rng.normal(size=(2, 4))
        dx, P, info = correct(x, P, rng.normal(size=2), LinearModel(H, np.eye(2) * 1e-8))
        x = x + dx
        P = P + np.eye(4) * 1e-6  # a little process noise, as between updates
        assert np.array_equal(P, P.T)
        assert np.linalg.eigvalsh(P).min() > 0.0


@pytest.mark.parametrize("m", [1, 2, 3, 5])
def test_nis_of_consistent_data_is_chi_square(m):
    """x ~ N(0, P), z = H x + v, v ~ N(0, R): the NIS is chi2(m). Over N seeded trials its mean is m
    within 4 standard errors sqrt(2 m / N), and the 95 % gate accepts 95 % within 4 binomial sigmas."""
    rng = np.random.default_rng(100 + m)
    n, trials = 4, 4000
    A = rng.normal(size=(n, n))
    P = A @ A.T + np.eye(n)
    model = LinearModel(rng.normal(size=(m, n)), np.diag(rng.uniform(0.5, 2.0, m)))
    Lp, Lr = np.linalg.cholesky(P), np.linalg.cholesky(model.R)
    stats = UpdateStats()
    nis = np.empty(trials)
    for k in range(trials):
        x_true = Lp @ rng.standard_normal(n)
        z = model.H @ x_true + Lr @ rng.standard_normal(m)
        nis[k] = correct(np.zeros(n), P, z, model, ChiSquareGate(0.95), stats)[2].nis
    assert abs(nis.mean() - m) < 4 * math.sqrt(2 * m / trials)
    acc = stats.accepted["linear"] / trials
    assert abs(acc - 0.95) < 4 * math.sqrt(0.95 * 0.05 / trials)
    assert stats.accepted["linear"] + stats.rejected["linear"] == trials


def test_an_outlier_is_rejected_and_counted_by_kind():
    stats = UpdateStats()
    P = np.eye(4)
    x = np.array([0.0, 0.0, 0.0, 1.0])
    model = fm.PositionFix(np.eye(2))
    dx, P1, info = correct(x, P, np.array([30.0, 0.0]), model, 0.95, stats)
    assert not info.accepted and info.dx is None and not dx.any() and P1 is P
    assert info.nis == pytest.approx(30.0**2 / 2) and info.threshold == pytest.approx(chi2.ppf(0.95, 2))
    correct(x, P, np.array([0.5, 0.0]), model, 0.95, stats)
    correct(x, P, np.array([0.0]), fm.CorridorHeading(0.0, 0.1), 0.95, stats)
    assert stats.rejected == {"position": 1} and stats.accepted == {"position": 1, "corridor": 1} and stats.n_rejected == 1
    # no gate: the same outlier goes in
    assert correct(x, P, np.array([30.0, 0.0]), model, None)[2].accepted


def test_gate_with_a_fixed_dimension():
    """A 1-D innovation gated with the 2-D 95 % threshold (5.99, i.e. 98.6 % in 1-D), as the corridor update keeps it."""
    g = ChiSquareGate(0.95, dim=2)
    assert g.threshold(1) == pytest.approx(chi2.ppf(0.95, 2)) and chi2.cdf(g.threshold(1), 1) == pytest.approx(0.9857, abs=1e-4)


# ---------------------------------------------------------------- robust kernels
def test_robust_kernel_weights():
    h, c = Huber(1.345), Cauchy(2.3849)
    assert h.weight(1.0) == 1.0 and h.weight(2.69) == pytest.approx(0.5)
    assert c.weight(0.0) == 1.0 and c.weight(2.3849) == pytest.approx(0.5)


class _KernelFix(fm.PositionFix):
    def __init__(self, R, kernel):
        super().__init__(R)
        self.kernel = kernel


def test_robust_kernel_inflates_r_by_its_weight():
    """P = R = I and an innovation of 10 along x: S = 2 I, NIS = 100 / 2 = 50, r = 7.07; Huber(1.345)
    weighs it w = 1.345 / 7.07, i.e. R becomes R / w, and the correction K y = y / (1 + 1 / w)."""
    P = np.eye(2)
    y = np.array([10.0, 0.0])
    dx_plain, _, _ = correct(np.zeros(2), P, y, fm.PositionFix(np.eye(2)))
    dx_rob, _, info = correct(np.zeros(2), P, y, _KernelFix(np.eye(2), Huber()))
    w = 1.345 / math.sqrt(50.0)
    assert info.weight == pytest.approx(w)
    np.testing.assert_allclose(dx_rob, y / (1.0 + 1.0 / w), rtol=1e-12)
    assert dx_rob[0] < dx_plain[0] == pytest.approx(5.0)
    # within the kernel's quadratic zone nothing changes
    dx_in, _, info_in = correct(np.zeros(2), P, np.array([0.5, 0.0]), _KernelFix(np.eye(2), Huber()))
    assert info_in.weight == 1.0 and dx_in[0] == pytest.approx(0.25)


# ---------------------------------------------------------------- the measurement carries its model
def test_local_fusion_update_takes_any_measurement_and_counts_by_kind():
    from hybridloc.fusion import LocalFusion
    from hybridloc.types import AbsoluteFix

    f = LocalFusion(init=(0.0, 0.0, 1.0))
    info = f.update(Measurement(np.array([0.5, 0.0]), fm.PositionFix(np.eye(2))))
    assert info.accepted and f.x[0] == pytest.approx(0.25)
    ok, _ = f.correct(AbsoluteFix(0.0, [100.0, 0.0], np.eye(2), "wifi"))
    assert not ok and f.stats.rejected["position"] == 1 and f.n_rejected == 1
    with pytest.raises(TypeError):
        f.correct("not a fix")


# ---------------------------------------------------------------- resampling and log-weights
def test_log_normalise_does_not_underflow():
    logw = np.array([-2000.0, -2001.0, -np.inf])
    out, total = log_normalise(logw)
    w = np.exp(out)
    assert w.sum() == pytest.approx(1.0) and w[2] == 0.0 and w[0] / w[1] == pytest.approx(math.e)
    assert log_normalise(np.full(3, -np.inf))[1] == -np.inf


@pytest.mark.parametrize("name", sorted(RESAMPLERS))
def test_resamplers_are_unbiased(name):
    """E[N_i] = N w_i: the mean count over T seeded runs is within 5 standard errors of N w_i (the
    count's variance is at most multinomial's, N w_i (1 - w_i))."""
    rng = np.random.default_rng(30)
    n, runs = 50, 2000
    w = rng.gamma(0.5, size=n)
    w /= w.sum()
    scheme = resampler(name)
    counts = np.zeros(n)
    for _ in range(runs):
        idx = scheme(w, rng)
        assert idx.shape == (n,) and idx.min() >= 0 and idx.max() < n
        counts += np.bincount(idx, minlength=n)
    mean = counts / runs
    se = np.sqrt(n * w * (1 - w) / runs)
    assert np.all(np.abs(mean - n * w) <= 5 * se + 1e-12)


def test_systematic_and_residual_keep_the_whole_part_of_each_count():
    rng = np.random.default_rng(31)
    w = rng.dirichlet(np.ones(40))
    for name in ("systematic", "residual"):
        c = np.bincount(resampler(name)(w, rng), minlength=40)
        assert np.all(c >= np.floor(40 * w) - (name == "systematic"))
    c = np.bincount(resampler("systematic")(w, rng), minlength=40)
    assert np.all(np.abs(c - 40 * w) < 1.0)  # systematic: each count is floor or ceil of N w_i
    with pytest.raises(ValueError):
        resampler("nonsense")


def test_particle_filter_log_weights_constraint_hook_and_resampler():
    """A custom constraint hook (a wall at x = 3, nothing east of it) kills every particle that crosses
    it, as a -inf log-likelihood; the weights stay normalised through fixes far in the tail; each
    resampler runs."""
    from hybridloc.fusion import ParticleConfig, ParticleFusion
    from hybridloc.types import AbsoluteFix, StepEvent

    class WestOfThree:
        def log_density(self, floor, p):
            return np.where(p[:, 0] < 3.0, 0.0, -np.inf)

        def log_transition(self, floor, p, q):
            return np.zeros(len(p))

    for name in sorted(RESAMPLERS):
        pf = ParticleFusion(None, ParticleConfig(n_particles=300, seed=4), init=(0.0, 0.0, 0.3), constraint=WestOfThree(), resampler=name)
        for k in range(10):
            e = pf.predict(StepEvent(0.5 * (k + 1), 0.7, 0.0, 0.05, math.radians(3)))
        assert np.all(pf.p[pf.w > 0, 0] < 3.0) and e.pos[0] < 3.0
        assert pf.w.sum() == pytest.approx(1.0) and np.isfinite(pf.logw[pf.w > 0]).all()
        ok, e = pf.correct(AbsoluteFix(5.0, [2.0, 1.5], np.eye(2) * 0.5, "wifi"))
        assert pf.w.sum() == pytest.approx(1.0)
    with pytest.raises(ValueError):
        ParticleFusion(None, ParticleConfig(n_particles=300), resampler="nonsense")

"""Dead reckoning written once (:mod:`hybridloc.pdr.deadreckoning`): walks whose positions follow by hand,
the covariance growth against its closed form, position at any time, and bad input."""

import math

import numpy as np
import pytest

from hybridloc.pdr import DeadReckoning, dead_reckon
from hybridloc.types import StepEvent

# cos(pi/2), sin(pi) ... are not 0 in floating point but ~6e-17 (pi is rounded): a square walk closes
# to within a few of those per step, times the step length
ROUND = 1e-15


SIGMA_HEADING = math.radians(5.0)


def _steps(headings, length=0.5, t0=10.0, dt=0.5, sigma_length=0.05, sigma_heading=SIGMA_HEADING):
    return [StepEvent(t0 + dt * (i + 1), length, h, sigma_length, sigma_heading) for i, h in enumerate(headings)]


def test_straight_walk_east_is_exact():
    steps = [StepEvent(1.0 + 0.5 * i, L, 0.0, 0.01, 0.01) for i, L in enumerate([0.5, 0.75, 0.5, 0.25], start=1)]
    dr = DeadReckoning.from_steps(steps, pos0=(1.0, 2.0))
    # binary-exact lengths along heading 0 (cos 0 = 1, sin 0 = 0): every sum is exact
    assert dr.t.tolist() == [0.5, 1.5, 2.0, 2.5, 3.0]  # start 1 s before the first step
    assert dr.pos_enu.tolist() == [[1.0, 2.0], [1.5, 2.0], [2.25, 2.0], [2.75, 2.0], [3.0, 2.0]]
    assert dr.position.tolist() == [3.0, 2.0] and dr.n_steps == 4 and len(dr) == 5


def test_square_walk_comes_back():
    side = 3  # steps of 0.5 m a side: a 1.5 m square, counter-clockwise from East
    steps = _steps([h for h in (0.0, math.pi / 2, math.pi, -math.pi / 2) for _ in range(side)])
    dr = DeadReckoning.from_steps(steps)
    corners = dr.pos_enu[side::side]
    np.testing.assert_allclose(corners, [[1.5, 0.0], [1.5, 1.5], [0.0, 1.5], [0.0, 0.0]], rtol=0, atol=len(steps) * 0.5 * ROUND * 4)
    assert dr.to_trajectory().distance_travelled == pytest.approx(6.0, rel=1e-14)


@pytest.mark.parametrize("psi", [0.0, 0.3, 2.0, -2.5])
def test_covariance_grows_as_the_closed_form(psi):
    n, L, sl, sp = 40, 0.7, 0.04, math.radians(8.0)
    dr = DeadReckoning.from_steps(_steps([psi] * n, length=L, sigma_length=sl, sigma_heading=sp), cov0=np.diag([0.25, 0.25]))
    d, dp = np.array([math.cos(psi), math.sin(psi)]), np.array([-math.sin(psi), math.cos(psi)])
    for k in (0, 1, 10, n):
        C = dr.cov_enu[k]
        # Kourogi eqs 11-14 summed over k steps along one heading, on top of the start covariance
        assert d @ C @ d == pytest.approx(0.25 + k * sl**2, rel=1e-12)
        assert dp @ C @ dp == pytest.approx(0.25 + k * (L * math.tan(sp)) ** 2, rel=1e-12)
        assert d @ C @ dp == pytest.approx(0.0, abs=1e-12 * (0.25 + k * L**2))
    tr = dr.to_trajectory()
    np.testing.assert_array_equal(tr.sigma_enu[:, :2], np.sqrt(np.diagonal(dr.cov_enu, axis1=1, axis2=2)))
    assert np.all(tr.sigma_enu[:, 2] == 0.0) and np.all(tr.pos_enu[:, 2] == 0.0)


def test_position_at_steps_between_and_outside():
    steps = [StepEvent(2.0, 1.0, 0.0, 0.1, 0.1), StepEvent(3.0, 1.0, math.pi / 2, 0.1, 0.1)]
    dr = DeadReckoning.from_steps(steps, pos0=(5.0, 5.0), t0=1.0)
    # at the rows: the rows
    np.testing.assert_array_equal(dr.position_at([1.0, 2.0, 3.0]), dr.pos_enu)
    # between: constant velocity over the step
    np.testing.assert_allclose(dr.position_at(1.5), [5.5, 5.0], rtol=0, atol=ROUND * 10)
    np.testing.assert_allclose(dr.position_at(2.25), [6.0, 5.25], rtol=0, atol=ROUND * 10)
    # outside: held (at the start before t0, stopped after the last step)
    np.testing.assert_array_equal(dr.position_at(-100.0), [5.0, 5.0])
    np.testing.assert_array_equal(dr.position_at(1e9), dr.pos_enu[-1])
    assert dr.covers(1.0) and dr.covers(3.0) and not dr.covers(0.999) and not dr.covers(3.001)
    # shapes: a scalar gives (2,), M times (M, 2)
    assert dr.position_at(2.5).shape == (2,) and dr.position_at(np.linspace(0, 4, 7)).shape == (7, 2)
    # covariance: that of the last row at or before t
    np.testing.assert_array_equal(dr.covariance_at(2.5), dr.cov_enu[1])
    np.testing.assert_array_equal(dr.covariance_at([0.0, 1e9]), dr.cov_enu[[0, 2]])


def test_no_steps_holds_the_start():
    dr = DeadReckoning.from_steps([], pos0=(3.0, 4.0))
    assert len(dr) == 0 and not dr.covers(0.0)
    np.testing.assert_array_equal(dr.position_at([0.0, 1.0]), [[3.0, 4.0], [3.0, 4.0]])
    with pytest.raises(ValueError, match="no rows"):
        dr.to_trajectory()
    tr = dead_reckon([], 3.0, 4.0)  # the batch tool's convention: one row at t = 0
    assert tr.t.tolist() == [0.0] and tr.pos_enu.tolist() == [[3.0, 4.0, 0.0]]


def test_the_copies_arithmetic_is_kept_bit_for_bit():
    """A running sum from any start, cumsum of StepEvent.displacement_enu from zero (the former copies'
    two ways), streaming one step at a time, and lengths/headings given as arrays all agree to the bit."""
    rng = np.random.default_rng(18)
    steps = [
        StepEvent(float(t), float(L), float(h), 0.05, 0.1)
        for t, L, h in zip(np.cumsum(rng.uniform(0.4, 0.7, 300)), rng.uniform(0.5, 0.9, 300), rng.uniform(-math.pi, math.pi, 300))
    ]
    batch = DeadReckoning.from_steps(steps)
    cumsum = np.vstack([[0.0, 0.0], np.cumsum([s.displacement_enu for s in steps], axis=0)])
    np.testing.assert_array_equal(batch.pos_enu, cumsum)
    live = DeadReckoning(batch.t[0])
    for s in steps:
        live.add(s)
    np.testing.assert_array_equal(live.pos_enu, batch.pos_enu)
    np.testing.assert_array_equal(live.cov_enu, batch.cov_enu)
    arrays = DeadReckoning.from_lengths_headings([s.t for s in steps], [s.length for s in steps], [s.heading for s in steps])
    np.testing.assert_array_equal(arrays.pos_enu, batch.pos_enu)
    assert arrays.cov_enu is None
    # from another start: a running sum from it (not the start plus a cumsum)
    x, y, rows = 1e3 / 3, -2e3 / 7, []
    for s in steps:
        x, y = x + s.length * math.cos(s.heading), y + s.length * math.sin(s.heading)
        rows.append((x, y))
    np.testing.assert_array_equal(DeadReckoning.from_steps(steps, pos0=(1e3 / 3, -2e3 / 7)).pos_enu[1:], rows)
    # and the batch tool's Trajectory: the same positions, sigmas from the same covariance
    tr = dead_reckon(steps)
    np.testing.assert_array_equal(tr.pos_enu[:, :2], batch.pos_enu)


def test_live_track_without_start_and_with_a_bounded_history():
    steps = _steps([0.0] * 9, length=0.5, t0=0.0, dt=1.0)  # steps at t = 1 .. 9
    dr = DeadReckoning(covariance=False, max_rows=4)
    assert dr.t_last is None and not dr.covers(1.0)
    dr.add(steps[0])
    # no start row: the track begins at the first step, after its displacement
    assert dr.t.tolist() == [1.0] and dr.pos_enu.tolist() == [[0.5, 0.0]] and dr.cov_enu is None
    dr.extend(steps[1:])
    # each time a 5th row comes, the oldest 2 go: after 9 steps the rows of steps 7, 8, 9 are left
    assert dr.n_steps == 9 and dr.t_last == 9.0 and dr.t.tolist() == [7.0, 8.0, 9.0]
    assert dr.position.tolist() == [4.5, 0.0] and not dr.covers(dr.t[0] - 0.5)
    with pytest.raises(ValueError, match="does not accumulate"):
        dr.covariance_at(9.0)


def test_bad_input_is_a_clear_error():
    steps = _steps([0.0, 0.1, 0.2])
    with pytest.raises(ValueError, match="strictly increasing"):
        DeadReckoning.from_steps([steps[0], steps[2], steps[1]])
    with pytest.raises(ValueError, match="strictly increasing"):
        DeadReckoning.from_steps([steps[0], steps[0]])
    with pytest.raises(ValueError, match="start time"):
        DeadReckoning.from_steps(steps, t0=steps[0].t)  # the start must come before the first step
    with pytest.raises(ValueError, match="finite"):
        DeadReckoning(float("nan"))
    with pytest.raises(ValueError, match="finite"):
        DeadReckoning.from_steps(steps, pos0=(0.0, float("inf")))
    dr = DeadReckoning.from_steps(steps)
    with pytest.raises(ValueError, match="finite"):
        dr.position_at([10.0, float("nan")])
    with pytest.raises(ValueError, match="finite"):
        dr.covariance_at(float("nan"))
    with pytest.raises(ValueError, match="non-finite step times"):
        DeadReckoning.from_lengths_headings([1.0, float("nan")], [0.5, 0.5], [0.0, 0.0])
    with pytest.raises(ValueError, match="non-finite lengths"):
        DeadReckoning.from_lengths_headings([1.0, 2.0], [0.5, float("nan")], [0.0, 0.0])
    with pytest.raises(ValueError, match="2 step times, 2 lengths and 1 headings"):
        DeadReckoning.from_lengths_headings([1.0, 2.0], [0.5, 0.5], [0.0])
    with pytest.raises(ValueError, match="strictly increasing"):
        DeadReckoning.from_lengths_headings([2.0, 1.0], [0.5, 0.5], [0.0, 0.0])


def test_kalman_filter_keeps_the_pdr_track_through_a_clock_that_goes_back():
    """LocalFusion's own PDR track (for GPS displacements, Kourogi eq 17) is a live DeadReckoning: a
    step whose time goes back starts the track over from where it was instead of failing."""
    from hybridloc.fusion.kalman import LocalFusion

    f = LocalFusion(init=(0.0, 0.0, 1.0))
    for s in _steps([0.0] * 4, length=0.5, t0=0.0, dt=1.0):  # t = 1 .. 4, 2 m East
        f.predict(s)
    np.testing.assert_array_equal(f._raw_at(2.5), [1.25, 0.0])
    assert f._raw_at(0.5) is None  # before the first step: not in the track
    f.predict(StepEvent(3.0, 0.5, math.pi / 2, 0.05, 0.05))  # the clock went back to t = 3
    assert f._raw.t.tolist() == [3.0] and f._raw.position.tolist() == [2.0, 0.5]

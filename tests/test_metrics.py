import math

import numpy as np
import pytest

from hybridloc.metrics import (
    absolute_trajectory_error,
    error_at_points,
    floor_hit_rate,
    percentiles,
    return_to_start_error,
    step_count_error,
    summarize_errors,
    umeyama,
)


def _rot2(a):
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def test_umeyama_recovers_known_transform_2d_and_3d():
    rng = np.random.default_rng(3)
    src = rng.normal(size=(50, 2)) * 10
    R = _rot2(0.7)
    dst = src @ R.T + [5.0, -2.0]
    R_est, t_est, s = umeyama(src, dst)
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, [5.0, -2.0], atol=1e-10)
    assert s == 1.0
    src3 = rng.normal(size=(40, 3))
    c, si = math.cos(0.3), math.sin(0.3)
    R3 = np.array([[c, 0, si], [0, 1, 0], [-si, 0, c]])
    _, _, s3 = umeyama(src3, 2.5 * src3 @ R3.T, with_scale=True)
    assert s3 == pytest.approx(2.5)


def test_umeyama_never_returns_a_reflection():
    src = np.array([[0, 0], [1, 0], [0, 1], [1, 1.0]])
    dst = src * [1, -1]  # a mirror image: the best proper rotation is not the mirror
    R, _, _ = umeyama(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_ate_is_zero_for_rigidly_moved_copy_and_known_for_offset():
    t = np.linspace(0, 2 * math.pi, 200, endpoint=False)  # centroid exactly at the centre
    gt = np.column_stack([np.cos(t), np.sin(t), 0.1 * t])
    est = gt[:, :2] @ _rot2(1.1).T + [10, 3]
    assert absolute_trajectory_error(est, gt, dims=2).rmse == pytest.approx(0.0, abs=1e-10)
    # In 3-D a pure translation (here a constant height offset) is removed by the rigid alignment.
    est3 = gt + [0, 0, 0.5]
    assert absolute_trajectory_error(est3, gt, dims=3).rmse == pytest.approx(0.0, abs=1e-10)
    # Noise that alignment cannot absorb: a radius error of 0.1 on a circle of radius 1.
    est_r = gt[:, :2] * 1.1
    assert absolute_trajectory_error(est_r, gt, dims=2).rmse == pytest.approx(0.1, rel=1e-6)


def test_return_to_start_ojeda_eqs_7_9():
    # A 16.25 m square (65 m, as in Ojeda's experiment) ending 0.3 m east and 0.4 m north of the start.
    sq = np.array([[0, 0], [16.25, 0], [16.25, 16.25], [0, 16.25], [0.3, 0.4]])
    r = return_to_start_error(sq)
    assert r.e_r == pytest.approx(0.5)
    D = 16.25 * 3 + math.hypot(16.25 - 0.4, 0.3)
    assert r.distance == pytest.approx(D)
    assert r.e_p == pytest.approx(100 * 0.5 / D)


def test_error_at_points_interpolates_in_time():
    t = np.array([0.0, 10.0])
    p = np.array([[0.0, 0.0], [10.0, 0.0]])
    e = error_at_points(t, p, np.array([5.0, 2.0, 20.0]), np.array([[5.0, 1.0], [2.0, 0.0], [0, 0]]))
    assert e[0] == pytest.approx(1.0) and e[1] == pytest.approx(0.0) and math.isnan(e[2])
    s = summarize_errors(e)
    assert s.n == 2 and s.mean == pytest.approx(0.5)


def test_percentiles_floor_and_steps():
    p = percentiles(np.arange(101), (50, 75, 95))
    assert p == {50: 50.0, 75: 75.0, 95: 95.0}
    assert floor_hit_rate(["F1", "F2", None, "F1"], ["F1", "F1", "F1", "F1"]) == 0.5
    assert step_count_error(101, 100) == pytest.approx(0.01)
    with pytest.raises(ValueError):
        step_count_error(3, 0)


def test_walkable_coverage_is_the_area_of_the_discs_inside():
    """A 10 m x 10 m walkable square: one label in the middle reaches pi r^2 of it (the buffered disc's
    area within 0.2 % of the circle's, 64 segments), a label repeated counts once, one on the edge half a
    disc, one far outside nothing; an empty area has no coverage, a radius <= 0 is an error."""
    import shapely

    from hybridloc.metrics import walkable_coverage

    sq = shapely.box(0.0, 0.0, 10.0, 10.0)
    r = 2.0
    disc = math.pi * r * r / 100.0
    assert walkable_coverage(sq, [[5.0, 5.0]], r) == pytest.approx(disc, rel=2e-3)
    assert walkable_coverage(sq, [[5.0, 5.0]] * 3, r) == pytest.approx(disc, rel=2e-3)
    assert walkable_coverage(sq, [[5.0, 0.0]], r) == pytest.approx(disc / 2, rel=2e-3)
    assert walkable_coverage(sq, [[50.0, 50.0], [np.nan, 1.0]], r) == 0.0
    assert walkable_coverage(sq, np.zeros((0, 2)), r) == 0.0
    assert walkable_coverage(sq, [[x, y] for x in range(11) for y in range(11)], 1.0) == 1.0
    assert math.isnan(walkable_coverage(shapely.MultiPolygon(), [[0.0, 0.0]], r))
    with pytest.raises(ValueError):
        walkable_coverage(sq, [[5.0, 5.0]], 0.0)

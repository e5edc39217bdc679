import numpy as np
import pytest

from hybridloc.geo import GeodeticOrigin, dominant_axis, ecef_to_geodetic, geodetic_to_ecef
from hybridloc.units import DEG


def test_ecef_round_trip():
    lat, lon, h = 30.29 * DEG, 120.07 * DEG, 15.0
    back = ecef_to_geodetic(geodetic_to_ecef(lat, lon, h))
    assert back[0] == pytest.approx(lat, abs=1e-11)
    assert back[1] == pytest.approx(lon, abs=1e-11)
    assert back[2] == pytest.approx(h, abs=1e-4)


def test_enu_axes_and_scale():
    o = GeodeticOrigin.from_degrees(45.0, 7.0, 200.0)
    # One arc-minute of latitude is about 1852 m (the nautical mile) and points North.
    e = o.geodetic_to_enu((45.0 + 1 / 60) * DEG, 7.0 * DEG, 200.0)
    assert abs(e[0]) < 1e-6
    assert e[1] == pytest.approx(1852.0, rel=3e-3)
    assert e[2] == pytest.approx(0.0, abs=0.5)  # Earth curvature drops ~0.27 m over 1.85 km
    # Longitude increases to the East.
    assert o.geodetic_to_enu(45.0 * DEG, 7.001 * DEG, 200.0)[0] > 0


def test_enu_round_trip_many_points():
    o = GeodeticOrigin.from_degrees(-33.9, 151.2, 30.0)
    rng = np.random.default_rng(0)
    p = rng.uniform(-500, 500, (100, 3))
    lat, lon, h = o.enu_to_geodetic(p)
    np.testing.assert_allclose(o.geodetic_to_enu(lat, lon, h), p, atol=1e-6)


def test_origin_rejects_radians_mistaken_for_degrees():
    with pytest.raises(ValueError):
        GeodeticOrigin.from_degrees(100.0, 0.0)


def test_dominant_axis_of_a_rotated_grid_and_none_without_one():
    """A grid of walls turned by 30 deg (and their perpendiculars, the same axis mod 90 deg) with a
    third as much wall length at random angles: the axis is 30 deg (to 0.5: the band mean of exact
    grid walls); walls at uniform random angles have no dominant grid."""
    rng = np.random.default_rng(3)
    walls = []
    for k in range(40):
        a = np.radians(30.0) + (np.pi / 2) * (k % 2)
        p0 = rng.uniform(-50, 50, 2)
        walls.append([p0, p0 + 10.0 * np.array([np.cos(a), np.sin(a)])])
    for _ in range(40):
        a = rng.uniform(0, np.pi)
        p0 = rng.uniform(-50, 50, 2)
        walls.append([p0, p0 + 3.3 * np.array([np.cos(a), np.sin(a)])])
    ax, share = dominant_axis(np.array(walls))
    assert np.degrees(ax) == pytest.approx(30.0, abs=0.5)
    assert 0.7 < share < 0.9
    random_walls = []
    for _ in range(400):
        a = rng.uniform(0, np.pi)
        p0 = rng.uniform(-50, 50, 2)
        random_walls.append([p0, p0 + 5.0 * np.array([np.cos(a), np.sin(a)])])
    assert dominant_axis(np.array(random_walls)) is None
    assert dominant_axis(np.zeros((0, 2, 2))) is None

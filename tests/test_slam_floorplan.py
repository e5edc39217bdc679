"""The floor plan as a field (distance outside the walkable area) and the anchoring search."""

import math

import numpy as np
import pytest
import shapely
from shapely.geometry import MultiPolygon, Polygon, box

from hybridloc.geo import wall_crossings
from hybridloc.slam.anchoring import anchor_points
from hybridloc.slam.floorplan import WalkableField
from hybridloc.types import Floor

H = 0.25  # raster resolution of the tests, m


def _floor(walkable, outline=None) -> Floor:
    walkable = walkable if isinstance(walkable, MultiPolygon) else MultiPolygon([walkable])
    walls = []
    for poly in walkable.geoms:
        for ring in [poly.exterior, *poly.interiors]:
            c = np.asarray(ring.coords)
            walls += list(np.stack([c[:-1], c[1:]], axis=1))
    return Floor("F1", 0, 0.0, outline or walkable, walkable, np.asarray(walls), ())


@pytest.fixture(scope="module")
def square():
    """A 10 m x 10 m room [0, 10]^2."""
    return WalkableField.from_floor(_floor(box(0.0, 0.0, 10.0, 10.0)), resolution=H)


def test_distance_in_a_square_room_is_the_euclidean_distance_to_it(square):
    """d = 0 inside; outside, the distance to the square (to the side, or to the corner beyond both
    sides), to within the raster's resolution (the boundary lies somewhere between two nodes)."""
    rng = np.random.default_rng(0)
    p = rng.uniform(-8.0, 18.0, size=(2000, 2))
    d, _ = square(p)
    dx = np.maximum(0.0, np.maximum(-p[:, 0], p[:, 0] - 10.0))
    dy = np.maximum(0.0, np.maximum(-p[:, 1], p[:, 1] - 10.0))
    truth = np.hypot(dx, dy)
    deep = truth == 0
    deep &= (p.min(1) > H) & (p.max(1) < 10.0 - H)  # a cell away from the walls: exactly 0
    assert np.all(d[deep] == 0.0)
    np.testing.assert_allclose(d, truth, atol=H)


def test_gradient_points_away_from_the_room_and_matches_finite_differences(square):
    # outside a side: the unit normal; beyond a corner: the unit vector from the corner
    _, g = square(np.array([[-3.1, 5.1], [13.1, 4.9], [5.05, -2.1], [-3.1, -4.1]]))
    np.testing.assert_allclose(g[:3], [[-1.0, 0.0], [1.0, 0.0], [0.0, -1.0]], atol=1e-9)
    corner = np.array([-3.1, -4.1]) / math.hypot(3.1, 4.1)
    np.testing.assert_allclose(g[3], corner, atol=0.05)  # the raster's Euclidean distance to node centres
    # finite differences of the bilinear field (the exact Jacobian of what is evaluated), away from
    # cell edges where the interpolant has kinks
    rng = np.random.default_rng(1)
    cells = rng.integers(-30, 70, size=(300, 2))
    p = (cells + rng.uniform(0.2, 0.8, size=(300, 2))) * H
    eps = 1e-6
    d, g = square(p)
    for k in range(2):
        e = np.zeros(2)
        e[k] = eps
        fd = (square(p + e)[0] - square(p - e)[0]) / (2 * eps)
        np.testing.assert_allclose(g[:, k], fd, atol=1e-6)


def test_beyond_the_raster_the_distance_grows_linearly(square):
    """The raster ends at the margin (10 m); farther out d(p) = d(edge) + |p - edge| with a unit pull."""
    p = np.array([[5.0, 40.0], [5.0, 60.0], [-70.0, 5.0]])
    d, g = square(p)
    np.testing.assert_allclose(d, [30.0, 50.0, 70.0], atol=H)
    np.testing.assert_allclose(g, [[0.0, 1.0], [0.0, 1.0], [-1.0, 0.0]], atol=1e-9)
    fd = (square(p + [0.0, 1e-3])[0] - square(p - [0.0, 1e-3])[0]) / 2e-3
    np.testing.assert_allclose(fd[:2], 1.0, atol=1e-6)


def test_contains_and_log_likelihood(square):
    p = np.array([[5.0, 5.0], [0.1, 9.9], [-0.1, 5.0], [12.0, 5.0], [30.0, 5.0]])
    assert square.contains(p).tolist() == [True, True, False, False, False]
    ll = square.log_likelihood(p, sigma=1.0, floor=-8.0)
    assert ll[0] == 0.0 and ll[1] >= -0.5 * H**2  # within a cell of the wall the raster blurs d by up to H
    assert ll[3] == pytest.approx(-0.5 * 2.0**2, abs=H * 2.0)  # -d^2/2, d = 2 m (d ll/dd = -d)
    assert ll[4] == -8.0  # floored (20 m out)
    assert square.log_likelihood(p[3:4], sigma=2.0)[0] == pytest.approx(-0.5, abs=H)


def test_crosses_wall_agrees_with_the_segment_test():
    """A room with an inner wall: moves through a wall cross it, moves along the corridor do not; the
    STRtree query gives what :func:`hybridloc.geo.wall_crossings` gives, segment by segment."""
    room = Polygon([(0, 0), (20, 0), (20, 10), (0, 10)], [[(8, 2), (12, 2), (12, 8), (8, 8)]])
    f = WalkableField.from_floor(_floor(room), resolution=H)
    p0 = np.array([[2.0, 5.0], [2.0, 1.0], [2.0, 5.0], [10.0, 5.0], [5.0, 5.0]])
    p1 = np.array([[15.0, 5.0], [18.0, 1.0], [2.0, 5.0], [10.0, 20.0], [5.0, 9.0]])
    assert f.crosses_wall(p0, p1).tolist() == [True, False, False, True, False]
    rng = np.random.default_rng(2)
    a, b = rng.uniform(-5, 25, size=(500, 2)), rng.uniform(-5, 25, size=(500, 2))
    np.testing.assert_array_equal(f.crosses_wall(a, b), wall_crossings(f.walls, a, b) > 0)


def _l_world():
    """An asymmetric plan of 2-m corridors: a west-east corridor along y = 5 (x 0..51), a north-south
    one along x = 50 (y 4..40) and a stub at x = 20 going north to y = 20, all with dead ends."""
    corridors = [box(0, 4, 51, 6), box(49, 4, 51, 40), box(19, 4, 21, 20)]
    return _floor(shapely.union_all(corridors).buffer(0))


def test_anchor_points_recovers_a_known_placement_of_an_asymmetric_point_set():
    """Points every 1 m along the corridors' centre lines, into the dead ends to 0.5 m from their walls
    (the true shape), rotated by 6 deg, scaled by 1/1.05 and shifted by an unknown offset: the search
    puts every point back in its own corridor and it is not ambiguous. Inside the walkable area the
    likelihood is flat, so the placement is determined only up to the corridors' play: 1 m across a
    2-m corridor, and the 0.5 m end gaps along it, over a 50-m shape; each point within 2 m."""
    f = WalkableField.from_floor(_l_world(), resolution=H)
    truth = np.vstack(
        [
            np.column_stack([np.arange(0.5, 50.0), np.full(50, 5.0)]),
            np.column_stack([np.full(35, 50.0), np.arange(5.0, 39.6)]),
            np.column_stack([np.full(14, 20.0), np.arange(6.0, 19.6)]),
        ]
    )
    th, s = math.radians(6.0), 1.05
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    comp = ((truth - 30.0) @ R) / s + np.array([-117.0, 245.0])  # truth = s R (comp - offset) + 30
    a = anchor_points(comp, f)
    err = np.hypot(*(a.apply(comp) - truth).T)
    assert not a.ambiguous, (a.score, a.runner_up)
    assert err.max() < 2.0, err.max()
    assert f.contains(a.apply(comp)).all()
    assert a.rotation == pytest.approx(th, abs=math.atan(2.0 / 49.5))  # a 2 m corridor over the 49.5 m leg
    assert a.scale == pytest.approx(s, abs=1.5 / 49.5)  # the leg's x 0.5..50 between walls at 0 and 51: 1.5 m of play over 49.5 m


def test_anchor_points_is_ambiguous_in_a_symmetric_corridor_world():
    """A grid of identical corridors: a straight 30-m walk fits every corridor equally well."""
    corridors = [box(0, y - 1.5, 100, y + 1.5) for y in (10, 30, 50, 70)] + [box(x - 1.5, 0, x + 1.5, 80) for x in (10, 50, 90)]
    f = WalkableField.from_floor(_floor(shapely.union_all(corridors)), resolution=H)
    walk = np.column_stack([np.arange(0.0, 30.0), np.zeros(30)]) + [500.0, -200.0]
    a = anchor_points(walk, f)
    assert a.ambiguous
    assert len(a.modes) >= 2 and a.score - a.runner_up < 1.0  # an equally good placement elsewhere
    placed = a.apply(walk)
    assert f.contains(placed).mean() > 0.9  # the best placement is in a corridor: it just is not the only one


def test_anchor_points_refuses_a_shape_that_fits_nowhere():
    """A 40 x 40 m square loop in a plan of narrow corridors with no such square: the best placement
    leaves most points off the walkable area, so it is not claimed."""
    f = WalkableField.from_floor(_l_world(), resolution=H)
    t = np.arange(0.0, 40.0)
    sq = np.vstack(
        [np.column_stack([t, 0 * t]), np.column_stack([40 + 0 * t, t]), np.column_stack([40 - t, 40 + 0 * t]), np.column_stack([0 * t, 40 - t])]
    )
    a = anchor_points(sq, f)
    assert a.ambiguous and a.mean_fit < -0.5


def test_anchor_points_remembers_a_search_and_answers_it_as_the_search_would(monkeypatch):
    """The search is a pure function of its arguments, so the field remembers it: asked again with the
    same points it answers what a fresh search gives (a new field has nothing remembered), a copy the
    caller may change, and any changed argument (a point, the weights, a setting) searches anew."""
    from hybridloc.slam import anchoring

    f = WalkableField.from_floor(_l_world(), resolution=H)
    walk = np.column_stack([np.arange(0.5, 40.0), np.full(40, 5.2)]) + [3.0, -7.0]
    a = anchor_points(walk, f)
    calls = []
    real = anchoring._search

    def counting(*args):
        calls.append(1)
        return real(*args)

    monkeypatch.setattr(anchoring, "_search", counting)  # counts every search below; restored after the test
    b = anchor_points(walk.copy(), f)
    assert calls == []  # remembered
    fresh = anchor_points(walk, WalkableField.from_floor(_l_world(), resolution=H))
    assert len(calls) == 1
    for x in (a, b):
        np.testing.assert_array_equal(x.T, fresh.T)
        np.testing.assert_array_equal(x.t, fresh.t)
        assert (x.score, x.runner_up, x.ambiguous, x.mean_fit) == (fresh.score, fresh.runner_up, fresh.ambiguous, fresh.mean_fit)
    b.t += 100.0  # the caller's copy: the remembered answer does not move
    np.testing.assert_array_equal(anchor_points(walk, f).t, a.t)
    moved = walk.copy()
    moved[3, 1] += 0.01
    anchor_points(moved, f)
    anchor_points(walk, f, weights=np.full(len(walk), 2.0))
    anchor_points(walk, f, min_log_ratio=5.0)
    assert len(calls) == 4
    # bounded: the least recently used search is dropped first
    assert len(f._anchor_memo) <= anchoring.MEMO_SIZE
    small = WalkableField.from_floor(_l_world(), resolution=H)
    monkeypatch.setattr(anchoring, "MEMO_SIZE", 2)
    anchor_points(walk, small)
    anchor_points(moved, small)
    anchor_points(walk, small)  # used again: now the most recent
    anchor_points(walk + 1.0, small)  # a third: `moved` goes
    assert len(small._anchor_memo) == 2
    calls.clear()
    anchor_points(walk, small)
    anchor_points(walk + 1.0, small)
    assert calls == []
    anchor_points(moved, small)
    assert len(calls) == 1
    # a pickled field (to a Dask worker) leaves its caches behind and searches alike
    import pickle

    g = pickle.loads(pickle.dumps(f))
    assert not hasattr(g, "_anchor_memo") and not hasattr(g, "_raster_cache")
    np.testing.assert_array_equal(anchor_points(walk, g).t, a.t)

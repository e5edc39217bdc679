import dataclasses
import math
import pickle

import numpy as np
import pytest
from shapely.geometry import Polygon

from hybridloc.types import (
    RSSI_MAX_DBM,
    RSSI_MIN_DBM,
    AbsoluteFix,
    ContainmentRegion,
    Fix,
    FixSource,
    ImuBlock,
    Pose,
    RfScan,
    StepEvent,
    Technology,
    Trajectory,
    Waypoints,
    rssi_in_range,
)
from hybridloc.units import bearing_deg_to_heading, heading_to_bearing_deg, wrap_angle


def test_wrap_angle_half_open_interval():
    assert wrap_angle(math.pi) == pytest.approx(math.pi)
    assert wrap_angle(-math.pi) == pytest.approx(math.pi)
    assert wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    w = wrap_angle(np.linspace(-20, 20, 101))
    assert np.all((w > -math.pi) & (w <= math.pi))


def test_heading_bearing_conventions():
    # East is heading 0 / bearing 90; North is heading pi/2 / bearing 0.
    assert heading_to_bearing_deg(0.0) == pytest.approx(90.0)
    assert heading_to_bearing_deg(math.pi / 2) == pytest.approx(0.0)
    assert bearing_deg_to_heading(180.0) == pytest.approx(-math.pi / 2)


def test_imu_block_validates_and_is_read_only():
    t = np.arange(10) * 0.02
    a = np.tile([0, 0, 9.81], (10, 1))
    blk = ImuBlock(t, a, np.zeros((10, 3)))
    assert blk.rate_hz == pytest.approx(50.0)
    with pytest.raises(ValueError):
        blk.accel_body[0, 0] = 1.0
    with pytest.raises(ValueError, match="strictly increasing"):
        ImuBlock(t[::-1], a, np.zeros((10, 3)))
    with pytest.raises(ValueError, match="rows"):
        ImuBlock(t, a[:5], np.zeros((10, 3)))
    assert len(blk.slice(0.05, 0.11)) == 3


def test_step_event_covariance_matches_monte_carlo():
    """Kourogi eqs 11-14: the tangent-line covariance of (L cos psi, L sin psi) against sampling."""
    s = StepEvent(t=1.0, length=0.7, heading=0.6, sigma_length=0.05, sigma_heading=0.05)
    rng = np.random.default_rng(1)
    L = 0.7 + 0.05 * rng.standard_normal(200_000)
    psi = 0.6 + 0.05 * rng.standard_normal(200_000)
    d = np.column_stack([L * np.cos(psi), L * np.sin(psi)])
    emp = np.cov(d.T)
    # The tangent-line approximation is exact up to O(sigma_psi^2) relative terms (~0.25 % here) plus
    # the sampling error of a covariance from 2e5 samples (~0.3 %): 3 % is a wide margin.
    np.testing.assert_allclose(s.displacement_covariance(), emp, rtol=0.03, atol=2e-6)


def test_step_event_rejects_nan_and_wraps():
    with pytest.raises(ValueError):
        StepEvent(0.0, float("nan"), 0.0, 0.1, 0.1)
    with pytest.raises(ValueError):
        StepEvent(0.0, -0.1, 0.0, 0.1, 0.1)
    assert StepEvent(0.0, 0.5, 7.0, 0.1, 0.1).heading == pytest.approx(7.0 - 2 * math.pi)


def test_rf_scan_range_and_immutability():
    s = RfScan(1.0, "wifi", {"aa": -60, "bb": -80.5})
    assert s.technology is Technology.WIFI and len(s) == 2
    with pytest.raises(TypeError):
        s.rssi_dbm["cc"] = -50  # type: ignore[index]
    with pytest.raises(ValueError, match="outside"):
        RfScan(1.0, "wifi", {"aa": 100})  # UJIIndoorLoc's "not detected" must never pass as dBm
    # to a worker process and back: the same scan, still read-only (rebuilt without re-checking)
    for scan in (s, RfScan(2.0, "ble", {"aa": -61.5}, {"aa": 2.4e9}, {"aa": 0.25}, "Pixel 7")):
        back = pickle.loads(pickle.dumps(scan))
        assert type(back) is RfScan and (back.t, back.technology, dict(back.rssi_dbm)) == (scan.t, scan.technology, dict(scan.rssi_dbm))
        assert (dict(back.frequency_hz), dict(back.age_s), back.device_model) == (dict(scan.frequency_hz), dict(scan.age_s), scan.device_model)
        with pytest.raises(TypeError):
            back.age_s["bb"] = 1.0  # type: ignore[index]


def test_rssi_range_is_one_check_for_floats_and_arrays():
    assert rssi_in_range(RSSI_MIN_DBM) and rssi_in_range(RSSI_MAX_DBM) and rssi_in_range(-61.5)
    for bad in (RSSI_MIN_DBM - 1e-9, 1e-9, 100.0, math.nan, math.inf, -math.inf):
        assert not rssi_in_range(bad), bad
    np.testing.assert_array_equal(rssi_in_range(np.array([-130.0, 0.5, np.nan, -40.0])), [True, False, False, True])


def test_fix_record_keeps_its_parts_consistent():
    f = AbsoluteFix(2.0, [1.0, 2.0], np.diag([4.0, 9.0]), "wifi", "F1", 0.9)
    region = ContainmentRegion("F1", Polygon([(0, 0), (4, 0), (4, 3), (0, 3)]), 0.95, 2.0)
    a = Fix(f, region, {"F1": 0.9, "F2": 0.1})
    assert a and a.t == 2.0 and a.floor_probs == {"F1": 0.9, "F2": 0.1} and a.reason == ""
    with pytest.raises(TypeError):
        a.floor_probs["F3"] = 0.0  # type: ignore[index]
    none = Fix(None, reason="no known transmitter in the scan", t=3.0)
    assert not none and none.t == 3.0
    with pytest.raises(ValueError):
        Fix(None, region)  # a region needs a fix
    with pytest.raises(ValueError):
        Fix(f, t=5.0)  # the answer's time is the fix's
    with pytest.raises(ValueError):
        Fix(f, reason="why")  # a reason is for "no fix"
    import pickle

    back = pickle.loads(pickle.dumps(a))
    assert back.floor_probs == a.floor_probs and back.region.area.equals(region.area)


def test_pose_covariance_is_optional_and_read_only():
    p = Pose(1.0, 2.0, 3.0, "F1")
    assert p.cov is None and p.pos_enu.tolist() == [2.0, 3.0]
    q = Pose(1.0, 2.0, 3.0, None, [[1.0, 0.0], [0.0, 2.0]])
    assert not q.cov.flags.writeable
    with pytest.raises(ValueError):
        Pose(1.0, 2.0, 3.0, None, np.eye(3))


def test_absolute_fix_checks_covariance():
    f = AbsoluteFix(2.0, [1.0, 2.0], np.diag([4.0, 9.0]), "wifi", "F1", 0.9)
    assert f.source is FixSource.WIFI
    np.testing.assert_allclose(f.sigma, [2.0, 3.0])
    with pytest.raises(ValueError, match="positive definite"):
        AbsoluteFix(2.0, [1.0, 2.0], np.diag([4.0, -1.0]), "wifi")
    with pytest.raises(ValueError, match="symmetric"):
        AbsoluteFix(2.0, [1.0, 2.0], [[1.0, 0.5], [0.0, 1.0]], "wifi")


def test_trusted_absolute_fix_is_the_checked_one_without_the_checks():
    """AbsoluteFix.trusted (the kNN locator's constructor) holds what the checked constructor holds:
    copies, frozen, the same fields; a caller's later change to its arrays does not reach the fix."""
    pos, cov = np.array([1.0, 2.0]), np.array([[4.0, 0.5], [0.5, 9.0]])
    t = AbsoluteFix.trusted(2.0, pos, cov, FixSource.WIFI, "F1", 0.9)
    c = AbsoluteFix(2.0, pos, cov, "wifi", "F1", 0.9)
    pos[0], cov[0, 0] = 99.0, 99.0
    for f in (t, c):
        assert (f.t, f.source, f.floor, f.floor_prob) == (2.0, FixSource.WIFI, "F1", 0.9)
        np.testing.assert_array_equal(f.pos_enu, [1.0, 2.0])
        np.testing.assert_array_equal(f.cov, [[4.0, 0.5], [0.5, 9.0]])
        assert not f.pos_enu.flags.writeable and not f.cov.flags.writeable
        with pytest.raises(dataclasses.FrozenInstanceError):
            f.t = 3.0  # type: ignore[misc]
        back = pickle.loads(pickle.dumps(f))  # from a worker process: the same fix, still frozen
        assert (back.t, back.source, back.floor, back.floor_prob) == (f.t, f.source, f.floor, f.floor_prob)
        assert back.pos_enu.tobytes() == f.pos_enu.tobytes() and back.cov.tobytes() == f.cov.tobytes()
        assert not back.pos_enu.flags.writeable and not back.cov.flags.writeable


def test_absolute_fix_symmetry_test_is_numpys_allclose():
    """The written-out symmetry test accepts and refuses exactly what np.allclose(c, c.T, atol) does,
    near its edge (asymmetries around atol + rtol |c|) and far from it, at several scales."""
    rng = np.random.default_rng(7)
    for _ in range(2000):
        scale = 10.0 ** rng.uniform(-6, 6)
        a = rng.uniform(0.5, 2.0) * scale
        b = rng.uniform(-0.4, 0.4) * scale
        tol = 1e-9 * max(1.0, a, abs(b)) + 1e-5 * abs(b)
        c = np.array([[a, b], [b + tol * rng.uniform(0.0, 2.0) * rng.choice([-1, 1]), 1.3 * a]])
        want = np.allclose(c, c.T, atol=1e-9 * max(1.0, float(np.abs(c).max())))
        try:
            AbsoluteFix(0.0, [0.0, 0.0], c, "wifi")
            got = True
        except ValueError as exc:
            assert "symmetric" in str(exc)
            got = False
        assert got == want


def test_containment_region():
    r = ContainmentRegion("F1", Polygon([(0, 0), (4, 0), (4, 3), (0, 3)]), 0.95)
    assert r.contains((1, 1)) and not r.contains((5, 1))
    assert r.area_m2 == pytest.approx(12.0)


def test_trajectory_and_waypoints():
    tr = Trajectory([0.0, 1.0, 2.0], [[0, 0], [3, 4], [3, 0]])
    assert tr.pos_enu.shape == (3, 3)
    assert tr.distance_travelled == pytest.approx(9.0)
    with pytest.raises(ValueError):
        Trajectory([0.0, 1.0], [[0, 0, 0]])
    with pytest.raises(ValueError, match="sorted"):
        Waypoints([2.0, 1.0], [[0, 0], [1, 1]])


def test_position_covariance_grows_by_step_covariance():
    s = StepEvent(t=1.0, length=1.0, heading=0.0, sigma_length=0.1, sigma_heading=0.1)
    C = s.propagate_position_covariance(np.eye(2) * 0.01)
    np.testing.assert_allclose(C, np.diag([0.01 + 0.01, 0.01 + math.tan(0.1) ** 2]))


def test_imu_block_tells_saturated_readings():
    """At the full scale when it is known; otherwise only a reading repeated exactly on 3 samples
    beyond the plausible range (a clipped plateau). A 2-sample repeat, or a plateau below the
    plausible range, is not saturation."""
    t = np.arange(12) * 0.01
    acc = np.tile([0.0, 0.0, 9.8], (12, 1))
    gyr = np.zeros((12, 3))
    gyr[3:7, 0] = 8.0  # a 4-sample plateau
    gyr[9:11, 1] = 8.0  # a 2-sample one
    sa, sg = ImuBlock(t, acc, gyr).saturated(50.0, 5.0)
    assert not sa.any() and sg.nonzero()[0].tolist() == [3, 4, 5, 6]
    assert not ImuBlock(t, acc, gyr).saturated(50.0, 10.0)[1].any()  # below the plausible range
    sa, sg = ImuBlock(t, acc, gyr, accel_range=9.8, gyro_range=8.0).saturated(50.0, 5.0)
    assert sa.all() and sg.nonzero()[0].tolist() == [3, 4, 5, 6, 9, 10]
    with pytest.raises(ValueError, match="full scale"):
        ImuBlock(t, acc, gyr, gyro_range=-1.0)


def test_imu_block_tells_a_clipping_ceiling_whose_readings_wander():
    """A sensor that filters after its converter clips at a level its readings wander about (never an
    exact repeat): the readings within 1 % of an axis's extreme, reached in 3 or more separate swings,
    are saturated. Peaks that spread as a live signal's do, a level reached in only 2 swings, and a
    level 6 swings share a third below the sensor's largest reading are not."""
    rng = np.random.default_rng(4)
    rate, n_swings = 200.0, 8
    t = np.arange(int(n_swings * rate)) / rate
    acc = np.tile([0.0, 0.0, 9.8], (len(t), 1))
    peaks = np.linspace(9.0, 12.0, n_swings)  # rad/s, one bell per second, each swing's own peak
    phase = (t % 1.0) - 0.5
    bell = np.exp(-0.5 * (phase / 0.05) ** 2)
    live = np.zeros((len(t), 3))
    live[:, 1] = peaks[(t // 1.0).astype(int)] * bell
    live[:, 2] = -4.0 * bell  # a quieter axis: 8 equal peaks, inside the plausible range
    assert not ImuBlock(t, acc, live).saturated(50.0, 5.0)[1].any()
    level = 8.85  # the gait-driven set's ~507 deg/s
    clipped = live.copy()
    over = clipped[:, 1] > level
    clipped[over, 1] = level * (1.0 + 0.002 * rng.standard_normal(int(over.sum())))  # wanders +-0.2 %
    sg = ImuBlock(t, acc, clipped).saturated(50.0, 5.0)[1]
    assert np.all(sg[over]) and sg.sum() <= over.sum() + 2 * n_swings  # the plateaus and their edges only
    two = live.copy()
    top = np.where(t < 2.0, 9.2, 6.0) * (1.0 + 0.002 * rng.standard_normal(len(t)))
    two[:, 1] = np.minimum(two[:, 1], top)  # 2 swings at a wandering top; 6 at another, a third below it
    assert not ImuBlock(t, acc, two).saturated(50.0, 5.0)[1].any()

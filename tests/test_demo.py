"""`hybridloc demo` end to end: server, surveys, map rebuild, phone clients, scores, PNG and GeoJSON."""

import json
import re
import subprocess
import sys

import numpy as np


def test_demo_runs_end_to_end(tmp_path):
    r = subprocess.run([sys.executable, "-m", "hybridloc.cli", "demo", "--out", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "overall at" in r.stdout and "PDR alone mean" in r.stdout and "fused mean" in r.stdout
    # the server's crowd SLAM: live against corrected, and the coverage the crowd added (two shares)
    assert "crowd SLAM on the server" in r.stdout and "corrected mean" in r.stdout, r.stdout[-3000:]
    cov = re.search(r"radio-map label ([0-9.]+) % \(map v\d+, survey.*-> ([0-9.]+) % \(map v(\d+)", r.stdout)
    assert cov, r.stdout[-3000:]
    assert 0.0 < float(cov[1]) <= 100.0 and 0.0 < float(cov[2]) <= 100.0
    assert (tmp_path / "demo.png").read_bytes()[:4] == b"\x89PNG"
    fc = json.loads((tmp_path / "demo.geojson").read_text())
    kinds = {f["properties"].get("kind") for f in fc["features"]}
    assert {"track", "true_waypoint", "floor"} <= kinds
    assert list((tmp_path / "poses").glob("*.csv"))
    n_corr = int(re.search(r"(\d+) of \d+ clients' walks corrected", r.stdout)[1])
    assert sum(f["properties"].get("kind") == "corrected_track" for f in fc["features"]) == n_corr


def test_true_motion_average_keeps_a_map_bias_and_averages_noise():
    """The radio map's floor in ``eval fusion``: fixes moved by the true motion and averaged. A bias
    every fix shares survives whole; noise that alternates in sign averages out; no fix, no answer."""
    from hybridloc.demo import _true_motion_average_errors

    wp_t, wp_xy = np.array([0.0, 10.0, 20.0]), np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])  # 1 m/s east
    t = np.arange(1.0, 21.0, 1.0)
    noise = np.where(np.arange(t.size) % 2 == 0, 2.0, -2.0)
    biased = [(ti, ti + 3.0, 4.0, "F1") for ti in t]  # every fix 5 m off, the same way
    noisy = [(ti, ti, n, "F1") for ti, n in zip(t, noise)]
    np.testing.assert_allclose(_true_motion_average_errors(biased, wp_t, wp_xy, 4.0), [5.0, 5.0])
    np.testing.assert_allclose(_true_motion_average_errors(noisy, wp_t, wp_xy, np.inf), [0.0, 0.0], atol=1e-12)
    assert np.isnan(_true_motion_average_errors([(30.0, 0.0, 0.0, "F1")], wp_t, wp_xy, 5.0)).all()


def test_true_motion_steps_retrace_the_waypoints():
    """The perfect PDR of ``eval fusion``: dead-reckoned from the first waypoint, its steps land on
    the waypoint path at every step time (an L-shaped walk, the turn between two steps); steps before
    the first or after the last waypoint do not move."""
    import math

    from hybridloc.demo import true_motion_steps
    from hybridloc.types import StepEvent

    wp_t, wp_xy = np.array([0.0, 10.0, 20.0]), np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0]])
    t = np.arange(-1.0, 22.0, 0.55)
    steps = [StepEvent(t=float(ti), length=0.7, heading=1.0, sigma_length=0.1, sigma_heading=0.2, degraded="no-mag") for ti in t]
    ideal = true_motion_steps(steps, wp_t, wp_xy)
    assert [s.t for s in ideal] == [s.t for s in steps]
    pos = np.cumsum([[s.length * math.cos(s.heading), s.length * math.sin(s.heading)] for s in ideal], axis=0)
    tc = np.clip(t, 0.0, 20.0)
    truth = np.column_stack([np.interp(tc, wp_t, wp_xy[:, 0]), np.interp(tc, wp_t, wp_xy[:, 1])])
    assert np.allclose(pos, truth - truth[0], atol=1e-9)
    assert ideal[0].length == 0.0 and ideal[-1].length == 0.0 and all(s.degraded == "" for s in ideal)
    moving = [s for s in ideal if s.length > 0]
    assert all(abs(s.heading) < 1e-9 or abs(s.heading - math.pi / 2) < 1e-9 or 0 < s.heading < math.pi / 2 for s in moving)
    assert true_motion_steps([], wp_t, wp_xy) == [] and true_motion_steps(steps, wp_t[:1], wp_xy[:1]) == []


def test_clients_on_a_surveyed_route_are_told_apart(tmp_path):
    """eval fusion splits its clients by whether a survey walked their route (the same marks, give or
    take 1 m, on the same floor), read from the traces' waypoints alone."""
    from hybridloc.demo import _routes_walked_by_surveys

    def trace(name, floor, marks):
        lines = [f"#\tSiteID:s\tFloorName:{floor}"] + [f"{1574559495000 + 5000 * i}\tTYPE_WAYPOINT\t{x}\t{y}" for i, (x, y) in enumerate(marks)]
        p = tmp_path / f"{name}.txt"
        p.write_text("\n".join(lines) + "\n", encoding="utf-8")
        return p

    route = [(0, 0), (5, 0), (10, 0), (10, 5)]
    survey = [trace("s1", "F1", route), trace("s2", "F2", [(0, 0), (0, 9)])]
    again = trace("c1", "F1", [(x + 0.2, y - 0.2) for x, y in route][::-1])  # the same route, walked back
    upstairs = trace("c2", "F2", route)  # the same marks on another floor
    aside = trace("c3", "F1", [(x, y + 4.0) for x, y in route])
    assert _routes_walked_by_surveys(survey + [again, upstairs, aside], survey) == {str(again)}


def test_floor_hits_score_each_mark_on_its_own_floor():
    """A walk up the stairs: the estimate held at each waypoint is scored against that mark's floor,
    not the trace's start floor."""
    from hybridloc.demo import _floor_hits
    from hybridloc.types import Waypoints

    wps = Waypoints(np.array([0.0, 10.0, 20.0, 30.0]), np.zeros((4, 2)), "F1", ("F1", "F1", "F2", "F2"))
    poses = [(5.0, 0, 0, "F1"), (15.0, 0, 0, "F1"), (25.0, 0, 0, "F2")]  # the switch to F2 seen 5 s late
    assert _floor_hits(poses, wps) == [True, False, True]
    assert _floor_hits([(5.0, 0, 0, "F1")], wps) == [True, False, False]

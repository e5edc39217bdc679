"""``hybridloc eval crowd`` (issue #21 point 6): the bundled 35-walk sample replayed as a crowd through a
real server (Zenoh on loopback, SQLite with its migrations), the causal scoring, the survey draw, the
learning curve's thirds and the command's refusals."""

from __future__ import annotations

import io
import json
import math
import sys
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest

from hybridloc.cli import main
from hybridloc.crowd_eval import crowd_report, live_errors, plan_crowd, run_crowd, thirds, track_errors
from hybridloc.samples import ILC_SITE1_F1
from hybridloc.types import CorrectedTrack
from hybridloc.wire.protocol import check_id

#: the keys the issue names for the JSON line
ISSUE_KEYS = ("live_mean_m", "live_mean_first_third_m", "live_mean_last_third_m", "corrected_mean_m", "coverage", "walks_quarantined", "seconds")


# ------------------------------------------------------------------------------------- scoring
def test_live_errors_hold_the_newest_row_and_leave_waypoints_before_the_first_fix_unscored():
    # rows (t, x, y, floor, ...): the first at t = 10 s (the client's first fix), then one per step
    poses = [(10.0, 0.0, 0.0, "F1"), (12.0, 3.0, 4.0, "F1"), (12.0, 6.0, 8.0, "F1"), (20.0, 10.0, 0.0, "F1")]
    wp_t = np.array([0.0, 9.99, 10.0, 11.0, 12.0, 15.0, 25.0])
    wp_xy = np.zeros((7, 2))
    e = live_errors(poses, wp_t, wp_xy)
    # before the first row: not scored; at and after it: the newest row at or before the waypoint
    # (at equal times the later row: two rows at 12 s, the second is what the phone showed)
    assert np.isnan(e[:2]).all()
    np.testing.assert_allclose(e[2:], [0.0, 0.0, 10.0, 10.0, 10.0])
    assert np.isnan(live_errors([], wp_t, wp_xy)).all() and live_errors(poses, [], np.zeros((0, 2))).size == 0


def test_live_errors_take_rows_in_time_order_whatever_their_order_in_the_list():
    poses = [(5.0, 1.0, 0.0, "F1"), (1.0, 0.0, 2.0, "F1")]
    np.testing.assert_allclose(live_errors(poses, [2.0, 6.0], np.zeros((2, 2))), [2.0, 1.0])


def _track(t, xy, anchored="map"):
    n = len(t)
    return CorrectedTrack(1, np.asarray(t, float), np.asarray(xy, float), np.tile(np.eye(2), (n, 1, 1)), ("F1",) * n, ("step",) * n, anchored)


def test_track_errors_interpolate_the_corrected_track_and_leave_times_outside_it_unscored():
    a = _track([0.0, 10.0], [[0.0, 0.0], [10.0, 0.0]])
    b = _track([20.0, 30.0], [[0.0, 5.0], [0.0, 15.0]])  # the same device's second stored walk
    e = track_errors([a, b], [5.0, 15.0, 25.0, 40.0], [[5.0, 1.0], [0.0, 0.0], [0.0, 10.0], [0.0, 0.0]])
    np.testing.assert_allclose(e[[0, 2]], [1.0, 0.0])
    assert np.isnan(e[[1, 3]]).all()
    assert np.isnan(track_errors([], [1.0], [[0.0, 0.0]])).all()


# ----------------------------------------------------------------------------------- the draw
def test_the_survey_draw_is_seeded_and_the_clients_are_the_other_walks_in_time_order():
    from hybridloc.io.msft import find_ilc_traces

    n = len(find_ilc_traces(ILC_SITE1_F1))
    plan = plan_crowd(ILC_SITE1_F1, 0.2, seed=0)
    assert len(plan.surveys) == round(0.2 * n) and len(plan.surveys) + len(plan.clients) == n
    assert {w.path for w in plan.surveys}.isdisjoint(w.path for w in plan.clients)
    starts = [w.t_start for w in plan.clients]
    assert starts == sorted(starts) and all(math.isfinite(t) for t in starts)
    devices = [w.device for w in plan.surveys + plan.clients]
    assert len(set(devices)) == n and all(check_id(d) == d for d in devices)
    assert plan.floors == ("F1",) and check_id(plan.site, "site") == plan.site
    again = plan_crowd(ILC_SITE1_F1, 0.2, seed=0)
    other = plan_crowd(ILC_SITE1_F1, 0.2, seed=1)
    assert [w.path for w in again.surveys] == [w.path for w in plan.surveys]
    assert {w.path for w in other.surveys} != {w.path for w in plan.surveys}


@pytest.mark.parametrize("n", [0, 1, 2, 3, 7, 28])
def test_thirds_partition_the_positions_in_order(n):
    parts = thirds(n)
    assert len(parts) == 3
    assert np.concatenate(parts).tolist() == list(range(n))
    sizes = [len(p) for p in parts]
    assert max(sizes) - min(sizes) <= 1


# ---------------------------------------------------------------------------- refusals
@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--survey-fraction", "0"], "--survey-fraction"),
        (["--survey-fraction", "1"], "--survey-fraction"),
        (["--survey-fraction", "1.5"], "--survey-fraction"),
        (["--survey-fraction", "-0.1"], "--survey-fraction"),
        (["--survey-fraction", "0.001"], "at least one survey"),
        (["--floors", "F9"], "F9"),
        (["--floors", ","], "--floors"),
        (["--concurrency", "0"], "--concurrency"),
    ],
)
def test_bad_options_are_one_line_and_exit_2(extra, needle, tmp_path, capsys):
    rc = main(["eval", "crowd", str(ILC_SITE1_F1), "--out", str(tmp_path), *extra])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1 and needle in err[0], err


@pytest.mark.parametrize("kind", ["missing", "file", "empty folder"])
def test_a_site_folder_that_is_not_one_is_one_line_and_exit_2(kind, tmp_path, capsys):
    site = tmp_path / "site"
    if kind == "file":
        site.write_text("not a site\n")
    elif kind == "empty folder":
        site.mkdir()
    rc = main(["eval", "crowd", str(site), "--out", str(tmp_path / "out")])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(err) == 1 and str(site) in err[0], err


# --------------------------------------------------------------------- the crowd, end to end
@pytest.fixture(scope="module")
def crowd(tmp_path_factory):
    """The bundled sample as a crowd: 7 surveys (F = 0.2), 28 phone clients, 3 at a time, unpaced."""
    out = tmp_path_factory.mktemp("crowd")
    return run_crowd(ILC_SITE1_F1, 0.2, seed=0, out=out, concurrency=3, progress=False)


def test_every_other_walk_is_a_client_scored_in_time_order(crowd):
    C = crowd.clients
    assert len(C) == len(crowd.plan.clients) and not crowd.skipped
    assert [c.order for c in C] == list(range(len(C)))
    assert [c.walk for c in C] == list(crowd.plan.clients)
    # each client is one device, one walk on the server
    assert all(len(c.walk_ids) == 1 for c in C) and len({c.walk_ids[0] for c in C}) == len(C)
    assert all(c.unacked == 0 for c in C)
    # each client starts with the map in service then: the survey map first; newer versions only from the
    # server's batch re-solves (its SLAM worker re-solves every 25 new walks by default), never older
    versions = [c.map_version for c in C]
    assert crowd.map_version_survey == 1 and versions[0] == 1 and versions == sorted(versions)
    assert crowd.map_version_final >= versions[-1]
    # every client heard the server, and its live scoring covers each of its waypoints
    for c in C:
        assert c.fixes_received > 0 and c.live.shape == (c.waypoints,)
        scored = np.isfinite(c.live)
        assert np.all(c.live[scored] >= 0)
        # unscored waypoints are exactly a leading run: those before its first fix
        k = c.unscored
        assert not scored[:k].any() and scored[k:].all()


def test_clients_jsonl_holds_each_client_and_waypoint_as_scored(crowd):
    rows = [json.loads(ln) for ln in (crowd.out / "clients.jsonl").read_text().splitlines()]
    C = crowd.clients
    assert [r["order"] for r in rows] == [c.order for c in C] and [r["device"] for r in rows] == [c.walk.device for c in C]
    cuts = thirds(len(C))
    assert [r["third"] for r in rows] == ["first"] * len(cuts[0]) + ["middle"] * len(cuts[1]) + ["last"] * len(cuts[2])
    for r, c in zip(rows, C):
        assert r["walk_ids"] == list(c.walk_ids) and r["map_version"] == c.map_version and len(r["waypoints"]) == c.waypoints
        live = np.array([np.nan if w["live_m"] is None else w["live_m"] for w in r["waypoints"]])
        np.testing.assert_array_equal(np.isnan(live), np.isnan(c.live))
        np.testing.assert_allclose(live[np.isfinite(live)], c.live[np.isfinite(c.live)], atol=1e-3)  # written to the mm
        for key, mine in (
            ("corrected_m", c.corrected),
            ("incremental_m", c.incremental),
            ("survey_only_m", c.survey_only),
            ("replayed_m", c.replayed),
        ):
            got = np.array([np.nan if w[key] is None else w[key] for w in r["waypoints"]])
            want = np.full(c.waypoints, np.nan) if mine is None else np.asarray(mine, float)
            np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
            np.testing.assert_allclose(got[np.isfinite(got)], want[np.isfinite(want)], atol=1e-3)
        for w in r["waypoints"]:
            if w["live_m"] is not None:  # the error is the distance of the live position from the truth
                assert math.isclose(math.hypot(w["live_x"] - w["x"], w["live_y"] - w["y"]), w["live_m"], abs_tol=3e-3)
            else:
                assert w["live_x"] is None and w["live_y"] is None


def test_the_survey_only_baseline_replays_every_client_with_the_survey_map_and_with_the_map_served(crowd):
    C = crowd.clients
    assert crowd.baseline and all(c.survey_only is not None and c.replayed is not None for c in C)
    for c in C:
        for e in (c.survey_only, c.replayed):
            assert e.shape == (c.waypoints,)
            scored = np.isfinite(e)
            # scored from the first fix on: unscored waypoints are a leading run, as in the live scoring
            k = int((~scored).sum())
            assert not scored[:k].any() and scored[k:].all() and np.all(e[scored] >= 0)
        if c.map_version == crowd.map_version_survey:
            # served the survey map: the two replays are one computation
            np.testing.assert_array_equal(c.survey_only, c.replayed)
    # the figures printed are those of the arrays (per third, each on its own scored waypoints)
    buf = io.StringIO()
    head = crowd_report(crowd, out=buf)
    assert "survey-only baseline" in buf.getvalue() and "the same replay with the maps the server served" in buf.getvalue()
    cuts = thirds(len(C))
    sv = [np.nanmean(np.concatenate([C[i].survey_only for i in part])) for part in cuts]
    assert math.isclose(head["survey_only_mean_first_third_m"], sv[0], rel_tol=1e-9)
    assert math.isclose(head["survey_only_mean_last_third_m"], sv[2], rel_tol=1e-9)
    assert math.isclose(head["survey_only_learning_gain"], 1 - sv[2] / sv[0], rel_tol=1e-9)
    a = np.concatenate([c.survey_only for c in C])
    b = np.concatenate([c.replayed for c in C])
    both = np.isfinite(a) & np.isfinite(b)
    assert math.isclose(head["crowd_map_gain"], 1 - b[both].mean() / a[both].mean(), rel_tol=1e-9, abs_tol=1e-12)


def test_probe_learning_replays_the_run_as_eval_crowd_does(crowd):
    """scripts/probe_learning.py's ``served`` and ``survey`` variants are the report's two replays."""
    import subprocess

    script = Path(__file__).resolve().parents[1] / "scripts" / "probe_learning.py"
    argv = [sys.executable, str(script), str(crowd.out), str(ILC_SITE1_F1), "--survey-fraction", "0.2", "--variants", "served,survey"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    fig = json.loads(done.stdout.strip().splitlines()[-1])
    head = crowd_report(crowd, out=io.StringIO())
    assert math.isclose(fig["survey"]["first_m"], head["survey_only_mean_first_third_m"], abs_tol=1e-3)
    assert math.isclose(fig["survey"]["last_m"], head["survey_only_mean_last_third_m"], abs_tol=1e-3)
    assert math.isclose(fig["served"]["first_m"], head["replayed_mean_first_third_m"], abs_tol=1e-3)
    assert math.isclose(fig["served"]["last_m"], head["replayed_mean_last_third_m"], abs_tol=1e-3)


def test_the_thirds_follow_each_other(crowd):
    C = crowd.clients
    first, middle, last = (C[int(p[0]) : int(p[-1]) + 1] for p in thirds(len(C)))
    # a third starts when the previous one has finished (wall clock of the replays)
    assert max(c.wall[1] for c in first) <= min(c.wall[0] for c in middle)
    assert max(c.wall[1] for c in middle) <= min(c.wall[0] for c in last)
    assert [c.walk.t_start for c in C] == sorted(c.walk.t_start for c in C)


def test_the_report_ends_with_the_json_line_of_the_issue(crowd):
    buf = io.StringIO()
    head = crowd_report(crowd, out=buf)
    text = buf.getvalue()
    for phrase in ("survey walks", "clients", "unscored", "learning curve", "first  third", "last   third", "goals:", "time: surveys"):
        assert phrase in text, phrase
    from hybridloc.cli._common import print_headline

    with redirect_stdout(io.StringIO()) as line:
        print_headline(head)
    fig = json.loads(line.getvalue().strip().splitlines()[-1])
    assert set(ISSUE_KEYS) <= set(fig)
    for k in ("live_mean_m", "live_median_m", "live_mean_first_third_m", "live_mean_middle_third_m", "live_mean_last_third_m", "seconds"):
        assert isinstance(fig[k], float) and math.isfinite(fig[k]) and fig[k] >= 0, k
    assert fig["clients"] == len(crowd.clients) and fig["survey_walks"] == len(crowd.plan.surveys)
    assert fig["unscored_waypoints"] == sum(c.unscored for c in crowd.clients)
    assert fig["waypoints"] == sum(c.waypoints for c in crowd.clients)
    if not crowd.slam_on:  # the server runs no crowd SLAM: nothing corrected, null in the JSON
        assert fig["corrected_mean_m"] is None and fig["coverage"] is None and fig["walks_quarantined"] is None
    else:
        assert fig["corrected_mean_m"] is None or math.isfinite(fig["corrected_mean_m"])
        assert fig["coverage"] is None or 0.0 <= fig["coverage"] <= 1.0
        assert isinstance(fig["walks_quarantined"], int)
        # the batch re-solves after the crowd: at least one, repeated only while the coverage grows
        from hybridloc.crowd_eval import FINAL_BATCH_MIN_GAIN, FINAL_BATCHES

        covs = crowd.final_coverages
        assert 1 <= fig["final_batches"] == len(covs) <= FINAL_BATCHES
        assert all(b - a >= FINAL_BATCH_MIN_GAIN for a, b in zip(covs[:-2], covs[1:-1]))  # every repeat was earned
        assert fig["coverage_first_batch"] is None or math.isclose(fig["coverage_first_batch"], covs[0], rel_tol=1e-4)  # printed to 6 digits


def test_the_command_prints_its_figures_and_ends_with_one_json_line(tmp_path, capsys):
    # the options reach the run; --no-slam: a server without crowd SLAM (the fixture's run has it), so
    # nothing is corrected, the corrected figures are null, and the survey-only baseline still prints
    argv = ["eval", "crowd", str(ILC_SITE1_F1), "--survey-fraction", "0.6", "--seed", "3", "--floors", "F1", "--no-slam"]
    rc = main([*argv, "--out", str(tmp_path), "--concurrency", "4"])
    out = capsys.readouterr().out
    assert rc == 0
    fig = json.loads(out.strip().splitlines()[-1])
    assert set(ISSUE_KEYS) <= set(fig)
    assert fig["survey_fraction"] == 0.6 and fig["seed"] == 3 and fig["survey_walks"] == 21 and fig["clients"] == 14
    assert math.isfinite(fig["live_mean_m"])
    assert "crowd SLAM off" in out and "corrected: undefined" in out
    assert fig["corrected_mean_m"] is None and fig["correction_gain"] is None and fig["coverage"] is None
    # every client was served the survey map: the replay with it is the survey-only baseline
    assert fig["map_versions"] == 1 and fig["crowd_map_gain"] == 0.0
    assert math.isfinite(fig["survey_only_mean_first_third_m"]) and "survey-only baseline" in out
    assert (tmp_path / "server.db").is_file()


def test_the_grown_map_run_counts_the_walks_it_served(tmp_path, capsys):
    """--grow-map: the server serves each added crowd walk's labels on top of its map version; the
    report says how many walks it grew the map by (crowd walks only: never more than the clients),
    and the JSON line says the run grew it."""
    argv = ["eval", "crowd", str(ILC_SITE1_F1), "--survey-fraction", "0.6", "--floors", "F1", "--grow-map"]
    rc = main([*argv, "--out", str(tmp_path), "--concurrency", "4"])
    out = capsys.readouterr().out
    assert rc == 0
    fig = json.loads(out.strip().splitlines()[-1])
    assert fig["grow_map"] is True and "the served map grown at every added walk (--grow-map)" in out
    assert isinstance(fig["walks_grown"], int) and 1 <= fig["walks_grown"] <= fig["clients"] == 14
    assert f"{fig['walks_grown']} walks' labels served on top of the map versions" in out
    assert set(ISSUE_KEYS) <= set(fig) and math.isfinite(fig["live_mean_m"])


def test_double_site_copies_walks_later_under_other_ids(tmp_path):
    """scripts/double_site.py (the 500-walk load test): every chosen walk is copied under another id with
    every time shifted by the same amount; lines the reader skips are copied as they are; ``--copies N``
    spreads the N copies over the floors by their shares of the walks; without it every walk is copied."""
    import subprocess

    site = tmp_path / "site"
    day_ms = 86400 * 1000
    for fl, ids in (("F1", ("5dd9a", "5dd9b", "5dd9c", "5dd9d", "5dd9e", "5dd9f")), ("F2", ("5dda1", "5dda2"))):
        (site / fl / "path_data_files").mkdir(parents=True)
        (site / fl / "floor_info.json").write_text("{}")
        for i, wid in enumerate(ids):
            t0 = 1574560000000 + 1000 * i
            rows = [
                f"#\tstartTime:{t0}",
                f"{t0 + 10}\tTYPE_WAYPOINT\t1.0\t2.0",
                f"{t0 + 20}\tTYPE_WIFI\tap\t00:11\t-60\t2412\t{t0 + 15}",
                "not a row",
                f"#\tendTime:{t0 + 30}",
            ]
            (site / fl / "path_data_files" / f"{wid}.txt").write_text("\n".join(rows))
    script = Path(__file__).resolve().parents[1] / "scripts" / "double_site.py"
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, str(script), str(site), str(out), "--copies", "4", "--days", "1"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert "12 walks (8 and copies of 4 of them" in done.stdout
    made = sorted(p.name for p in out.glob("*/path_data_files/*.txt"))
    assert len(made) == 12 and (out / "F1" / "floor_info.json").is_file()
    copies = [p for p in out.glob("*/path_data_files/f*.txt")]
    # F1 holds 6 of the 8 walks, F2 2: 3 and 1 of the 4 copies
    assert sorted(p.parent.parent.name for p in copies) == ["F1", "F1", "F1", "F2"]
    for cp in copies:
        src = (site / cp.parent.parent.name / "path_data_files" / ("5" + cp.name[1:])).read_text().split("\n")
        got = cp.read_text().split("\n")
        assert got[3] == src[3] == "not a row"
        assert int(got[0].split(":")[1]) - int(src[0].split(":")[1]) == day_ms
        assert int(got[1].split("\t")[0]) - int(src[1].split("\t")[0]) == day_ms
        assert int(got[2].split("\t")[-1]) - int(src[2].split("\t")[-1]) == day_ms  # the WiFi row's last-seen time
        assert got[2].split("\t")[1:-1] == src[2].split("\t")[1:-1]
    every = subprocess.run([sys.executable, str(script), str(site), str(tmp_path / "all")], capture_output=True, text=True, timeout=120)
    assert every.returncode == 0 and "16 walks (8 and copies of 8 of them" in every.stdout
    assert len(list((tmp_path / "all").glob("*/path_data_files/f*.txt"))) == 8
    bad = subprocess.run([sys.executable, str(script), str(site), str(tmp_path / "o2"), "--copies", "9"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--copies must be in [0, 8]" in bad.stderr

import re
import subprocess
import sys

import pytest


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hybridloc.cli", *args], capture_output=True, text=True, timeout=300)


def test_help_and_version():
    r = _run("--version")
    assert r.returncode == 0 and "hybridloc" in r.stdout
    assert _run().returncode == 2  # a command is required


def test_cli_length_models_are_the_librarys():
    """The CLI lists the step length models without importing numpy at start-up; the list must be
    the library's own."""
    from hybridloc.cli import LENGTH_MODELS
    from hybridloc.pdr.steplength import MODELS

    assert set(LENGTH_MODELS) == set(MODELS)


def test_inspect_reports_bad_file_with_exit_2(tmp_path):
    """Bad input is the user's to mend: exit status 2 (issue #19; it was 1), one line, no traceback."""
    p = tmp_path / "junk.bin"
    p.write_bytes(b"\x00junk")
    r = _run("data", "inspect", str(p))
    assert r.returncode == 2 and "unknown format" in r.stderr and "Traceback" not in r.stderr


@pytest.mark.shared_data
def test_inspect_real_files(ilc_site1, pyshoe_dir, shared_data):
    trace = sorted((ilc_site1 / "F1" / "path_data_files").glob("*.txt.gz"))[0]
    mat = sorted(pyshoe_dir.glob("*.mat"))[0]
    r = _run("data", "inspect", str(trace), str(mat), str(shared_data / "ujiindoorloc" / "trainingData.csv.gz"))
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert "format      msft" in out and "waypoints" in out and "wifi" in out and "50.0 Hz" in out
    assert "format      pyshoe" in out and "200.1 Hz" in out and "authors" in out
    assert "19937 fingerprints" in out


def test_eval_pdr_phone_on_bundled_sample_prints_figures():
    from hybridloc.samples import ILC_SITE1_F1

    r = _run("eval", "pdr-phone", str(ILC_SITE1_F1))
    assert r.returncode == 0, r.stderr
    for key in ("constant", "weinberg", "frequency", "segment length error median", "heading-change error median", "error at waypoints"):
        assert key in r.stdout
    # the last line is one JSON object of the headline figures, named with their units, for scripts and CI
    import json

    head = json.loads(r.stdout.splitlines()[-1])
    assert {"segment_length_median_pct", "turn_error_median_deg", "waypoint_error_mean_m"} <= set(head)
    assert 0 <= head["segment_length_median_pct"] < 100 and head["waypoint_error_mean_m"] > 0
    assert f"segment length error median {head['segment_length_median_pct']:.1f}%" in r.stdout  # the same figure as the table's


def test_pdr_phone_bad_input_is_a_clear_error(tmp_path):
    p = tmp_path / "g.csv"
    p.write_text("t,ax,ay,az,gx,gy,gz\n" + "\n".join(f"{i * 0.02:.2f},0,0,1.0,0,0,0" for i in range(100)))
    r = _run("pdr", "phone", str(p), "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "looks like g" in r.stderr
    r = _run("pdr", "phone", str(p), "--out", str(tmp_path / "o"), "--accel-unit", "g")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "o" / "g" / "steps.csv").is_file()


def test_sensorconnect_walk_through_data_inspect_and_pdr_foot(shared_data, tmp_path):
    files = sorted((shared_data / "gait-driven-own").glob("SensorConnectData_*.csv.gz"))
    if not files:
        pytest.skip("gait-driven-own is absent from ../shared/data")
    r = _run("data", "inspect", str(files[0]))
    assert r.returncode == 0, r.stderr
    assert "scaledAccel (g -> m/s^2)" in r.stdout and "footprints" in r.stdout
    r = _run("pdr", "foot", str(files[0]), "--out", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    assert "strides" in r.stdout and list((tmp_path / "out").iterdir())
    # the clipped samples' count and share (the 3DM-GX5-25 clips at a ceiling its readings wander about)
    assert re.search(r"saturated samples \d+ \(\d+\.\d %\)", r.stdout)
    assert "--preset gait-driven" in r.stdout  # the default settings on this sensor: the hint names the held-out ones


def test_pdr_foot_preset_applies_the_held_out_settings_and_options_override_it(shared_data, tmp_path):
    """SensorConnectData_34, 24 strides walked: with the default (adaptive) detector the sensor's
    mid-swing dips are counted as steps (a third more); --preset gait-driven counts them as walked,
    and an explicit --detector overrides the preset's."""
    p = shared_data / "gait-driven-own" / "SensorConnectData_34.csv.gz"
    if not p.is_file():
        pytest.skip(f"{p} is absent")

    def strides(*opts):
        r = _run("pdr", "foot", str(p), "--out", str(tmp_path / "o"), *opts)
        assert r.returncode == 0, r.stderr
        return int(re.search(r"(\d+) strides", r.stdout).group(1)), r.stdout

    from hybridloc.ins.foot import FOOT_PRESETS

    usage = _run("pdr", "foot", "--help").stdout
    assert set(re.search(r"--preset \{([^}]*)\}", usage).group(1).split(",")) == set(FOOT_PRESETS)  # the option lists every preset

    n, out = strides("--preset", "gait-driven")
    assert n == 24 and "--preset gait-driven applies" not in out
    assert strides()[0] > 24
    assert strides("--preset", "gait-driven", "--detector", "adaptive")[0] > 24


@pytest.mark.shared_data
def test_eval_pdr_phone_holds_each_floor_out(ilc_site1):
    """On site1's three floors, every floor is scored with the yaw pull chosen on the other two and
    lengths fitted there, beside the plain baseline held out alike; the held-out figures are in the
    JSON line, and a walker's heading-change error stays inside what a phone PDR can have (the marks
    alone turn by a median 6 deg on straight walks: under 3 deg held out would be a leak)."""
    import json

    r = _run("eval", "pdr-phone", str(ilc_site1), "--every", "15", "--k-mags", "0.03,0.1")
    assert r.returncode == 0, r.stderr
    assert "held out by floor (3 floors)" in r.stdout
    for f in ("F1", "F2", "F3"):
        assert f"  {f}: heading-change median" in r.stdout
    head = json.loads(r.stdout.splitlines()[-1])
    assert 3.0 < head["turn_error_held_out_by_floor_deg"] < 30.0 and 0 < head["segment_length_held_out_by_floor_median_pct"] < 50
    assert {"turn_error_plain_held_out_deg", "segment_length_plain_held_out_median_pct", "floors_length_below_plain"} <= set(head)

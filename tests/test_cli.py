import subprocess
import sys

import pytest


def _run(*args):
    return subprocess.run([sys.executable, "-m", "hybridloc.cli", *args], capture_output=True, text=True, timeout=120)


def test_help_and_version():
    r = _run("--version")
    assert r.returncode == 0 and "hybridloc" in r.stdout
    assert _run().returncode == 2  # a command is required


def test_inspect_reports_bad_file_with_exit_1(tmp_path):
    p = tmp_path / "junk.bin"
    p.write_bytes(b"\x00junk")
    r = _run("data", "inspect", str(p))
    assert r.returncode == 1 and "unknown format" in r.stderr


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

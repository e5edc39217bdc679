"""`hybridloc demo` end to end: server, surveys, map rebuild, phone clients, scores, PNG and GeoJSON."""

import json
import subprocess
import sys


def test_demo_runs_end_to_end(tmp_path):
    r = subprocess.run([sys.executable, "-m", "hybridloc.cli", "demo", "--out", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "overall at" in r.stdout and "PDR alone mean" in r.stdout and "fused mean" in r.stdout
    assert (tmp_path / "demo.png").read_bytes()[:4] == b"\x89PNG"
    fc = json.loads((tmp_path / "demo.geojson").read_text())
    kinds = {f["properties"].get("kind") for f in fc["features"]}
    assert {"track", "true_waypoint", "floor"} <= kinds
    assert list((tmp_path / "poses").glob("*.csv"))

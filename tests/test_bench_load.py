"""The load benchmark runs end to end (not its speed: that is the benchmark's to print): a few phone
clients through a real server, every batch stored once, every scan answered."""

import json

from benchmarks import bench_load


def test_bench_load_small_run_loses_and_doubles_nothing(capsys):
    r = bench_load.main(["--clients", "4", "--minutes", "0.2", "--sessions", "2", "--ceiling-batches", "2"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert json.loads(last) == r
    assert r["lost"] == 0 and r["doubled"] == 0
    assert r["steps_sent"] == 4 * 12 * len(bench_load.STEP_T) and r["scans_sent"] == 4 * 6
    assert r["fixes"] + r["no_fix"] == r["scans_sent"]  # one answer per stored scan, none twice
    assert r["realtime_factor"] > 0
    # the large-batch ceiling: 2 devices x 2 batches of 1,000 steps + 100 scans, all stored
    assert r["ceiling_lossless"] and r["ceiling_steps_per_s"] > 0 and r["raw_rows_per_s"] > 0
    assert r["ceiling_ratio"] == round(r["ceiling_steps_per_s"] / r["raw_rows_per_s"], 4)

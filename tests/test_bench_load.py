"""The load benchmark runs end to end (not its speed: that is the benchmark's to print): a few phone
clients through a real server, every batch stored once, every scan answered."""

import json

import pytest

from benchmarks import bench_load


def test_bench_load_small_run_loses_and_doubles_nothing(capsys, tmp_path, monkeypatch):
    """Through the server's ingest workers (serve --ingest-workers 2): their scans answered from the real
    map; the run's temporary folders (databases of hundreds of MB on long runs) removed at the end."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    r = bench_load.main(["--clients", "4", "--minutes", "0.2", "--sessions", "2", "--ceiling-batches", "2", "--ingest-workers", "2"])
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert json.loads(last) == r
    assert r["lost"] == 0 and r["doubled"] == 0
    assert r["steps_sent"] == 4 * 12 * len(bench_load.STEP_T) and r["scans_sent"] == 4 * 6
    assert r["fixes"] + r["no_fix"] == r["scans_sent"]  # one answer per stored scan, none twice
    assert r["realtime_factor"] > 0 and r["ingest_workers"] == 2 and r["ceiling_ingest_workers"] == 2
    assert r["workers_peak_rss_mb"] > 0  # the workers' memory is counted beside the server's
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(("hybridloc-load-", "hybridloc-ceiling-", "hybridloc-pg-"))]
    # the large-batch ceiling: 2 devices x 2 batches of 1,000 steps + 100 scans, all stored
    assert r["ceiling_lossless"] and r["ceiling_steps_per_s"] > 0 and r["raw_rows_per_s"] > 0
    assert r["ceiling_ratio"] == round(r["ceiling_steps_per_s"] / r["raw_rows_per_s"], 4)
    assert r["raw_rows_per_s"] == pytest.approx(0.5 * (r["raw_rows_per_s_before"] + r["raw_rows_per_s_after"]), abs=0.2)
    assert r["ceiling_step_form"] == "columns" and r["batch_encode_rows_ms"] is not None


def test_ceiling_only_with_step_rows(capsys):
    """``--ceiling-only`` runs no live load; ``--ceiling-steps rows`` sends today's rows, every batch stored."""
    r = bench_load.main(["--ceiling-only", "--ceiling-batches", "1", "--ceiling-steps", "rows", "--ingest-workers", "0"])
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == r
    assert r["ceiling_only"] and "steps_sent" not in r
    assert r["ceiling_lossless"] and r["ceiling_step_form"] == "rows" and r["batch_encode_rows_ms"] is None
    assert r["ceiling_ingest_workers"] == 0
    with pytest.raises(SystemExit):
        bench_load.main(["--ceiling-only", "--no-ceiling"])


@pytest.mark.slow  # about a minute; `make bench` runs bench_load with these faults at 300 clients
def test_bench_load_faults_lose_and_double_nothing_and_recover(capsys):
    """The long form of tests/test_server_faults.py in small: the server SIGKILLed and restarted, then a
    third of the sessions closed for a second; every batch stored once, each fault caught up (every batch
    sent before its end acknowledged) within the clients' reconnection (Zenoh's own, ~1.5 s) plus the
    resend timeout's cap (bench_load's MAX_RTO_S) and the server's start."""
    argv = ["--clients", "6", "--minutes", "0.3", "--sessions", "3", "--no-ceiling"]
    r = bench_load.main([*argv, "--fault", "server-kill@4", "--fault", "clients-drop@10:1", "--drop-fraction", "0.34"])
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == r
    assert r["lost"] == 0 and r["doubled"] == 0
    kinds = [(f["kind"], f["at_s"], f["devices"]) for f in r["faults"]]
    assert kinds == [("server-kill", 4, 6), ("clients-drop", 10, 2)]
    for f in r["faults"]:
        assert f["caught_up_s"] is not None and f["first_ack_s"] <= f["caught_up_s"] < 1.5 + bench_load.MAX_RTO_S + 10.0
    assert r["fault_caught_up_max_s"] == max(f["caught_up_s"] for f in r["faults"])


@pytest.mark.parametrize("bad", ["disk-full@3", "server-kill", "server-kill@x", "server-kill@-1", "clients-drop@3:700"])
def test_a_malformed_fault_is_refused(bad):
    with pytest.raises(ValueError, match="fault"):
        bench_load.parse_fault(bad)
    with pytest.raises(SystemExit):
        bench_load.main(["--clients", "2", "--minutes", "0.1", "--fault", bad])


def test_a_fault_is_parsed_with_its_default_downtime():
    assert bench_load.parse_fault("server-kill@30") == ("server-kill", 30, 0.0)
    assert bench_load.parse_fault("clients-drop@30") == ("clients-drop", 30, 10.0)
    assert bench_load.parse_fault("db-outage@5:2.5") == ("db-outage", 5, 2.5)

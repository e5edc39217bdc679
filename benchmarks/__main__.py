"""Run every benchmark: ``python -m benchmarks`` (``make bench``)."""

from pathlib import Path

from . import (
    bench_anchoring,
    bench_foot_ins,
    bench_foot_loops,
    bench_load,
    bench_loop_signal,
    bench_phone_pdr,
    bench_radiomap,
    bench_rebuild,
    bench_server,
    bench_sim,
    bench_slam,
    bench_slam_worker,
)

if __name__ == "__main__":
    bench_phone_pdr.main([])
    bench_foot_ins.main([])
    bench_foot_loops.main([])
    bench_radiomap.main([])
    bench_sim.main([])
    bench_server.main(["--postgres"] if Path("/usr/lib/postgresql").is_dir() else [])
    bench_slam.main([])
    bench_loop_signal.main([])
    bench_anchoring.main([])
    bench_slam_worker.main([])
    bench_rebuild.main([])
    # 300 phones (held in real time without faults) through a server SIGKILL, a fifth of the sessions
    # dropped for 10 s and, on PostgreSQL, the database paused for 10 s
    faults = ["--fault", "server-kill@30", "--fault", "clients-drop@60:10"]
    bench_load.main(["--clients", "300", "--minutes", "2", "--no-ceiling", *faults])
    if Path("/usr/lib/postgresql").is_dir():
        bench_load.main(["--clients", "300", "--minutes", "2", "--no-ceiling", "--db", "postgres", *faults, "--fault", "db-outage@90:10"])

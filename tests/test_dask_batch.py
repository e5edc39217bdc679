"""``slam rebuild`` and ``map rebuild`` as Dask distributed tasks (issue #23 point 6): the stored results
equal the serial path's, digest for digest, on a local cluster of worker processes and through the
command line on a real ``dask scheduler`` + ``dask worker`` on loopback.

The data: 9 real walks of the bundled sample on three floors (F2, F3 copies of F1's plan; every third
walk keeps its survey marks) and one more walk made of two unmarked sample walks, the second one floor
up (a walker taking the stairs): F1 and F2 are then one connected group (one chain of tasks), F3 another.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import dask
import psutil
import pytest
from distributed import Client

from hybridloc.errors import BadInput
from hybridloc.server.dask_batch import batch_client, floor_groups, stored_digest
from hybridloc.server.rebuild import rebuild
from hybridloc.server.slam_batch import run_batch
from hybridloc.server.store import Store
from hybridloc.wire.zconfig import free_port

from .helpers import interrupt_group, kill_group
from .slam_helpers import SITE, store_three_floors_with_stairs

CLI = [sys.executable, "-m", "hybridloc.cli"]
DASK = str(Path(sys.executable).with_name("dask"))
FLOORS = ("F1", "F2", "F3")


@pytest.fixture(scope="module")
def filled(tmp_path_factory) -> Path:
    """The database before any rebuild (copied by each test)."""
    db = tmp_path_factory.mktemp("dask") / "pristine.db"
    st = Store(str(db))
    try:
        dev = store_three_floors_with_stairs(st)
        assert [w.floors for w in (st.read_walk(x.walk_id) for x in st.walks(SITE, device=dev))] == [("F1", "F2")]
    finally:
        st.close()
    return db


def _copy(db: Path, tmp_path: Path, name: str) -> str:
    out = tmp_path / f"{name}.db"
    shutil.copy(db, out)
    return str(out)


def _digests(db: str) -> dict:
    st = Store(db, migrate=False)
    try:
        return stored_digest(st, SITE)
    finally:
        st.close()


def _cli(*argv: str, timeout: float = 240) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *argv], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def serial(filled, tmp_path_factory) -> dict:
    """Digests of the serial path (what ``--serial`` runs, here in this process): after ``slam rebuild``,
    then after ``map rebuild``."""
    db = _copy(filled, tmp_path_factory.mktemp("serial"), "serial")
    st = Store(db, migrate=False)
    try:
        assert run_batch(st, SITE).map_version == 1
        slam = stored_digest(st, SITE)
        assert rebuild(st, SITE, db + ".rebuild")[0] == 2
        return {"slam": slam, "survey": stored_digest(st, SITE)}
    finally:
        st.close()


def test_rebuilds_on_a_local_cluster_store_what_the_serial_path_stores(filled, serial, tmp_path):
    db = _copy(filled, tmp_path, "local")
    st = Store(db)
    walk_floors = [st.read_walk(w).floors for w in st.slam.solvable_walks(SITE)]
    assert floor_groups(walk_floors, FLOORS) == [["F1", "F2"], ["F3"]]
    children_before = {p.pid for p in psutil.Process().children(recursive=True)}
    stages: list[tuple[str, str]] = []
    try:
        with batch_client(workers=2) as client:
            assert len(client.nthreads()) == 2
            sm = run_batch(st, SITE, progress=lambda stage, floor, done, total: stages.append((stage, floor)), client=client)
            slam = stored_digest(st, SITE)
            v, n_labelled, relabelled = rebuild(st, SITE, tmp_path / "cache", client=client)
            survey = stored_digest(st, SITE)
        # the walk that took the stairs was solved in its group (its stored track: the last floor's points,
        # as on the serial path)
        (stairs,) = [w.walk_id for w in st.walks(SITE) if w.device.startswith("stairs")]
        assert "F2" in st.slam.tracks(SITE)[stairs].floor
    finally:
        st.close()
    assert sm.floors == list(FLOORS) and sm.map_version == 1 and sm.walks.get("corrected", 0) > 0
    # the solver's stages came back from the workers, for every floor
    assert {f for s, f in stages if s == "solve"} == set(FLOORS)
    assert [s for s, _ in stages].count("floors") == 1 + len(FLOORS)
    assert (v, relabelled) == (2, 10) and n_labelled > 0
    assert slam == serial["slam"], "slam rebuild on Dask stored other tracks, loops or map than the serial path"
    assert survey == serial["survey"], "map rebuild on Dask stored another map than the serial path"

    # the cluster is shut down: no worker process left behind (multiprocessing's resource tracker, started
    # with the first spawned process, lives as long as this interpreter: not a worker)
    def left() -> list[str]:
        out = []
        for p in psutil.Process().children(recursive=True):
            if p.pid not in children_before:
                with contextlib.suppress(psutil.Error):
                    cmd = " ".join(p.cmdline())
                    if "resource_tracker" not in cmd:
                        out.append(cmd)
        return out

    deadline = time.monotonic() + 10
    while left() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not left(), f"worker processes left running: {left()}"


def _start(argv: list[str]) -> subprocess.Popen:
    return subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def test_rebuild_commands_on_a_real_scheduler(filled, serial, tmp_path):
    db = _copy(filled, tmp_path, "remote")
    # a scheduler and a worker process of the Dask command line on loopback (started first: they come up
    # while the bad options are tried)
    address = f"tcp://127.0.0.1:{free_port()}"
    scheduler = _start([DASK, "scheduler", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1], "--no-dashboard"])
    worker = None
    try:
        # --preload: the workers import hybridloc's task module as they start, not at their first task
        worker = _start(
            [
                DASK,
                "worker",
                address,
                "--host",
                "127.0.0.1",
                "--nworkers",
                "1",
                "--nthreads",
                "1",
                "--no-dashboard",
                "--preload",
                "hybridloc.server.dask_batch",
            ]
        )
        # bad options: one line, exit 2, before any cluster
        for argv, what in ((["--workers", "0"], "at least 1"), (["--serial", "--workers", "2"], "--workers sizes the local")):
            r = _cli("slam", "rebuild", "--db", db, *argv)
            assert r.returncode == 2 and what in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert _cli("map", "rebuild", "--db", db, "--site", SITE, "--serial", "--scheduler", address).returncode == 2  # exclusive
        # no scheduler there: a BadInput (the command's one line and exit 2), after Dask's connect timeout
        with dask.config.set({"distributed.comm.timeouts.connect": "1s"}), pytest.raises(BadInput, match="cannot reach the Dask scheduler"):
            with batch_client(f"tcp://127.0.0.1:{free_port()}"):
                pass

        with Client(address, timeout=30) as c:
            c.wait_for_workers(1, timeout=60)
        r = _cli("slam", "rebuild", "--db", db, "--scheduler", address)
        assert r.returncode == 0, r.stderr
        out = json.loads(r.stdout.splitlines()[-1])
        assert out["executor"] == {"kind": "dask-scheduler", "workers": 1}
        assert f"tasks on the Dask scheduler at {address}" in r.stderr
        assert _digests(db) == serial["slam"]
        r = _cli("map", "rebuild", "--db", db, "--site", SITE, "--scheduler", address)
        assert r.returncode == 0, r.stderr
        assert _digests(db) == serial["survey"]
    finally:
        # the workers first (with their scheduler gone they would wait out its reconnection timeouts)
        for p in (worker, scheduler):
            if p is not None:
                p.terminate()
                try:
                    p.wait(20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


def test_ctrl_c_and_an_empty_site_close_the_local_cluster_without_tracebacks(filled, tmp_path):
    """Ctrl-C signals the whole process group: the cluster's worker processes leave it to the command,
    which closes them in order (exit 130, no traceback, no process left behind); a command with
    nothing to do (a site with no survey) closes the cluster without its workers' heartbeat errors."""
    db = _copy(filled, tmp_path, "ctrl_c")
    out = subprocess.run([*CLI, "map", "rebuild", "--db", db, "--site", "nowhere"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 1 and "no survey" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr and "ERROR" not in out.stderr, out.stderr
    proc = subprocess.Popen(
        [*CLI, "slam", "rebuild", "--db", db], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    try:
        lines = []
        while not any(" solve " in ln or " loops " in ln for ln in lines):  # the cluster's tasks are running
            ln = proc.stdout.readline()
            assert ln, "".join(lines)
            lines.append(ln)
        rest = interrupt_group(proc)
    finally:
        kill_group(proc)
    text = "".join(lines) + rest
    assert proc.returncode == 130, text
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text
    time.sleep(1.0)
    # still running (a zombie has ended: it waits for a parent to reap it, init in a container may not)
    left = [p for p in psutil.process_iter(["pid", "status"]) if _in_group(p, proc.pid) and p.info["status"] != psutil.STATUS_ZOMBIE]
    assert not left, left


def _in_group(p, pgid: int) -> bool:
    import os

    try:
        return os.getpgid(p.pid) == pgid
    except (ProcessLookupError, PermissionError):
        return False

"""A batch re-solve with the site's CrowdSlam kept in memory (the server's SLAM child) and its connected
groups of floors solved side by side in forked copies of the process (``run_batch(processes=2)``): it
stores what the serial path stores, digest for digest, and leaves the kept CrowdSlam in the state the
serial path leaves it in; a copy that crashes, or that changes a floor of another group, is discarded and
its floors are solved in the process itself, with the same results.

The data: as tests/test_dask_batch.py (9 real walks of the bundled sample on three floors and one walk
taking the stairs from F1 to F2), after a first batch run, so the second one starts from stored tracks:
F1 and F2 are one group (solved in the process), F3 another (solved in the fork).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hybridloc.server import slam_batch
from hybridloc.server.dask_batch import stored_digest
from hybridloc.server.slam_batch import floor_groups, load_radio_map, load_site, run_batch
from hybridloc.server.store import Store
from hybridloc.slam.online import CrowdSlam

from .slam_helpers import SITE, store_three_floors_with_stairs

FLOORS = ("F1", "F2", "F3")
CLI = [sys.executable, "-m", "hybridloc.cli"]

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="forked floor groups need os.fork")


@pytest.fixture(scope="module")
def solved_once(tmp_path_factory) -> Path:
    """The database after a first (serial) batch run (copied by each test)."""
    db = tmp_path_factory.mktemp("fork") / "once.db"
    st = Store(str(db))
    try:
        store_three_floors_with_stairs(st)
        assert run_batch(st, SITE).map_version == 1
    finally:
        st.close()
    return db


def _state(slam: CrowdSlam) -> str:
    """A digest of the kept CrowdSlam's state: each floor's held solutions, frame ids and orders, its
    loop audit and front end; the per-walk dictionaries in their order; the next frame id."""
    h = hashlib.sha256()
    for name in sorted(slam._floors):
        fl = slam._floors[name]
        h.update(f"{name}|{list(fl.held)}|{list(fl.scans)}|{fl.serial}|{len(fl.loops)}|{fl.fit_pieces}|{sorted(fl._rows)}|{len(fl._col)}".encode())
        for k, held in fl.held.items():
            h.update(f"{k}|{held.status}|{held.frame}".encode())
            for a in (held.pos, held.cov, held.nuisance):
                h.update(b"-" if a is None else np.ascontiguousarray(a).tobytes())
        h.update(repr([(lp.walk_a, lp.t_a, lp.walk_b, lp.t_b, lp.weight, lp.accepted) for lp in fl.loops]).encode())
    for name, d in slam._walk_dicts().items():
        h.update(f"{name}|{list(d)}".encode())
    for wid, tr in slam.tracks.items():
        h.update(f"{wid}|{None if tr is None else (tr.anchored, tr.scale, tr.heading_bias)}".encode())
        if tr is not None:
            h.update(np.ascontiguousarray(tr.pos_enu).tobytes())
    h.update(f"{slam.quarantined}|{slam.floor_moves}|{slam._next_frame}".encode())
    return h.hexdigest()


def _batch(src: Path, tmp_path: Path, name: str, processes: int, stages: list | None = None) -> tuple[dict, str]:
    """A second batch run, as the server's SLAM child makes it (its CrowdSlam kept), on a copy of ``src``:
    (the stored digests, the kept CrowdSlam's state digest)."""
    db = tmp_path / f"{name}.db"
    shutil.copy(src, db)
    st = Store(str(db), migrate=False)
    try:
        slam = load_site(st, SITE)
        _, rmap = load_radio_map(st, SITE)
        slam.set_vote_map(rmap)
        progress = (lambda stage, floor, done, total: stages.append((stage, floor))) if stages is not None else None
        sm = run_batch(st, SITE, progress=progress, slam=slam, processes=processes)
        assert sm.floors == list(FLOORS) and sm.map_version == 2
        return stored_digest(st, SITE), _state(slam)
    finally:
        st.close()


@pytest.fixture(scope="module")
def serial(solved_once, tmp_path_factory) -> tuple[dict, str]:
    return _batch(solved_once, tmp_path_factory.mktemp("serial"), "serial", 1)


def test_forked_groups_store_and_keep_what_the_serial_path_does(solved_once, serial, tmp_path):
    st = Store(str(solved_once), migrate=False)
    try:
        slam = load_site(st, SITE)
    finally:
        st.close()
    assert floor_groups(slam.held_walk_floors().values(), FLOORS) == [["F1", "F2"], ["F3"]]
    stages: list[tuple[str, str]] = []
    stored, state = _batch(solved_once, tmp_path, "forked", 2, stages)
    assert stored == serial[0], "the forked groups stored other tracks, loops or map than the serial path"
    assert state == serial[1], "the kept CrowdSlam differs from the serial path's after the forked groups"
    # the fork's solver stages came back through its pipe, and every floor was counted written
    assert {f for s, f in stages if s == "solve"} == set(FLOORS)
    assert [f for s, f in stages if s == "floors"].count("F3") == 2


def test_a_forked_group_that_crashes_is_solved_here(solved_once, serial, tmp_path, monkeypatch, caplog):
    here = os.getpid()
    solve = slam_batch.solve_floor

    def crashing(slam, floor, fold_walks, say):
        if os.getpid() != here:
            os._exit(3)  # the forked copy dies mid-run (a segfault, the OOM killer)
        return solve(slam, floor, fold_walks, say)

    monkeypatch.setattr(slam_batch, "solve_floor", crashing)
    stored, state = _batch(solved_once, tmp_path, "crash", 2)
    assert stored == serial[0] and state == serial[1]
    assert "died (exit code 3)" in caplog.text


def test_a_forked_group_that_touches_another_groups_floor_is_solved_here(solved_once, serial, tmp_path, monkeypatch, caplog):
    here = os.getpid()
    changed = CrowdSlam.outside_changed

    def outside(self, mark):
        # as if a walk the fork's batch could not fit had been re-added onto F1 by its fingerprints
        return ["F1"] if os.getpid() != here else changed(self, mark)

    monkeypatch.setattr(CrowdSlam, "outside_changed", outside)
    stored, state = _batch(solved_once, tmp_path, "conflict", 2)
    assert stored == serial[0] and state == serial[1]
    assert "floors outside its own changed (F1)" in caplog.text


def test_slam_rebuild_serial_with_processes_stores_what_one_process_stores(solved_once, tmp_path):
    one = tmp_path / "one.db"
    shutil.copy(solved_once, one)
    st = Store(str(one), migrate=False)
    try:
        run_batch(st, SITE)  # slam rebuild --serial: the CrowdSlam read from the database, one process
        want = stored_digest(st, SITE)
    finally:
        st.close()
    two = tmp_path / "two.db"
    shutil.copy(solved_once, two)
    r = subprocess.run([*CLI, "slam", "rebuild", "--db", str(two), "--serial", "--processes", "2"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1])["executor"] == {"kind": "serial", "workers": 1, "processes": 2}
    st = Store(str(two), migrate=False)
    try:
        assert stored_digest(st, SITE) == want
    finally:
        st.close()
    for argv, what in ((["--processes", "2"], "it needs --serial"), (["--serial", "--processes", "0"], "at least 1")):
        bad = subprocess.run([*CLI, "slam", "rebuild", "--db", str(two), *argv], capture_output=True, text=True, timeout=60)
        assert bad.returncode == 2 and what in bad.stderr, bad.stderr


def test_walks_the_forked_batch_drops_and_adds_again_end_as_in_the_serial_path(solved_once, tmp_path, monkeypatch, caplog):
    # the joint solve of F3 "cannot fit" its first walks: they are dropped and added again on their own
    # (CrowdSlam.rebuild_floor), which moves them to the end of the site's per-walk dictionaries
    verdicts = CrowdSlam._batch_verdicts

    def some_bad(self, fsl, sol, use):
        out = verdicts(self, fsl, sol, use)
        if fsl.floor == "F3" and not sol.em_moves:
            out.setdefault(min(k[0] for k in use), ("the test's verdict", None))
        return out

    monkeypatch.setattr(CrowdSlam, "_batch_verdicts", some_bad)
    caplog.set_level(logging.INFO, logger="hybridloc.slam.online")
    serial = _batch(solved_once, tmp_path, "serial-readd", 1)
    assert 'the batch gave "the test\'s verdict"; added on its own' in caplog.text  # the path is taken
    caplog.clear()
    forked = _batch(solved_once, tmp_path, "forked-readd", 2)
    assert "the forked solve is not used" not in caplog.text  # the fork's delta was adopted
    assert forked == serial


def test_a_forked_group_that_hangs_is_killed_and_solved_here(solved_once, serial, tmp_path, monkeypatch, caplog):
    here = os.getpid()
    solve = slam_batch.solve_floor

    def hanging(slam, floor, fold_walks, say):
        while os.getpid() != here:
            time.sleep(1.0)  # the forked copy never answers
        return solve(slam, floor, fold_walks, say)

    monkeypatch.setattr(slam_batch, "solve_floor", hanging)
    monkeypatch.setattr(slam_batch, "FORK_SILENCE_S", 3.0)
    stored, state = _batch(solved_once, tmp_path, "hang", 2)
    assert stored == serial[0] and state == serial[1]
    assert "said nothing for 3 s (killed)" in caplog.text

"""``slam rebuild`` and ``map rebuild`` serial vs on Dask, and what they cost as data grows (issue #23
point 6).

A seeded simulated site (:mod:`hybridloc.sim`: a generated building's ground floor, its plan copied as
``--floors`` floors; one walker per walk for ``--minutes``, phone-like steps with a per-walk scale error
and heading bias, WiFi scans from the radio model; walk i on floor i mod F; every fourth walk keeps
survey marks every 15 s, the others name their floor through a fix, as the server does). Each walk stays
on its floor, as the Indoor Location Competition recordings do, so the floors are independent groups and
can be solved in parallel (a walk crossing floors joins their groups: docs/slam.md).

For N, 2N and 4N walks: the database once, then per mode a copy of it and the two commands as the user
runs them (subprocesses): ``hybridloc slam rebuild`` then ``hybridloc map rebuild --site S``, either
``--serial``, on a local Dask cluster of ``--workers`` worker processes (default 2), or ``--serial`` with
``slam rebuild --processes W`` (its floor groups in forked copies of the command's process, no Dask). Measured: wall time
of each command (start-up and the cluster's included), the batch run's own time (``slam rebuild``'s JSON
``seconds``: from the claim to the new map), and the peak memory of the command's process tree (its RSS
plus its worker processes', sampled every 0.1 s) and of the command's own process. The stored results of
both modes are compared (digests of the map, tracks, walk states and loop audit: identical is required).
The growth exponent is the slope of log(time) over log(walks) from N to 4N (1: linear).

    python -m benchmarks.bench_rebuild [--walks N] [--floors F] [--minutes M] [--seed S] [--workers W]
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from benchmarks import headline

SITE = "sim-rebuild"
CLI = [sys.executable, "-m", "hybridloc.cli"]


# ------------------------------------------------------------------------------------------ the site
def simulated_site(seed: int, n_walks: int, floors: int, minutes: float):
    """(plan, walks): the simulated site (module docstring); walks are hybridloc.types.Walk."""
    import dataclasses

    from hybridloc.sim.building import generate_world
    from hybridloc.sim.radio import make_radio_model, simulate_radio
    from hybridloc.sim.walker import simulate_walk
    from hybridloc.types import FloorPlan, StepEvent, SurveyMark, Walk, WalkEnd

    rng = np.random.default_rng(seed)
    world = generate_world(rng, floors=1, seed=seed)
    model = make_radio_model(world, rng)
    base = world.plan.floors[0]
    plan = FloorPlan(SITE, tuple(dataclasses.replace(base, name=f"F{k + 1}", level=k) for k in range(floors)), (), world.plan.origin)
    walks = []
    for i in range(n_walks):
        sw = simulate_walk(world, rng, minutes, walker=i, t0=1.7e9 + 1000.0 * i)
        radio = simulate_radio(model, sw, rng)
        scale = float(rng.choice([0.85, 1.15]))  # the phone's step model is 15 % off, its heading 8 deg
        bias = float(rng.choice([-1.0, 1.0])) * math.radians(8.0)
        steps = [
            StepEvent(
                s.t,
                s.length * scale * float(rng.normal(1.0, 0.05)),
                s.heading + bias + float(rng.normal(0.0, math.radians(2.0))),
                0.05,
                math.radians(10.0),
                sigma_heading_change=math.radians(2.0),
            )
            for s in sw.steps
            if s.dz == 0.0
        ]
        fl = f"F{i % floors + 1}"
        marks: tuple = ()
        if i % 4 == 0:
            ts = np.arange(sw.t0 + 5.0, sw.t1, 15.0)
            pos, _ = sw.position_at(ts)
            marks = tuple(SurveyMark(float(t), float(p[0]), float(p[1]), fl) for t, p in zip(ts, pos))
        walks.append(Walk(SITE, f"w{i:03d}", None, sw.t0, sw.t1, "SIM PHONE", (fl,), tuple(steps), tuple(radio.wifi), marks, WalkEnd.MARKER))
    return plan, walks


def store_site(db: str, plan, walks) -> None:
    """Each walk as one device's ended walk (batches of at most 500 records, the last with the end-of-walk
    marker); an unmarked walk names its floor through a fix at its first scan."""
    from hybridloc.server.store import Store
    from hybridloc.types import AbsoluteFix
    from hybridloc.wire.messages import Batch

    st = Store(db)
    try:
        st.save_floor_plan(SITE, plan)
        for i, w in enumerate(walks):
            dev = f"dev{i:03d}"
            recs = sorted([("s", r) for r in w.steps] + [("c", r) for r in w.scans] + [("m", r) for r in w.marks], key=lambda x: x[1].t)
            chunks = [recs[k : k + 500] for k in range(0, len(recs), 500)] or [[]]
            st.persist(
                [
                    Batch(SITE, dev, n, w.device_model, [r for k, r in ch if k == "s"], [r for k, r in ch if k == "c"], [r for k, r in ch if k == "m"],
                          end_of_walk=n == len(chunks))
                    for n, ch in enumerate(chunks, 1)
                ]
            )  # fmt: skip
            if not w.marks and w.scans:
                st.add_fixes([(dev, AbsoluteFix(w.scans[0].t, np.zeros(2), np.eye(2), "wifi", w.floors[0]))])
    finally:
        st.close()


# ------------------------------------------------------------------------------------------ one command
class _PeakRss:
    """Peak RSS of a process and of its tree (itself + every descendant, summed), sampled every ``every_s``."""

    def __init__(self, pid: int, every_s: float = 0.1):
        import psutil

        self._proc = psutil.Process(pid)
        self.tree = self.own = 0
        self._stop = threading.Event()
        self._every = every_s
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import psutil

        while not self._stop.is_set():
            try:
                own = self._proc.memory_info().rss
                tree = own
                for c in self._proc.children(recursive=True):
                    try:
                        tree += c.memory_info().rss
                    except psutil.Error:
                        pass
            except psutil.Error:
                return
            self.own, self.tree = max(self.own, own), max(self.tree, tree)
            self._stop.wait(self._every)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


def run_command(argv: list[str]) -> dict:
    """Run one ``hybridloc`` command: wall time, peak tree and own RSS (MB), its stdout's last line."""
    t0 = time.monotonic()
    p = subprocess.Popen([*CLI, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    mem = _PeakRss(p.pid)
    out, err = p.communicate()
    wall = time.monotonic() - t0
    mem.stop()
    if p.returncode != 0:
        raise RuntimeError(f"hybridloc {' '.join(argv)} exited {p.returncode}: {err.strip().splitlines()[-1] if err.strip() else ''}")
    last = out.strip().splitlines()[-1] if out.strip() else ""
    return {"wall_s": wall, "tree_mb": mem.tree / 2**20, "own_mb": mem.own / 2**20, "last": last}


def run_mode(pristine: str, folder: Path, mode: str, workers: int) -> dict:
    """``slam rebuild`` then ``map rebuild`` on a copy of the database: serially, serially with the floor
    groups of ``slam rebuild`` in ``workers`` forked processes (``--serial --processes``), or on Dask."""
    from hybridloc.server.dask_batch import stored_digest
    from hybridloc.server.store import Store

    db = str(folder / f"{mode}.db")
    shutil.copy(pristine, db)
    how = ["--serial"] if mode in ("serial", "forked") else ["--workers", str(workers)]
    slam = run_command(["slam", "rebuild", "--db", db, *how, *(["--processes", str(workers)] if mode == "forked" else [])])
    site = json.loads(slam["last"])["sites"][0]
    st = Store(db, migrate=False)
    try:
        digest_slam = stored_digest(st, SITE)
    finally:
        st.close()
    survey = run_command(["map", "rebuild", "--db", db, "--site", SITE, *how])
    st = Store(db, migrate=False)
    try:
        digest_survey = stored_digest(st, SITE)
    finally:
        st.close()
    return {
        "slam": slam,
        "slam_run_s": float(site["seconds"]),
        "walks_corrected": int(site["walks_corrected"]),
        "loops_accepted": int(site["loops_accepted"]),
        "map": survey,
        "digest": (digest_slam, digest_survey),
    }


def _exponent(walks: list[int], secs: list[float]) -> float:
    """Slope of log(time) over log(walks) (least squares)."""
    return float(np.polyfit(np.log(walks), np.log(secs), 1)[0])


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--walks", type=int, default=16, help="N: the sizes are N, 2N and 4N walks (default 16)")
    ap.add_argument("--floors", type=int, default=2, help="floors of the simulated site (default 2)")
    ap.add_argument("--minutes", type=float, default=3.0, help="length of each walk, min (default 3)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2, help="worker processes of the local Dask cluster (default 2)")
    a = ap.parse_args(argv)
    sizes = [a.walks, 2 * a.walks, 4 * a.walks]
    print(
        f"[bench_rebuild] simulated site: {a.floors} floors, walks of {a.minutes:g} min, seed {a.seed}; sizes {sizes}; Dask: {a.workers} worker processes"
    )
    rows = []
    with tempfile.TemporaryDirectory(prefix="hybridloc-bench-rebuild-") as tmp:
        for n in sizes:
            folder = Path(tmp) / f"n{n}"
            folder.mkdir()
            t0 = time.monotonic()
            plan, walks = simulated_site(a.seed, n, a.floors, a.minutes)
            pristine = str(folder / "pristine.db")
            store_site(pristine, plan, walks)
            n_scans = sum(len(w.scans) for w in walks)
            print(f"  {n} walks ({n_scans} scans) simulated and stored in {time.monotonic() - t0:.1f} s")
            serial = run_mode(pristine, folder, "serial", a.workers)
            dask = run_mode(pristine, folder, "dask", a.workers)
            forked = run_mode(pristine, folder, "forked", a.workers)
            same = serial["digest"] == dask["digest"] == forked["digest"]
            rows.append((n, serial, dask, same, forked))
            for name, r in (("serial", serial), (f"dask x{a.workers}", dask), (f"fork x{a.workers}", forked)):
                print(
                    f"    {name:8s}  slam rebuild {r['slam']['wall_s']:6.1f} s (run {r['slam_run_s']:6.1f} s), peak {r['slam']['tree_mb']:6.0f} MB "
                    f"(command {r['slam']['own_mb']:5.0f} MB); map rebuild {r['map']['wall_s']:5.1f} s, peak {r['map']['tree_mb']:5.0f} MB; "
                    f"walks corrected {r['walks_corrected']}, loops accepted {r['loops_accepted']}"
                )
            print(
                f"    serial / dask: slam rebuild {serial['slam']['wall_s'] / dask['slam']['wall_s']:.2f}x (run {serial['slam_run_s'] / dask['slam_run_s']:.2f}x), "
                f"map rebuild {serial['map']['wall_s'] / dask['map']['wall_s']:.2f}x; serial / fork: slam rebuild "
                f"{serial['slam']['wall_s'] / forked['slam']['wall_s']:.2f}x (run {serial['slam_run_s'] / forked['slam_run_s']:.2f}x); "
                f"stored results identical: {same}"
            )
    s_wall = [r[1]["slam"]["wall_s"] for r in rows]
    d_wall = [r[2]["slam"]["wall_s"] for r in rows]
    s_run = [r[1]["slam_run_s"] for r in rows]
    d_run = [r[2]["slam_run_s"] for r in rows]
    ex_s, ex_d = _exponent(sizes, s_run), _exponent(sizes, d_run)
    ex_mem = _exponent(sizes, [r[1]["slam"]["tree_mb"] for r in rows])
    print(f"  growth N -> 4N (slope of log time over log walks): serial run {ex_s:.2f}, dask run {ex_d:.2f}; serial peak memory {ex_mem:.2f}")
    figures: dict = {"walks_n": sizes[0], "floors": a.floors, "workers": a.workers, "identical": all(r[3] for r in rows)}
    for k, tag in enumerate(("n", "2n", "4n")):
        n, serial, dask, _, forked = rows[k]
        figures.update(
            {
                f"serial_slam_s_{tag}": s_wall[k],
                f"dask_slam_s_{tag}": d_wall[k],
                f"serial_slam_run_s_{tag}": s_run[k],
                f"dask_slam_run_s_{tag}": d_run[k],
                f"slam_speedup_{tag}": s_wall[k] / d_wall[k],
                f"serial_map_s_{tag}": serial["map"]["wall_s"],
                f"dask_map_s_{tag}": dask["map"]["wall_s"],
                f"serial_slam_peak_mb_{tag}": serial["slam"]["tree_mb"],
                f"dask_slam_peak_mb_{tag}": dask["slam"]["tree_mb"],
                f"forked_slam_s_{tag}": forked["slam"]["wall_s"],
                f"forked_slam_run_s_{tag}": forked["slam_run_s"],
                f"forked_slam_speedup_{tag}": s_wall[k] / forked["slam"]["wall_s"],
                f"forked_slam_peak_mb_{tag}": forked["slam"]["tree_mb"],
            }
        )
    figures.update(growth_serial=ex_s, growth_dask=ex_d, growth_serial_memory=ex_mem)
    headline(figures)
    return figures


if __name__ == "__main__":
    main()

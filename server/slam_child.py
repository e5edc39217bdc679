"""The SLAM child process: where the server's crowd-SLAM compute runs (spawned, one per site worker).

The server's ingest thread must never wait on a solve, and a solve in a thread of the server process
would hold its GIL for seconds at a time. So each site's SLAM worker (:mod:`.slam_worker`, a thread
that only waits) spawns one child process running :func:`child_main`; the child keeps the site's
:class:`CrowdSlam` in memory between calls (:data:`_SITES`: rebuilt from the database when absent -
after a restart - or when a batch run completed elsewhere), reads walks and writes results through its
own :class:`Store`, and answers each call with a small summary (ids, states, the encoded track message)
that the worker publishes. Progress of a batch run travels back on the same queue.

The child runs at a lower CPU priority with one BLAS thread, so the server's threads get the CPU
first. It is spawned, never forked (a fork after ``zenoh.open`` breaks the child), imports no Zenoh,
and ends itself when its parent is gone (a SIGKILLed server must not leave a solver writing on). For a
batch run it forks copies of itself in turn, one per share of the site's groups of floors
(``SlamOptions.batch_processes``, :func:`.slam_batch._solve_groups`): it holds no Zenoh session, and a
copy only solves and answers on its pipe, then leaves by ``os._exit`` (it ends with the child too).
"""

from __future__ import annotations

import importlib
import logging
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from hybridloc.slam.online import CrowdSlam
from hybridloc.wire.codecs import TRACK
from hybridloc.wire.messages import Track

from . import db as m
from .child_process import yield_to_server
from .slam_batch import load_radio_map, load_site, result_of, run_batch
from .store import Store

log = logging.getLogger("hybridloc.server.slam")


@dataclass
class _Site:
    slam: CrowdSlam
    batch_run: int | None  # the newest complete batch run when the CrowdSlam was built or last updated
    map_version: int | None


#: site -> its CrowdSlam kept between calls
_SITES: dict[str, _Site] = {}
_HOOK: tuple[Callable[..., None], str] | None = None


def _latest_batch(store: Store, site: str) -> int | None:
    with Session(store.engine) as s:
        q = select(func.max(m.SlamRun.id)).where(m.SlamRun.site_id == site, m.SlamRun.kind == "batch", m.SlamRun.status == "complete")
        return s.execute(q).scalar_one()


def _map_version(store: Store, site: str) -> int | None:
    with Session(store.engine) as s:
        return s.execute(select(func.max(m.RadioMapVersion.version)).where(m.RadioMapVersion.site_id == site)).scalar_one()


def site_slam(store: Store, site: str) -> CrowdSlam:
    """The site's CrowdSlam: the one kept in memory, or rebuilt from the database when there is none or a
    batch run completed since it was built (a ``slam rebuild`` in another process); the newest radio map."""
    latest = _latest_batch(store, site)
    c = _SITES.get(site)
    if c is None or c.batch_run != latest:
        t0 = time.monotonic()
        c = _Site(load_site(store, site), latest, _map_version(store, site))
        _SITES[site] = c
        log.info("site %s: crowd SLAM loaded from the database (%d walks held) in %.1f s", site, len(c.slam.walks), time.monotonic() - t0)
    else:
        mv = _map_version(store, site)
        if mv != c.map_version:
            _, rmap = load_radio_map(store, site)
            if rmap is not None:
                c.slam.set_map(rmap)
                c.slam.set_vote_map(None)  # a map made elsewhere (a survey's): the vote reads it too
            c.map_version = mv
    return c.slam


def _hook(event: str, site: str, subject) -> None:
    if _HOOK is not None:
        _HOOK[0](event, site, subject, _HOOK[1])


def _track_message(site: str, device: str, walk_id: int, run: int, track, map_version: int | None) -> bytes:
    return TRACK.encode(Track(site, device, int(walk_id), map_version, run, track, time.time()))


# ------------------------------------------------------------------------------------------ calls
def add_walk(store: Store, site: str, walk_id: int, progress=None) -> dict:
    """Add one ended walk incrementally (its own variables solved, its neighbours held) and store the
    outcome: corrected, relative, or quarantined with the reason (not held, the map untouched)."""
    walk = store.read_walk(walk_id)
    _hook("walk", site, walk)
    slam = site_slam(store, site)
    out = slam.add_walk(walk)
    res = result_of(int(walk_id), out.track, out.quarantined)
    run = store.slam.save_walk(site, res, out.loops, stats={"seconds": out.seconds})
    store.slam.drop_live_runs(int(walk_id), run)
    mv = _map_version(store, site)
    loops = list(out.loops)
    return {
        "walk_id": int(walk_id),
        "device": walk.device,
        "status": res.status,
        "reason": res.reason,
        "run": run,
        "seconds": float(out.seconds),
        "loops": len(loops),
        "loops_accepted": sum(bool(lp.accepted) for lp in loops),
        "track": _track_message(site, walk.device, walk_id, run, out.track, mv) if out.track is not None and res.status != "quarantined" else None,
    }


def provisional(store: Store, site: str, walk_id: int, progress=None) -> dict:
    """A provisional correction of an open walk (its records so far): solved like an ended walk, not
    stored, not held - only the track message for the device, under a run id of its own
    (:meth:`~.slam_store.SlamStore.live_run`)."""
    walk = store.read_walk(walk_id)
    slam = site_slam(store, site)
    held = int(walk_id) in slam.walks
    out = slam.add_walk(walk)
    if not held:
        slam.remove_walk(int(walk_id))
    ok = out.track is not None and not out.quarantined
    run = store.slam.live_run(site, int(walk_id)) if ok else None
    return {
        "walk_id": int(walk_id),
        "device": walk.device,
        "t_end": walk.t_end,
        "seconds": float(out.seconds),
        "track": _track_message(site, walk.device, walk_id, run, out.track, _map_version(store, site)) if ok else None,
    }


def batch(
    store: Store,
    site: str,
    floors: list[str] | None = None,
    online: list[str] | None = None,
    lease_s: float = 60.0,
    processes: int = 1,
    progress=None,
) -> dict:
    """A batch re-solve (:func:`~.slam_batch.run_batch`) with the CrowdSlam kept here, its groups of floors
    spread over ``processes`` (this one and forked copies; one process under a test's hook, which runs
    before each floor); the track messages of the newest changed walk of each device in ``online``."""
    slam = site_slam(store, site)
    hook = (lambda f: _hook("floor", site, f)) if _HOOK is not None else None
    summary = run_batch(store, site, floors, progress, slam=slam, lease_s=lease_s, floor_hook=hook, processes=processes)
    c = _SITES.get(site)
    if c is not None:
        if summary.resumed:
            _SITES.pop(site, None)  # the floors solved before the kill are not in memory: reload
        else:
            # Known, measured, left as it is: the kept CrowdSlam keeps the map it was built with (the
            # survey map, or the one of its last load) - only the version is noted, so site_slam does
            # not load the run's new crowd map. Loading it (eval crowd, site1, F = 0.1, 2026-12-05)
            # lifted the coverage 68.6 -> 76.1 % but the correction gain fell 46 -> 30 % (goal 40 %):
            # the crowd map's fixes place walks worse than the survey map's. Measured again once a batch no
            # longer fixed walks to their own fed-back labels (4769ed2): coverage 67.7 %, learning 30 %,
            # correction 15 % (the final batches took the walks' corrected mean 7.99 -> 10.82 m).
            c.batch_run = summary.run_id
            c.map_version = _map_version(store, site)
            # ... but the floor vote reads the run's crowd map (CrowdSlam.set_vote_map): its labels name
            # more walks' floors than the survey's (site1: 82.2 against 77.5 % of the crowd walks on their
            # true floor, scripts/probe_walk_floors.py), and a floor is not a position fed back
            if c.slam.cfg.floor_vote:
                _, rmap = load_radio_map(store, site)
                c.slam.set_vote_map(rmap)
    want = set(online or ())
    newest: dict[str, int] = {}
    for wid, dev in summary.changed.items():
        if dev in want and wid > newest.get(dev, -1):
            newest[dev] = wid
    tracks = store.slam.tracks(site, walk_ids=newest.values()) if newest else {}
    msgs = {dev: _track_message(site, dev, wid, summary.run_id, tracks[wid], summary.map_version) for dev, wid in newest.items() if wid in tracks}
    return {"summary": summary.as_dict(), "tracks": msgs}


CALLS: dict[str, Callable[..., Any]] = {"add_walk": add_walk, "provisional": provisional, "batch": batch}


# ------------------------------------------------------------------------------------------ the process
def child_main(req_q, resp_q, parent_pid: int, db_url: str, hook: str | None, hook_arg: str, log_level: int) -> None:
    """The child's loop: (call id, name, kwargs) in, ("result", id, ok, value or traceback) and
    ("progress", id, (stage, floor, done, total)) out; None ends it."""
    global _HOOK
    logging.basicConfig(level=log_level, format="%(levelname)s %(name)s [slam child]: %(message)s")
    # the solver yields to the server: a lower CPU priority, and one BLAS thread (OpenBLAS takes every
    # core by default; on 2 cores the acks' p99 was then 117 ms while the child solved against 36 ms
    # idle; with this, p50 27 ms either way, p99 93 / 67 ms: benchmarks/bench_slam_worker.py)
    yield_to_server(parent_pid, 10, "hybridloc-slam-watch")
    if hook:
        mod, _, fn = hook.partition(":")
        _HOOK = (getattr(importlib.import_module(mod), fn), hook_arg)
    store = Store(db_url, migrate=False)
    try:
        while True:
            msg = req_q.get()
            if msg is None:
                return
            cid, name, kwargs = msg

            def progress(stage: str, floor: str, done: int, total: int, cid: int = cid) -> None:
                resp_q.put(("progress", cid, (str(stage), str(floor), int(done), int(total))))

            try:
                value = CALLS[name](store, progress=progress, **kwargs)
                resp_q.put(("result", cid, True, value))
            except Exception as exc:  # noqa: BLE001 - reported to the worker, which logs it with the walk id
                resp_q.put(("result", cid, False, (type(exc).__name__, str(exc), traceback.format_exc())))
    finally:
        store.close()

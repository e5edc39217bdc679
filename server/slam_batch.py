"""The batch re-solve of a site from what is stored: ``hybridloc slam rebuild`` and the server's schedule.

:func:`run_batch` is the one function both call (the command in its own process, the server in its
SLAM child process, :mod:`.slam_child`):

1. claim the site's batch run under a lease (:meth:`~.slam_store.SlamStore.claim_batch`): an
   unfinished run whose holder died (its heartbeat stopped, or its process is gone) is resumed, a live
   one refuses (:class:`~.slam_store.SlamBusy`: never two batch runs of a site at once); a heartbeat
   thread keeps the lease alive while the floors are solved;
2. per floor not yet done, :meth:`CrowdSlam.rebuild_floor` over every solvable walk of the site (ended,
   not quarantined) and :meth:`~.slam_store.SlamStore.write_floor`: the floor's tracks, loops and
   checkpoint in one transaction. A walk the solve quarantines (diverged, left the walkable area) is
   stored so and labels nothing;
3. the crowd radio maps from the labels of every walk's absolute track (the run's own for the floors it
   solved, the current ones elsewhere; survey walks are labelled by their mark-anchored tracks) and
   :meth:`~.slam_store.SlamStore.finish_run`: the new map version and the walks' new tracks become
   current in one transaction. Until then readers see the previous version.

A run killed at any point loses nothing: the floors it finished stay checkpointed and the next call
resumes after them; the previous map stays in service meanwhile.
"""

from __future__ import annotations

import logging
import os
import socket
import tempfile
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from hybridloc.errors import BadInput, ComputationFailed, MissingData
from hybridloc.slam.online import CrowdSlam, build_crowd_maps, labels_from_tracks
from hybridloc.types import CorrectedTrack, WalkEnd

from . import db as m
from .slam_store import CORRECTED, QUARANTINED, RELATIVE, SlamBusy, WalkResult
from .store import Store

log = logging.getLogger("hybridloc.server.slam")

#: A batch run's lease is stale when its heartbeat is this old, s (the holder refreshes it every quarter
#: of it; a holder on this host whose process is gone is stale at once).
LEASE_S = 60.0

ProgressFn = Callable[[str, str, int, int], None]

__all__ = ["LEASE_S", "BatchSummary", "SlamBusy", "load_site", "run_batch", "site_floors"]


@dataclass
class BatchSummary:
    """What a batch run did (``slam rebuild``'s JSON line, the server's log and announcements)."""

    site: str
    run_id: int
    resumed: bool
    floors: list[str]
    floors_skipped: list[str]  # checkpointed before a kill: not solved again
    walks: dict[str, int]  # by state, over the floors solved by this call
    quarantined: list[int]
    loops_accepted: int
    loops_rejected: int
    map_version: int | None
    n_scans: int
    coverage: float | None
    seconds: float
    changed: dict[int, str] = field(default_factory=dict)  # walk id -> device, walks whose track the run set

    def as_dict(self) -> dict:
        d = asdict(self)
        d["changed"] = {str(k): v for k, v in self.changed.items()}
        return d


# ------------------------------------------------------------------------------------------ lease
def _lease() -> dict:
    return {"token": uuid.uuid4().hex, "host": socket.gethostname(), "pid": os.getpid(), "heartbeat": time.time()}


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this host (a zombie, killed and not yet reaped, does not)."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as fh:
            return fh.read().rpartition(")")[2].split()[0] not in ("Z", "X")
    except FileNotFoundError:
        return False
    except OSError:
        pass
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def lease_is_stale(lease: dict, lease_s: float = LEASE_S, now: float | None = None) -> bool:
    """A lease whose heartbeat is older than ``lease_s`` or whose holder on this host is gone."""
    now = time.time() if now is None else now
    if now - float(lease.get("heartbeat", 0.0)) > lease_s:
        return True
    return lease.get("host") == socket.gethostname() and not _pid_alive(int(lease.get("pid", -1)))


class _Heartbeat:
    """Refreshes a run's lease every ``lease_s / 4`` s from a thread; :meth:`check` raises
    :class:`SlamBusy` once the lease is lost (taken over after a stall longer than the lease)."""

    def __init__(self, store: Store, site: str, run_id: int, lease: dict, lease_s: float):
        self.store, self.site, self.run_id, self.lease, self.lease_s = store, site, run_id, lease, lease_s
        self.lost = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"hybridloc-slam-lease-{run_id}", daemon=True)

    def __enter__(self) -> _Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        while not self._stop.wait(self.lease_s / 4):
            try:
                if not self.store.slam.renew_lease(self.run_id, self.lease["token"], time.time()):
                    self.lost = True
                    return
            except Exception:  # noqa: BLE001 - a busy database: try again at the next beat
                log.warning("batch run %d: lease not renewed", self.run_id, exc_info=True)

    def check(self) -> None:
        if self.lost or not self.store.slam.renew_lease(self.run_id, self.lease["token"], time.time()):
            self.lost = True
            raise SlamBusy(self.site, self.run_id, {"pid": "?", "host": "?", "heartbeat": "lost"})


# ------------------------------------------------------------------------------------------ the site
def site_floors(store: Store, site: str) -> list[str]:
    """Floors named by the site's ended walks, sorted."""
    with Session(store.engine) as s:
        q = (
            select(m.WalkFloor.floor)
            .join(m.Walk, m.Walk.id == m.WalkFloor.walk_id)
            .where(m.Walk.site_id == site, m.Walk.end_reason != WalkEnd.OPEN.value)
            .distinct()
        )
        return sorted(str(f) for f in s.execute(q).scalars())


def sites_with_walks(store: Store) -> list[str]:
    with Session(store.engine) as s:
        return sorted(str(x) for x in s.execute(select(m.Walk.site_id).where(m.Walk.end_reason != WalkEnd.OPEN.value).distinct()).scalars())


def load_radio_map(store: Store, site: str):
    """(version, RadioMap) of the site's newest stored map, or (None, None)."""
    import io

    from hybridloc.radio.radiomap import RadioMap

    got = store.load_map(site)
    if got is None:
        return None, None
    return got[0], RadioMap.load(io.BytesIO(got[1]))


def load_site(store: Store, site: str) -> CrowdSlam:
    """A site's :class:`CrowdSlam` rebuilt from the database: its floor plan, its newest radio map, and
    every solvable walk that has a track held with it as the current solution (no solve)."""
    slam = CrowdSlam(site, store.load_floor_plan(site))
    _, rmap = load_radio_map(store, site)
    if rmap is not None:
        slam.set_map(rmap)
    states = store.slam.walk_states(site)
    tracks = store.slam.tracks(site)
    for wid in store.slam.solvable_walks(site):
        st = states.get(wid)
        if st is not None and st.status in (CORRECTED, RELATIVE) and wid in tracks:
            slam.hold(store.read_walk(wid), tracks[wid])
    return slam


def _on_floor(track: CorrectedTrack | None, floor: str) -> CorrectedTrack | None:
    """The points of ``track`` on ``floor`` (None when it has none there): each floor's checkpoint holds
    its own points only, so a walk crossing floors is not written twice."""
    if track is None:
        return None
    sel = np.asarray(track.floor) == floor
    if not sel.any():
        return None
    if sel.all():
        return track
    idx = np.flatnonzero(sel)
    return CorrectedTrack(
        track.walk_id,
        track.t[idx],
        track.pos_enu[idx],
        track.cov[idx],
        tuple(track.floor[i] for i in idx),
        tuple(track.kind[i] for i in idx),
        track.anchored,
        track.scale,
        track.heading_bias,
    )


def _merge(a: CorrectedTrack, b: CorrectedTrack) -> CorrectedTrack:
    """One track of two walks' pieces (different floors), in time order."""
    t = np.concatenate([a.t, b.t])
    o = np.argsort(t, kind="stable")
    fl, kd = a.floor + b.floor, a.kind + b.kind
    best = a.anchored if a.anchored != "relative" else b.anchored
    return CorrectedTrack(
        a.walk_id,
        t[o],
        np.concatenate([a.pos_enu, b.pos_enu])[o],
        np.concatenate([a.cov, b.cov])[o],
        tuple(fl[i] for i in o),
        tuple(kd[i] for i in o),
        best,
        a.scale,
        a.heading_bias,
    )


def result_of(walk_id: int, track: CorrectedTrack | None, quarantined: str) -> WalkResult:
    """The stored state of one walk's solve: quarantined (with the reason), corrected (an absolute
    track), relative (a shape only, or nothing to place: no floor, too few steps)."""
    if quarantined:
        return WalkResult(walk_id, QUARANTINED, track, quarantined)
    if track is None:
        return WalkResult(walk_id, RELATIVE, None, "no track: nothing to place (no floor or too few steps)")
    return WalkResult(walk_id, CORRECTED if track.anchored != "relative" else RELATIVE, track)


def _map_bytes(rmap) -> bytes:
    with tempfile.TemporaryDirectory(prefix="hybridloc-map-") as d:
        p = Path(d) / "map.npz"
        rmap.save(p)
        return p.read_bytes()


# ------------------------------------------------------------------------------------------ the run
def run_batch(
    db: str | Store,
    site: str,
    floors: Iterable[str] | None = None,
    progress: ProgressFn | None = None,
    slam: CrowdSlam | None = None,
    lease_s: float = LEASE_S,
    floor_hook: Callable[[str], None] | None = None,
) -> BatchSummary:
    """Re-solve ``floors`` (None: every floor of the site's walks) of ``site`` from the database ``db``
    (a URL or an open :class:`Store`) and store the result atomically (module docstring).

    ``progress(stage, floor, done, total)``: stage "floors" before and after each floor (done = floors
    finished, the resumed ones included), the solver's own stages inside a floor, "map" and "done".
    ``slam``: the site's CrowdSlam when the caller keeps one (the server's child), else it is rebuilt
    from the database. ``floor_hook(floor)`` runs before each floor is solved (tests: slow a run down).

    :class:`MissingData` for a site without ended walks, :class:`BadInput` for a floor none of its walks
    names, :class:`SlamBusy` while another process solves the site, :class:`ComputationFailed` when a
    solve fails (the run is ended as failed; the previous map stays)."""
    t0 = time.monotonic()
    store, own = (db, False) if isinstance(db, Store) else (Store(str(db)), True)
    say = progress or (lambda *_: None)
    try:
        known = site_floors(store, site)
        if not known:
            raise MissingData(f"site {site!r} has no ended walks with a floor in the database")
        want = None if floors is None else sorted(set(floors))
        if want is not None:
            bad = [f for f in want if f not in known]
            if bad:
                raise BadInput(f"site {site!r} has no walks on floor(s) {', '.join(bad)} (floors: {', '.join(known)})")
        lease = _lease()
        run_id, resumed, _ = store.slam.claim_batch(site, want, lease, lambda held: lease_is_stale(held, lease_s))
        done_before = store.slam.floors_done(run_id)
        todo = want if want is not None else known
        if resumed:
            log.info("site %s: resuming batch run %d after floors %s", site, run_id, sorted(done_before) or "none")
        try:
            with _Heartbeat(store, site, run_id, lease, lease_s) as hb:
                summary = _solve_run(store, site, run_id, todo, done_before, say, slam, hb, floor_hook)
        except SlamBusy:
            raise
        except (KeyboardInterrupt, SystemExit):
            # interrupted (Ctrl-C, SIGTERM): the floors done stay checkpointed; free the run for a resume
            store.slam.release_lease(run_id, lease["token"])
            raise
        except Exception as exc:
            log.exception("site %s: batch run %d failed", site, run_id)
            store.slam.fail_run(run_id, f"{type(exc).__name__}: {exc}")
            raise ComputationFailed(f"site {site}: batch run {run_id} failed ({type(exc).__name__}: {exc}); the previous map stays") from exc
        summary.resumed = resumed
        summary.seconds = time.monotonic() - t0
        return summary
    finally:
        if own:
            store.close()


def _solve_run(
    store: Store,
    site: str,
    run_id: int,
    todo: list[str],
    done_before: set[str],
    say: ProgressFn,
    slam: CrowdSlam | None,
    hb: _Heartbeat,
    floor_hook: Callable[[str], None] | None,
) -> BatchSummary:
    plan = store.load_floor_plan(site)
    if slam is None:
        slam = load_site(store, site)
    # every solvable walk is in the graph: the held ones with their current track, the others (pending,
    # failed before, added while a batch ran) without one
    for wid in store.slam.solvable_walks(site):
        if wid not in slam.walks:
            slam.hold(store.read_walk(wid), None)
    by_state: Counter = Counter()
    quarantined: list[int] = []
    acc = rej = 0
    n = len(todo)
    finished = len(done_before & set(todo))
    for fl in todo:
        if fl in done_before:
            continue
        say("floors", fl, finished, n)
        if floor_hook is not None:
            floor_hook(fl)
        t_f = time.monotonic()

        def inner(stage: str, _floor: str, done: int, total: int, fl: str = fl) -> None:
            if stage != "done":  # the solver's own end of the floor: "floors" says it next
                say(stage, fl, done, total)

        out = slam.rebuild_floor(fl, progress=inner)
        results = []
        for wid, wo in sorted(out.walks.items()):
            res = result_of(int(wid), _on_floor(wo.track, fl), wo.quarantined)
            results.append(res)
            by_state[res.status] += 1
            if res.status == QUARANTINED:
                quarantined.append(int(wid))
        loops = list(out.loops)
        acc += sum(bool(lp.accepted) for lp in loops)
        rej += sum(not lp.accepted for lp in loops)
        hb.check()
        store.slam.write_floor(run_id, fl, results, loops, stats=dict(out.stats or {}, seconds=time.monotonic() - t_f))
        finished += 1
        say("floors", fl, finished, n)
    # the labels of every walk's absolute track: this run's on its floors, the current ones elsewhere
    say("map", "", 0, 1)
    run_floors = set(todo)
    tracks = store.slam.run_tracks(run_id, statuses=(CORRECTED, RELATIVE))
    states = store.slam.walk_states(site)
    for wid, tr in store.slam.tracks(site).items():
        st = states.get(wid)
        if st is None or st.status not in (CORRECTED, RELATIVE):
            continue
        rest = [f for f in set(tr.floor) if f not in run_floors]
        for f in rest:
            piece = _on_floor(tr, f)
            if piece is not None:
                tracks[wid] = _merge(tracks[wid], piece) if wid in tracks else piece
    walks = {wid: slam.walks[wid] if wid in slam.walks else store.read_walk(wid) for wid in tracks}
    labels = labels_from_tracks(list(walks.values()), tracks)
    maps = build_crowd_maps(labels, site, plan)
    wifi = [ls for ls in labels if ls.scan.technology.value == "wifi"]
    labelled = sorted({int(ls.source) for ls in labels})
    survey = [w for w in labelled if walks[w].marks]
    coverage = _coverage(store, site, labels)
    provenance = {
        "walks": labelled,
        "survey_walks": survey,
        "marks": int(sum(len(walks[w].marks) for w in survey)),
        "floors": todo,
        "coverage": coverage,
        "run": run_id,
        "resumed_after": sorted(done_before),
    }
    rmap = maps.get("wifi")
    hb.check()
    version = store.slam.finish_run(
        run_id,
        _map_bytes(rmap) if rmap is not None else None,
        n_scans=len(wifi),
        provenance=provenance,
        stats={"walks": dict(by_state), "quarantined": quarantined, "loops_accepted": acc, "loops_rejected": rej, "labels": len(labels)},
    )
    if rmap is None:
        log.info("site %s: batch run %d built no radio map (%d WiFi labels); the previous map stays", site, run_id, len(wifi))
    say("done", "", n, n)
    changed = {wid: walks[wid].device for wid in tracks if wid in walks}
    return BatchSummary(
        site, run_id, False, todo, sorted(done_before), dict(by_state), quarantined, acc, rej, version, len(wifi), coverage, 0.0, changed
    )


def _coverage(store: Store, site: str, labels) -> float | None:
    """Share of the scans of the site's ended walks without survey marks that got an absolute label."""
    crowd = {w.walk_id: w.n_scans for w in store.walks(site, ended_only=True) if w.n_marks == 0}
    total = sum(crowd.values())
    if not total:
        return None
    return sum(1 for ls in labels if int(ls.source) in crowd) / total

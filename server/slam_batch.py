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

import contextlib
import logging
import os
import signal
import socket
import tempfile
import threading
import time
import uuid
import warnings
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from hybridloc.errors import BadInput, ComputationFailed, MissingData
from hybridloc.slam.online import CrowdSlam, build_crowd_maps, labels_from_marks, labels_from_tracks
from hybridloc.types import CorrectedTrack, WalkEnd

from . import db as m
from .child_process import usable_cores  # noqa: F401 - imported from here by the batch commands and eval crowd
from .slam_store import CORRECTED, QUARANTINED, RELATIVE, SlamBusy, WalkResult
from .store import Store

log = logging.getLogger("hybridloc.server.slam")

#: A batch run's lease is stale when its heartbeat is this old, s (the holder refreshes it every quarter
#: of it; a holder on this host whose process is gone is stale at once).
LEASE_S = 60.0

ProgressFn = Callable[[str, str, int, int], None]


class WorkerLost(ComputationFailed):
    """The Dask cluster lost a worker or the scheduler while it solved a run: like a killed process, the
    floors written stay checkpointed and the next call resumes after them (the lease is released)."""


__all__ = ["LEASE_S", "BatchSummary", "FloorDone", "SlamBusy", "WorkerLost", "load_site", "run_batch", "site_floors", "solve_floor"]


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
    for wid, track in hold_order(store, site):
        if track is not None:
            slam.hold(store.read_walk(wid), track)
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
def floor_groups(walk_floors: Iterable[Iterable[str]], floors: Iterable[str]) -> list[list[str]]:
    """The connected groups of ``floors`` (each sorted; groups in the order of their first floor):
    two floors are in one group when some walk names both (``walk_floors``: each walk's floors; a walk's
    pieces lie on floors it names, so this is the pieces' grouping or a coarser one)."""
    names = sorted(set(floors))
    parent = {f: f for f in names}

    def root(f: str) -> str:
        while parent[f] != f:
            parent[f] = parent[parent[f]]
            f = parent[f]
        return f

    for fl in walk_floors:
        on = [f for f in fl if f in parent]
        for f in on[1:]:
            a, b = root(on[0]), root(f)
            if a != b:
                parent[max(a, b)] = min(a, b)
    groups: dict[str, list[str]] = {}
    for f in names:
        groups.setdefault(root(f), []).append(f)
    return sorted(groups.values(), key=lambda g: g[0])


def run_batch(
    db: str | Store,
    site: str,
    floors: Iterable[str] | None = None,
    progress: ProgressFn | None = None,
    slam: CrowdSlam | None = None,
    lease_s: float = LEASE_S,
    floor_hook: Callable[[str], None] | None = None,
    client=None,
    processes: int = 1,
) -> BatchSummary:
    """Re-solve ``floors`` (None: every floor of the site's walks) of ``site`` from the database ``db``
    (a URL or an open :class:`Store`) and store the result atomically (module docstring).

    ``progress(stage, floor, done, total)``: stage "floors" before and after each floor (done = floors
    finished, the resumed ones included), the solver's own stages inside a floor, "map" and "done".
    ``slam``: the site's CrowdSlam when the caller keeps one (the server's child), else it is rebuilt
    from the database. ``floor_hook(floor)`` runs before each floor is solved (tests: slow a run down).
    ``client``: a :class:`distributed.Client`: the floors are solved as Dask tasks, a chain per connected
    group of floors (:mod:`.dask_batch`), and written here as they come (not with ``slam`` or
    ``floor_hook``); None: in this process, one floor after another, or with ``processes`` > 1 the
    connected groups of floors spread over this process and ``processes - 1`` forked copies of it
    (:func:`_solve_groups`; not with ``floor_hook``). Every path stores the same results.

    :class:`MissingData` for a site without ended walks, :class:`BadInput` for a floor none of its walks
    names, :class:`SlamBusy` while another process solves the site, :class:`ComputationFailed` when a
    solve fails (the run is ended as failed; the previous map stays)."""
    if client is not None and (slam is not None or floor_hook is not None):
        raise ValueError("run_batch: a Dask client solves from the database, without a kept CrowdSlam or a floor hook")
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
                if client is None:
                    summary = _solve_run(store, site, run_id, todo, done_before, say, slam, hb, floor_hook, processes)
                else:
                    from .dask_batch import solve_run_on_dask

                    summary = solve_run_on_dask(client, store, site, run_id, todo, done_before, say, hb)
        except SlamBusy:
            raise
        except (KeyboardInterrupt, SystemExit, WorkerLost):
            # interrupted (Ctrl-C, SIGTERM, a Dask worker or scheduler gone): the floors done stay
            # checkpointed; free the run for a resume
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


@dataclass
class FloorDone:
    """One floor of a batch run solved: what :meth:`~.slam_store.SlamStore.write_floor` stores (computed
    by this process or by a Dask worker, :mod:`.dask_batch`, and written by the run's own process)."""

    floor: str
    results: list[WalkResult]
    loops: list
    stats: dict


def solve_floor(slam: CrowdSlam, floor: str, fold_walks: list[int], say: ProgressFn) -> FloorDone:
    """:meth:`CrowdSlam.rebuild_floor` of one floor and the stored state of each of its walks (pure: no
    database). ``fold_walks``: the walks held when the run began (their rank is each walk's EM fold).

    On one BLAS thread, wherever it runs (this process, the server's SLAM child, a Dask worker): the
    tracks' covariances (the solver's marginals) differ in their last bits with the BLAS thread count,
    and one thread was not slower (48 simulated walks on 2 floors, benchmarks/bench_rebuild.py's site,
    one run each on a shared 2-core machine: 30.9 s against 34.9 s with its 2 threads)."""
    from threadpoolctl import threadpool_limits

    t_f = time.monotonic()

    def inner(stage: str, _floor: str, done: int, total: int) -> None:
        if stage != "done":  # the solver's own end of the floor: "floors" says it next
            say(stage, floor, done, total)

    with threadpool_limits(limits=1):
        out = slam.rebuild_floor(floor, progress=inner, fold_walks=fold_walks)
    results = [result_of(int(wid), _on_floor(wo.track, floor), wo.quarantined) for wid, wo in sorted(out.walks.items())]
    return FloorDone(floor, results, list(out.loops), dict(out.stats or {}, seconds=time.monotonic() - t_f))


@dataclass
class _Tally:
    """What the floors of a run gave, summed as they are written."""

    by_state: Counter = field(default_factory=Counter)
    quarantined: list[int] = field(default_factory=list)
    accepted: int = 0
    rejected: int = 0

    def add(self, fd: FloorDone) -> None:
        for res in fd.results:
            self.by_state[res.status] += 1
            if res.status == QUARANTINED:
                self.quarantined.append(int(res.walk_id))
        self.accepted += sum(bool(lp.accepted) for lp in fd.loops)
        self.rejected += sum(not lp.accepted for lp in fd.loops)


def write_floor(store: Store, run_id: int, fd: FloorDone, tally: _Tally, hb: _Heartbeat) -> None:
    """Check the lease, store the floor's checkpoint (one transaction), count it."""
    tally.add(fd)
    hb.check()
    store.slam.write_floor(run_id, fd.floor, fd.results, fd.loops, stats=fd.stats)


def hold_order(store: Store, site: str) -> list[tuple[int, CorrectedTrack | None]]:
    """Every solvable walk of the site as a batch run holds it, in that order: first those with a current
    track (corrected or relative: :func:`load_site`), then the others without one (pending, failed
    before, added while a batch ran). The order is each floor's order of pieces, which the incremental
    re-add of a walk the batch could not fit reads: a Dask worker holding a part of the site holds it
    in the same order (:mod:`.dask_batch`)."""
    states = store.slam.walk_states(site)
    tracks = store.slam.tracks(site)
    solvable = store.slam.solvable_walks(site)
    first = [w for w in solvable if (st := states.get(w)) is not None and st.status in (CORRECTED, RELATIVE) and w in tracks]
    held = set(first)
    return [(w, tracks[w]) for w in first] + [(w, None) for w in solvable if w not in held]


@dataclass
class CrowdMapBuilt:
    """The crowd radio map of a run (:func:`crowd_map`): its bytes (None: too few labels), the WiFi label
    count, every label's walk (how many each: the coverage) and the walks with survey marks among them."""

    data: bytes | None
    n_wifi: int
    n_labels: int
    labels_per_walk: dict[int, int]
    survey_walks: list[int]
    n_marks: int


def crowd_map(walks: list, tracks: dict[int, CorrectedTrack], site: str, plan) -> CrowdMapBuilt:
    """The labels of every walk's absolute track and the crowd radio maps built from them (pure: no
    database; ``walks``: those of ``tracks`` in its order, then the survey walks without a track, which
    are labelled by their marks, :func:`labels_from_marks`; on one BLAS thread, as :func:`solve_floor`)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1):
        labels = labels_from_tracks(walks, tracks) + labels_from_marks(walks, tracks)
        maps = build_crowd_maps(labels, site, plan)
    rmap = maps.get("wifi")
    per_walk = Counter(int(ls.source) for ls in labels)
    by_id = {int(w.walk_id): w for w in walks}
    survey = [w for w in sorted(per_walk) if by_id[w].marks]
    return CrowdMapBuilt(
        _map_bytes(rmap) if rmap is not None else None,
        sum(1 for ls in labels if ls.scan.technology.value == "wifi"),
        len(labels),
        dict(sorted(per_walk.items())),
        survey,
        int(sum(len(by_id[w].marks) for w in survey)),
    )


def survey_walks(store: Store, site: str) -> list[int]:
    """The site's walks with survey marks, ended or still open (``map rebuild`` labels an open survey's
    scans too), but not the quarantined ones."""
    states = store.slam.walk_states(site)
    return [w.walk_id for w in store.walks(site) if w.n_marks > 0 and ((st := states.get(w.walk_id)) is None or st.status != QUARANTINED)]


def run_tracks_for_map(store: Store, site: str, run_id: int, run_floors: set[str]) -> dict[int, CorrectedTrack]:
    """The tracks a run's map labels: this run's on its floors, the current ones elsewhere."""
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
    return tracks


def finish(
    store: Store,
    site: str,
    run_id: int,
    todo: list[str],
    done_before: set[str],
    tally: _Tally,
    say: ProgressFn,
    hb: _Heartbeat,
    walk_of: Callable[[int], object],
    build: Callable[[list, dict[int, CorrectedTrack]], CrowdMapBuilt],
) -> BatchSummary:
    """The run's crowd map from the labels of every walk's absolute track (``build``: :func:`crowd_map`
    here or on a worker), then :meth:`~.slam_store.SlamStore.finish_run`: the new map and tracks current
    in one transaction. ``walk_of(walk_id)``: the walk (held in memory, else read)."""
    say("map", "", 0, 1)
    tracks = run_tracks_for_map(store, site, run_id, set(todo))
    walks = {wid: walk_of(wid) for wid in tracks}
    # surveys ended since the run began, still open, or held without an absolute track: their marks label
    # them, so the crowd map never serves fewer survey labels than a survey map it replaces
    untracked = [wid for wid in survey_walks(store, site) if wid not in tracks]
    built = build([walks[w] for w in tracks] + [walk_of(w) for w in untracked], tracks)
    labelled = sorted(built.labels_per_walk)
    coverage = _coverage(store, site, built.labels_per_walk)
    provenance = {
        "walks": labelled,
        "survey_walks": built.survey_walks,
        "marks": built.n_marks,
        "floors": todo,
        "coverage": coverage,
        "run": run_id,
        "resumed_after": sorted(done_before),
    }
    hb.check()
    version = store.slam.finish_run(
        run_id,
        built.data,
        n_scans=built.n_wifi,
        provenance=provenance,
        stats={
            "walks": dict(tally.by_state),
            "quarantined": tally.quarantined,
            "loops_accepted": tally.accepted,
            "loops_rejected": tally.rejected,
            "labels": built.n_labels,
        },
    )
    if built.data is None:
        log.info("site %s: batch run %d built no radio map (%d WiFi labels); the previous map stays", site, run_id, built.n_wifi)
    n = len(todo)
    say("done", "", n, n)
    changed = {wid: walks[wid].device for wid in tracks}  # type: ignore[attr-defined]
    return BatchSummary(
        site,
        run_id,
        False,
        todo,
        sorted(done_before),
        dict(tally.by_state),
        tally.quarantined,
        tally.accepted,
        tally.rejected,
        version,
        built.n_wifi,
        coverage,
        0.0,
        changed,
    )


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
    processes: int = 1,
) -> BatchSummary:
    """The serial path: one CrowdSlam of the whole site in this process, the floors one after another
    (with ``processes`` > 1, groups of them in forked copies of this process: :func:`_solve_groups`)."""
    plan = store.load_floor_plan(site)
    if slam is None:
        slam = load_site(store, site)
    # every solvable walk is in the graph: the held ones with their current track, the others (pending,
    # failed before, added while a batch ran) without one
    for wid in store.slam.solvable_walks(site):
        if wid not in slam.walks:
            slam.hold(store.read_walk(wid), None)
    # walks the map could not place when they were added: their floor asked again of today's map
    moved = slam.revote_floors()
    if moved:
        log.info("site %s: %d walk(s) held on another floor than they name, by their fingerprints", site, len(moved))
    fold_walks = sorted(slam.walks)
    tally = _Tally()
    n = len(todo)
    finished = len(done_before & set(todo))
    left = [fl for fl in todo if fl not in done_before]
    groups = floor_groups(slam.held_walk_floors().values(), left) if processes > 1 and floor_hook is None and hasattr(os, "fork") else [left]
    groups = [[fl for fl in left if fl in g] for g in groups]  # each group's floors in the run's order
    if len(groups) > 1:
        _solve_groups(store, run_id, slam, groups, fold_walks, say, tally, hb, finished, n, processes)
    else:
        for fl in left:
            finished = _solve_here(store, run_id, slam, fl, fold_walks, say, say, tally, hb, finished, n, floor_hook)
    return finish(
        store,
        site,
        run_id,
        todo,
        done_before,
        tally,
        say,
        hb,
        lambda wid: slam.walks[wid] if wid in slam.walks else store.read_walk(wid),
        lambda walks, tracks: crowd_map(walks, tracks, site, plan),
    )


def _solve_here(
    store: Store,
    run_id: int,
    slam: CrowdSlam,
    fl: str,
    fold_walks: list[int],
    say: ProgressFn,
    solver_say: ProgressFn,
    tally: _Tally,
    hb: _Heartbeat,
    finished: int,
    n: int,
    floor_hook: Callable[[str], None] | None = None,
) -> int:
    """One floor solved in this process and written, between its two "floors" progress messages
    (``solver_say`` gets the solver's own stages); returns the floors finished."""
    say("floors", fl, finished, n)
    if floor_hook is not None:
        floor_hook(fl)
    write_floor(store, run_id, solve_floor(slam, fl, fold_walks, solver_say), tally, hb)
    say("floors", fl, finished + 1, n)
    return finished + 1


def _split(groups: list[list[str]], parts: int) -> list[list[list[str]]]:
    """``groups`` dealt to ``parts`` processes: the first group to this one, each other one to the forked
    process with the fewest floors so far (a floor's cost is not known before its solve)."""
    out: list[list[list[str]]] = [[groups[0]]] + [[] for _ in range(max(1, min(parts, len(groups))) - 1)]
    for g in groups[1:]:
        min(out[1:] or out, key=lambda p: sum(len(x) for x in p)).append(g)
    return [p for p in out if p]


#: a forked copy that sends nothing (no solver stage, no result) for this long is taken as hung, killed,
#: and its floors solved in the process that forked it (a stage of a site1 floor takes up to ~60 s)
FORK_SILENCE_S = 900.0


class _Fork:
    """A copy of this process made by ``os.fork`` (not ``multiprocessing``: the server's SLAM child is a
    daemonic process, which multiprocessing does not let have children) and the pipe it answers on."""

    def __init__(self, target: Callable[..., None], *args):
        import multiprocessing as mp

        self.conn, send = mp.Pipe(duplex=False)
        self.exitcode: int | None = None
        with warnings.catch_warnings():
            # Python 3.12+ warns on a fork beside threads: the copy runs the solve alone (the pure library,
            # the pipe) and leaves by os._exit, never touching the database, Zenoh or another thread's lock
            warnings.simplefilter("ignore", DeprecationWarning)
            self.pid = os.fork()
        if self.pid == 0:  # the copy: run, answer, and leave without running the parent's exit handlers
            code = 1
            try:
                self.conn.close()
                target(*args, send)
                code = 0
            finally:
                os._exit(code)
        send.close()

    def alive(self) -> bool:
        if self.exitcode is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid == self.pid:
                self.exitcode = os.waitstatus_to_exitcode(status)
        return self.exitcode is None

    def end(self) -> None:
        """Kill it if it still runs, and reap it."""
        self.conn.close()
        if self.alive():
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signal.SIGKILL)
            _, status = os.waitpid(self.pid, 0)
            self.exitcode = os.waitstatus_to_exitcode(status)


def _forked_main(slam: CrowdSlam, groups: list[list[str]], fold_walks: list[int], mark, parent_pid: int, conn) -> None:
    """A forked copy of the batch's process: solve ``groups`` (in order) on the inherited CrowdSlam and
    send back each floor's result, then the state delta (None when the solves touched a floor of another
    process); on an exception, its text. It ends with the process that forked it."""
    from .child_process import _watch_parent

    threading.Thread(target=_watch_parent, args=(parent_pid,), name="hybridloc-slam-fork-watch", daemon=True).start()
    try:
        done = []
        for g in groups:
            for fl in g:
                done.append(solve_floor(slam, fl, fold_walks, lambda *a: conn.send(("progress", a))))
        bad = slam.outside_changed(mark)
        conn.send(("done", done, None if bad else slam.floors_delta(mark), bad))
    except BaseException as exc:  # noqa: BLE001 - reported to the process that forked this one
        import traceback

        conn.send(("error", f"{type(exc).__name__}: {exc}", traceback.format_exc()))
    finally:
        conn.close()


def _solve_groups(
    store: Store,
    run_id: int,
    slam: CrowdSlam,
    groups: list[list[str]],
    fold_walks: list[int],
    say: ProgressFn,
    tally: _Tally,
    hb: _Heartbeat,
    finished: int,
    n: int,
    processes: int,
) -> None:
    """Connected groups of floors (:func:`floor_groups`: no walk is held on two of them) solved side by
    side: the first group here, the others in ``processes - 1`` forked copies of this process, which
    share the site's CrowdSlam copy-on-write (no reload, no copy sent) and send back each floor's result
    and what the solves changed (:meth:`CrowdSlam.floors_delta`); each floor is written here as its
    result comes, and the copies' deltas are adopted after this process's own floors
    (:meth:`CrowdSlam.adopt_floors`), so the state equals the serial order's. The results equal the
    serial path's (tests/test_slam_fork.py): each group's solve reads only its own floors and walks.

    A copy that fails (an exception, a crash, a walk re-added by its fingerprints onto a floor of
    another group), or whose floors this process changed meanwhile, is discarded and its floors are
    solved here after this process's own, as the serial path does; its floors' results are written
    only once the copy is known to be good, so a discarded copy never leaves a checkpoint."""
    parts = _split(groups, processes)
    mine = parts[0]
    forks = []
    for part in parts[1:]:
        floors = [fl for g in part for fl in g]
        mark = slam.mark_floors(floors)
        proc = _Fork(_forked_main, slam, part, fold_walks, mark, os.getpid())
        forks.append({"floors": floors, "mark": mark, "conn": proc.conn, "proc": proc, "msg": None, "heard": time.monotonic()})
    announced: set[str] = set()
    try:

        def died(fk: dict) -> tuple:
            return ("error", f"the forked process died (exit code {fk['proc'].exitcode})", "")

        def drain() -> None:
            for fk in forks:
                while fk["msg"] is None and fk["conn"].poll():
                    try:
                        msg = fk["conn"].recv()
                    except (EOFError, OSError):  # it ended without its result
                        deadline = time.monotonic() + 5.0
                        while fk["proc"].alive() and time.monotonic() < deadline:
                            time.sleep(0.01)
                        fk["msg"] = died(fk)
                        break
                    fk["heard"] = time.monotonic()
                    if msg[0] == "progress":
                        if msg[1][1] not in announced:  # a floor the fork began: "floors" before it, as here
                            announced.add(msg[1][1])
                            say("floors", msg[1][1], finished, n)
                        say(*msg[1])
                    else:
                        fk["msg"] = msg

        def mine_say(stage: str, floor: str, done: int, total: int) -> None:
            say(stage, floor, done, total)
            drain()

        for g in mine:
            for fl in g:
                finished = _solve_here(store, run_id, slam, fl, fold_walks, say, mine_say, tally, hb, finished, n)
        redo: list[str] = []
        for fk in forks:
            while fk["msg"] is None:
                if not fk["conn"].poll(0.25):
                    if not fk["proc"].alive() and not fk["conn"].poll():
                        fk["msg"] = died(fk)
                    elif time.monotonic() - fk["heard"] > FORK_SILENCE_S:  # hung (a lock the fork inherited held?)
                        fk["proc"].end()
                        fk["msg"] = ("error", f"the forked process said nothing for {FORK_SILENCE_S:g} s (killed)", "")
                    continue
                drain()
            msg = fk["msg"]
            touched = slam.touched(fk["mark"])
            if msg[0] != "done" or msg[2] is None or touched:
                why = msg[1] if msg[0] == "error" else f"floors outside its own changed ({', '.join(msg[3] or touched)})"
                log.warning("floors %s: the forked solve is not used (%s); solving them here", ", ".join(fk["floors"]), why)
                redo += fk["floors"]
                continue
            for fd in msg[1]:
                write_floor(store, run_id, fd, tally, hb)
                finished += 1
                say("floors", fd.floor, finished, n)
            slam.adopt_floors(fk["mark"], msg[2])
        for fl in redo:
            finished = _solve_here(store, run_id, slam, fl, fold_walks, say, say, tally, hb, finished, n)
    finally:
        slam.end_mark()
        for fk in forks:
            fk["proc"].end()


def _coverage(store: Store, site: str, labels_per_walk: dict[int, int]) -> float | None:
    """Share of the scans of the site's ended walks without survey marks that got an absolute label."""
    crowd = {w.walk_id: w.n_scans for w in store.walks(site, ended_only=True) if w.n_marks == 0}
    total = sum(crowd.values())
    if not total:
        return None
    return sum(n for w, n in labels_per_walk.items() if w in crowd) / total

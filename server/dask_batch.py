"""Batch work on Dask distributed: ``slam rebuild`` and ``map rebuild`` as tasks of a Dask cluster.

The work leaves this process, the database does not: workers compute from what this process reads
and ships to them, and this process writes every result (the checkpoints, the new map version, the
tracks), so the guarantees of the serial path hold unchanged - atomic (readers see the old version
until :meth:`~.slam_store.SlamStore.finish_run`), resumable per floor (each floor is written as its
task returns), one batch run of a site at a time (the lease, renewed from here) - and a worker needs
neither a database driver nor a route to the database.

**Cluster** (:func:`batch_client`): ``--scheduler ADDRESS`` connects to a running scheduler (``dask
scheduler`` + ``dask worker`` on other machines; the workers need ``hybridloc`` installed); by default a
:class:`distributed.LocalCluster` of worker *processes* (one thread each, as many as the usable cores)
is started for the command and closed with it. Processes, not threads: a floor's solve is mostly
Python (the walk graph, the loop front end's candidate lists, the quarantine checks) holding the GIL,
so threads would take turns on one core; a local worker process costs ~3 s of imports (started on
every worker as soon as the client opens, while this process reads the database: :func:`_warm_up`)
and ~200 MB. Every solve runs on one BLAS thread (:func:`~.slam_batch.solve_floor`: the covariances'
last bits depend on the BLAS thread count), so two workers on two cores do not oversubscribe. A
worker process whose parent dies (the command killed) exits at once (Dask's parent-alive pipe).

**Tasks of a ``slam rebuild``** (:func:`solve_run_on_dask`): per site, per *connected group of floors*:
floors joined by a walk that crosses between them (a walk's pieces on two floors tie their solves: the
quarantine check and the incremental re-add of a walk the batch could not fit read the walk's other
floors), found from the walks' floors. A group is a Dask actor (:class:`GroupSolver`) on one worker:
it holds the group's walks (every solvable walk with a piece on one of its floors, in the serial
path's order, with its current track) and is asked for its floors one after the other, in the serial
order; each floor's result comes straight back and is written at once. Groups run in parallel.
Nothing else couples floors: each walk's EM fold is its rank among the walks held when the run began
(``fold_walks``), and frame ids of relative groups are compared only for equality within a floor.
Inside a floor the solve is one joint problem (one loop front end fitted on the whole floor, one GNC
schedule, EM with the floor's crowd map), so a floor is the smallest exact unit. The crowd map at the
end is one more task. Results equal the serial path's (tests/test_dask_batch.py compares digests of
the stored map, tracks, walk states and loop audit).

**Tasks of a ``map rebuild``** (:func:`hybridloc.server.rebuild.rebuild` with a client): one per device
to label (a device's survey walks are labelled together, bridged between its marks), then the map.

Progress: the workers' solver stages come back as Dask events (``Worker.log_event`` on a topic of the
run, :meth:`distributed.Client.subscribe_topic`) and go to the same progress callback as the serial
path's; "floors" counts the floors written.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import queue
import time
import uuid
from collections import deque
from collections.abc import Iterator

import numpy as np

from hybridloc.errors import BadInput
from hybridloc.slam.online import CrowdSlam

from .slam_batch import (
    BatchSummary,
    CrowdMapBuilt,
    FloorDone,
    ProgressFn,
    WorkerLost,
    _Heartbeat,
    _Tally,
    crowd_map,
    finish,
    floor_groups,
    hold_order,
    solve_floor,
    usable_cores,
    write_floor,
)
from .store import Store

log = logging.getLogger("hybridloc.server.dask")

#: how often the waiting loop passes the workers' progress events on, s
POLL_S = 0.25


@contextlib.contextmanager
def batch_client(scheduler: str | None = None, workers: int | None = None) -> Iterator:
    """A :class:`distributed.Client` for the batch commands (module docstring, "Cluster"): connected to
    the scheduler at ``scheduler`` (``tcp://HOST:PORT``), else to a local cluster of ``workers`` worker
    processes (default :func:`usable_cores`) started here. Closed (and the local cluster shut down,
    its processes joined) on exit, also on an exception."""
    from distributed import Client, LocalCluster

    if workers is not None and workers < 1:
        raise BadInput(f"--workers must be at least 1 (got {workers})")
    # Dask's own loggers say INFO at every connection and shutdown: quiet unless this process asks for INFO
    dlog = logging.getLogger("distributed")
    level_before = dlog.level
    dlog.setLevel(logging.INFO if logging.getLogger().getEffectiveLevel() < logging.WARNING else logging.WARNING)
    try:
        yield from _open_client(scheduler, workers, Client, LocalCluster)
    finally:
        dlog.setLevel(level_before)


@contextlib.contextmanager
def _warmed(client):
    """``client``, its workers' imports started (:func:`_warm_up`), closed at the end. A command that
    ends before the imports did (nothing to do) first lets them finish: a local cluster closed under a
    worker busy importing logged its heartbeat's failure with a traceback."""
    warm: list = []
    try:
        warm = _warm_up(client)
        yield client
        if warm:
            from distributed import wait

            with contextlib.suppress(Exception):
                wait(warm, timeout=WARM_UP_WAIT_S)
    finally:
        del warm
        client.close()


#: longest wait, s, for the warm-up imports when a command is done before them (:func:`_warmed`)
WARM_UP_WAIT_S = 15.0


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the local cluster starts its processes: they inherit the disposition (it
    survives the spawn's exec, and Python and asyncio leave an ignored SIGINT alone), so a Ctrl-C at
    the terminal, which signals the whole process group, reaches this process alone, which closes the
    cluster in order, instead of every worker dying of a KeyboardInterrupt with a traceback of its own."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


def _open_client(scheduler: str | None, workers: int | None, Client, LocalCluster) -> Iterator:
    if scheduler:
        try:
            client = Client(scheduler)  # waits up to Dask's distributed.comm.timeouts.connect (30 s)
        except (OSError, ValueError, TypeError) as exc:
            raise BadInput(f"cannot reach the Dask scheduler at {scheduler} ({type(exc).__name__}: {exc})") from exc
        with _warmed(client):
            yield client
        return
    n = workers or usable_cores()
    with _sigint_ignored():
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,  # no web server (and no bokeh needed)
            silence_logs=logging.ERROR,
            host="127.0.0.1",
        )
    try:
        with _warmed(Client(cluster)) as client:
            yield client
    finally:
        cluster.close()


def _import_task_modules() -> None:
    """Task: import what the batch tasks run (numpy, scipy, scikit-learn, shapely and hybridloc's SLAM)."""
    import hybridloc.server.rebuild  # noqa: F401
    import hybridloc.slam.online  # noqa: F401


def _warm_up(client) -> list:
    """A task per worker importing the task modules (~3 s of a fresh process) while this process reads
    the database, so the first solve does not wait for them; the futures are kept while the client is used."""
    try:
        return [client.submit(_import_task_modules, key=f"hybridloc-warm-up-{uuid.uuid4().hex}", workers=[w], pure=False) for w in client.nthreads()]
    except Exception:  # noqa: BLE001 - only a head start: the tasks import them anyway
        return []


def _infrastructure_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean the cluster, not the computation, failed (a worker or the scheduler gone)."""
    from distributed.client import FutureCancelledError
    from distributed.comm.core import CommClosedError
    from distributed.scheduler import KilledWorker

    return (KilledWorker, FutureCancelledError, CommClosedError)


# ------------------------------------------------------------------------------------------ events
def _send_event(topic: str, msg: dict) -> None:
    """A progress event from inside a task (ignored outside a worker)."""
    try:
        from distributed import get_worker

        get_worker().log_event(topic, msg)
    except ValueError:  # not running on a worker
        pass


class _Events:
    """The run's progress topic: events from the workers queued here, passed on by the waiting thread."""

    def __init__(self, client, say: ProgressFn):
        self.client, self.say = client, say
        self.topic = f"hybridloc-progress-{uuid.uuid4().hex}"
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        client.subscribe_topic(self.topic, lambda ev: self._q.put(ev[1]))

    def drain(self) -> None:
        while True:
            try:
                m = self._q.get_nowait()
            except queue.Empty:
                return
            self.say(str(m["stage"]), str(m["floor"]), int(m["done"]), int(m["total"]))

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.client.unsubscribe_topic(self.topic)
        self.drain()


# ------------------------------------------------------------------------------------------ slam: groups
# ------------------------------------------------------------------------------------------ slam: tasks
class GroupSolver:
    """A Dask actor (lives on one worker): the CrowdSlam of one connected group of floors - the group's
    walks held with their current tracks, in the serial order - and its floors solved one call at a time
    (:meth:`solve`), each call's :class:`~.slam_batch.FloorDone` sent straight back to the client.

    An actor, not a chain of tasks passing the CrowdSlam on: a floor's result must reach the client as
    soon as it is solved (the checkpoint), while the state stays on the worker; as a chained task's
    output the result would need a getter task, which a worker runs only after the next solve it has
    already queued (a run killed then loses a finished floor). A worker runs its actors' calls on one
    thread, one solve at a time."""

    def __init__(self, site: str, plan, map_bytes: bytes | None, held: list, fold_walks: list[int], topic: str):
        from hybridloc.radio.radiomap import RadioMap
        from hybridloc.slam.online import CrowdSlam

        self.fold_walks, self.topic = fold_walks, topic
        self.slam = CrowdSlam(site, plan)
        if map_bytes is not None:
            self.slam.set_map(RadioMap.load(io.BytesIO(map_bytes)))
        for walk, track in held:
            self.slam.hold(walk, track)

    def solve(self, floor: str) -> FloorDone:
        """One floor of the group (:func:`~.slam_batch.solve_floor`), in the serial order of the floors."""

        def say(stage: str, fl: str, done: int, total: int) -> None:
            _send_event(self.topic, {"stage": stage, "floor": fl, "done": done, "total": total})

        return solve_floor(self.slam, floor, self.fold_walks, say)


def _crowd_map_task(walks: list, tracks: dict, site: str, plan) -> CrowdMapBuilt:
    return crowd_map(walks, tracks, site, plan)


def solve_run_on_dask(
    client,
    store: Store,
    site: str,
    run_id: int,
    todo: list[str],
    done_before: set[str],
    say: ProgressFn,
    hb: _Heartbeat,
) -> BatchSummary:
    """The floors ``todo`` (minus ``done_before``) of a claimed batch run solved on Dask (module
    docstring): a :class:`GroupSolver` actor per connected group of floors, its floors asked one after
    the other in the serial order, each written here as it returns; then the crowd map as a task and
    :func:`~.slam_batch.finish`."""
    plan = store.load_floor_plan(site)
    got = store.load_map(site)
    map_bytes = got[1] if got is not None else None
    order = hold_order(store, site)
    walks = {wid: store.read_walk(wid) for wid, _ in order}
    fold_walks = sorted(walks)
    solve = [f for f in todo if f not in done_before]
    # each walk's floors as the groups' CrowdSlams hold it (CrowdSlam.held_floors: the floors it names,
    # or with the floor vote the one the server put it on) - the group that solves that floor must hold
    # it; the map is read only when the vote needs it
    probe = CrowdSlam(site, plan)
    if probe.cfg.floor_vote and map_bytes is not None:
        from hybridloc.radio.radiomap import RadioMap

        probe.set_map(RadioMap.load(io.BytesIO(map_bytes)))
    tracks = dict(order)
    held_floors = {wid: probe.held_floors(w, tracks[wid]) for wid, w in walks.items()}
    every_floor = set(todo) | {f for fl in held_floors.values() for f in fl}
    groups = [g for g in floor_groups(held_floors.values(), every_floor) if set(g) & set(solve)]
    tally = _Tally()
    n = len(todo)
    finished = len(done_before & set(todo))
    say("floors", solve[0] if solve else "", finished, n)
    tag = f"{run_id}-{uuid.uuid4().hex[:8]}"  # keys of this call only (a shared scheduler may run others)
    events = _Events(client, say)
    futures: list = []
    try:
        plan_f, map_f = client.scatter([plan, map_bytes], hash=False, broadcast=True)
        futures += [plan_f, map_f]
        if groups:
            payloads = [[(walks[wid], tr) for wid, tr in order if set(held_floors[wid]) & set(g)] for g in groups]
            # one scatter call: Dask spreads the list's items over the workers (round robin), and each
            # group's actor is then made where its walks are
            held_f = client.scatter(payloads, hash=False)
            made = [
                client.submit(
                    GroupSolver, site, plan_f, map_f, hf, fold_walks, events.topic, actor=True, key=f"hybridloc-group-{site}-{'+'.join(g)}-{tag}"
                )
                for g, hf in zip(groups, held_f)
            ]
            futures += held_f + made
            # per group: its floors to solve (serial order) and the call running
            queues = [deque(f for f in solve if f in g) for g in groups]
            running: list = [None] * len(groups)
            actors = [None] * len(groups)
            while any(queues) or any(r is not None for r in running):
                for k, q in enumerate(queues):
                    if actors[k] is None and made[k].done():
                        actors[k] = made[k].result()
                    if actors[k] is not None and running[k] is None and q:
                        running[k] = (q[0], actors[k].solve(q[0]))
                    if running[k] is not None and running[k][1].done():
                        fl, call = running[k]
                        running[k] = None
                        q.popleft()
                        write_floor(store, run_id, call.result(), tally, hb)
                        finished += 1
                        say("floors", fl, finished, n)
                events.drain()
                if not any(r is not None and r[1].done() for r in running):
                    time.sleep(POLL_S / 5)
            del actors, running
        events.drain()

        def build(map_walks: list, tracks: dict) -> CrowdMapBuilt:
            wf, tf = client.scatter([map_walks, tracks], hash=False)
            fut = client.submit(_crowd_map_task, wf, tf, site, plan_f, key=f"hybridloc-map-{site}-{tag}", pure=False)
            futures.extend((wf, tf, fut))
            return fut.result()

        return finish(store, site, run_id, todo, done_before, tally, say, hb, lambda wid: walks[wid] if wid in walks else store.read_walk(wid), build)
    except _infrastructure_errors() as exc:
        raise WorkerLost(f"site {site}: batch run {run_id}: the Dask cluster lost a worker or the scheduler ({type(exc).__name__}: {exc})") from exc
    finally:
        events.close()
        # an error or an interrupt: stop what still runs (done futures are released with their references)
        pending = [f for f in futures if not f.done()]
        if pending:
            with contextlib.suppress(Exception):
                client.cancel(pending)


# ------------------------------------------------------------------------------------------ digests
def map_digest(data: bytes | None) -> str | None:
    """sha256 of a stored radio map's content: every array (dtype, shape, bytes) and the metadata
    without its build time (``built_at``), in name order - equal for maps built alike at other times."""
    if data is None:
        return None
    h = hashlib.sha256()
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        for name in sorted(z.files):
            a = z[name]
            if name == "meta":
                meta = json.loads(a.tobytes().decode("utf-8"))
                meta.pop("built_at", None)
                h.update(b"meta" + json.dumps(meta, sort_keys=True).encode())
                continue
            h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def stored_digest(store: Store, site: str) -> dict[str, str | None]:
    """Digests of what a rebuild stored for ``site``: ``map`` (the newest map version's content,
    :func:`map_digest`), ``tracks`` (every current track: walk, points, covariances, floors, kinds,
    anchoring, scale, heading bias), ``states`` (each walk's status, anchoring and reason) and ``loops``
    (the current loop audit as a set of rows: their ids follow the order floors were written in)."""
    got = store.load_map(site)
    h = hashlib.sha256()
    for wid, tr in sorted(store.slam.tracks(site).items()):
        h.update(f"{wid}|{tr.anchored}|{tr.scale!r}|{tr.heading_bias!r}|{'/'.join(tr.floor)}|{'/'.join(tr.kind)}".encode())
        for a in (tr.t, tr.pos_enu, tr.cov):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    states = sorted((w, s.status, s.anchored, s.reason) for w, s in store.slam.walk_states(site).items())
    loops = sorted(
        repr((lp.floor, lp.walk_a, lp.t_a, lp.walk_b, lp.t_b, lp.similarity, lp.weight, lp.p_inlier, lp.accepted, lp.reason, lp.kind))
        for lp in store.slam.loops(site)
    )
    return {
        "map": map_digest(got[1]) if got is not None else None,
        "tracks": h.hexdigest(),
        "states": hashlib.sha256(repr(states).encode()).hexdigest(),
        "loops": hashlib.sha256("\n".join(loops).encode()).hexdigest(),
    }

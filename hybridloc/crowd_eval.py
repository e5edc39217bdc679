"""``hybridloc eval crowd``: the evaluation as a crowd would live it (issue #21, point 6).

A real server (Zenoh router on a loopback port, SQLite file) in this process, and the site's walks
replayed through real client sessions:

1. **surveys**: a seeded draw (``numpy.random.default_rng(seed)``) of round(F N) of the N walks of the
   selected floors, replayed concurrently as survey agents with their waypoint marks (the operator
   surveys before the crowd arrives); then the survey radio map is built from the stored marks
   (:func:`hybridloc.server.rebuild.rebuild`, what ``map rebuild`` does) and served;
2. **crowd**: every other walk, in time order (the recording's start time), as a phone client
   without marks: phone PDR, steps and scans uploaded, the server's fixes fused as they arrive
   (lock-step replay, :meth:`hybridloc.clients.agent.Agent.wait_answers`: a fix reaches the filter
   when it would live, however fast the replay runs). A few clients run at a time, in time order;
   each third of the clients starts only when the previous third has finished, so the thirds of the
   learning curve follow each other as they would live.

Scoring. Each client's live pose rows (one per step or accepted fix, each the estimate available at
that moment) are scored **causally** at every one of its hidden waypoints: the newest row at or before
the waypoint's time (:func:`live_errors`). A waypoint before the client's first row - its filter starts
from its first fix - is not scored, and counted. After the crowd, and after the server's SLAM has
processed every finished walk, each client's corrected track (the smoother's, read from the database,
:meth:`hybridloc.server.slam_store.SlamStore.tracks`) is scored at all its waypoints
(:func:`track_errors`); relative tracks (a shape in the walk's own frame) are never scored as
positions, they count against the coverage.

Figures: the learning curve (live error of the first, middle and last third of the clients in time
order), live versus corrected on the same waypoints, the server's coverage and quarantined walks,
time per phase, the ratios next to the goals (:data:`GOALS`). The last line is one JSON object.

The time of the crowd is compressed: clients replay as fast as the lock-step allows (``speed`` 0) and
the idle time between walks is skipped. The server's own work is not skipped: with the crowd SLAM on,
a client starts only when the server has processed every walk that ended before the client's walk
started on the recording's clock (what a live server, minutes between walks, would have done),
bounded by a timeout that is counted and reported.
"""

from __future__ import annotations

import concurrent.futures as cf
import io
import json
import math
import re
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import BadInput, ComputationFailed, MissingData
from .metrics import held_rows

#: the issue's goals: (learning: last third's live mean at least 30 % below the first third's;
#: correction: corrected tracks at least 40 % below the same clients' live tracks at the same
#: waypoints; coverage: at least 80 % of the unmarked walks' scans with an absolute corrected position)
GOALS = {"learning_gain": 0.30, "correction_gain": 0.40, "coverage": 0.80}
#: batch re-solves after the crowd: at most this many, repeated while one lifts the server's coverage by
#: at least FINAL_BATCH_MIN_GAIN (run_crowd)
FINAL_BATCHES = 3
FINAL_BATCH_MIN_GAIN = 0.005


# --------------------------------------------------------------------------------------------- plan
@dataclass(frozen=True)
class CrowdWalk:
    """One recording of the site, as the evaluation uses it (no sensor data read yet)."""

    path: Path
    device: str  # the device id it is replayed as (one device per walk: walk ids map 1:1)
    floor: str  # the floor folder it lies in
    t_start: float  # the recording's start time, s (the walks' clock: Unix time)


@dataclass(frozen=True)
class CrowdPlan:
    site: str  # the site id the walks name (SiteID), the server's site
    floors: tuple[str, ...]  # the floors evaluated
    surveys: tuple[CrowdWalk, ...]  # by file name
    clients: tuple[CrowdWalk, ...]  # in time order


def _recording_header(path: Path) -> tuple[float | None, str | None]:
    """(start time s, SiteID) from a recording's header lines (``startTime`` in Unix ms), falling back
    on the first record's time; only the lines up to the first record are read."""
    from .io.common import ReadReport
    from .io.msft import iter_ilc_records

    start, site = None, None
    for _, rtype, f in iter_ilc_records(path, ReadReport(str(path), "skip")):
        if rtype != "#":
            if start is None:
                try:
                    start = float(f[0]) / 1000.0
                except ValueError:
                    pass
            break
        for part in f:
            key, _, value = part.partition(":")
            if key.strip() == "startTime":
                try:
                    start = float(value) / 1000.0
                except ValueError:
                    pass
            elif key.strip() == "SiteID" and value.strip():
                site = value.strip()
    return start, site


def _device_id(stem: str, taken: set[str]) -> str:
    """A device id valid on the wire (1-64 of [A-Za-z0-9_.-], :func:`hybridloc.wire.protocol.check_id`)
    from a file's stem, unique among ``taken``."""
    base = re.sub(r"[^A-Za-z0-9_.-]", "_", stem)[:56] or "walk"
    dev, k = base, 1
    while dev in taken:
        k += 1
        dev = f"{base}-{k}"
    taken.add(dev)
    return dev


def plan_crowd(site_dir: str | Path, survey_fraction: float = 0.1, seed: int = 0, floors: list[str] | None = None) -> CrowdPlan:
    """The surveys (a seeded draw of round(F N) of the N walks of the selected floors) and the clients
    (every other walk, in time order). :class:`~hybridloc.errors.BadInput` for F outside (0, 1), an
    unknown floor, or a draw that leaves no survey or no client; :class:`~hybridloc.errors.MissingData`
    for a missing folder or one without recordings."""
    from .errors import check_input_dir
    from .io.msft import find_ilc_traces
    from .wire.protocol import check_id

    if not (isinstance(survey_fraction, (int, float)) and 0.0 < survey_fraction < 1.0):
        raise BadInput(f"--survey-fraction must be in (0, 1), got {survey_fraction!r}")
    site_dir = Path(site_dir)
    check_input_dir(site_dir, "Indoor Location Competition site folder")
    paths = find_ilc_traces(site_dir)
    if not paths:
        raise MissingData(f"{site_dir}: no Indoor Location Competition recordings (**/path_data_files/*.txt[.gz])")
    by_floor: dict[str, list[Path]] = {}
    for p in paths:
        by_floor.setdefault(p.parent.parent.name, []).append(p)
    if floors:
        unknown = [f for f in floors if f not in by_floor]
        if unknown:
            raise BadInput(f"--floors: unknown floor {unknown[0]!r} (the site has {', '.join(sorted(by_floor))})")
        chosen = list(dict.fromkeys(floors))
    else:
        chosen = sorted(by_floor)
    sel = sorted((p for f in chosen for p in by_floor[f]), key=lambda p: p.name)
    n_survey = int(round(survey_fraction * len(sel)))
    if n_survey < 1 or n_survey >= len(sel):
        raise BadInput(
            f"--survey-fraction {survey_fraction:g} of {len(sel)} walks draws {n_survey} surveys: at least one survey and one client are needed"
        )
    taken: set[str] = set()
    walks, sites = [], []
    for p in sel:
        start, site = _recording_header(p)
        if start is None:
            raise MissingData(f"{p}: no start time and no record (not an Indoor Location Competition recording)")
        sites.append(site)
        walks.append(CrowdWalk(p, _device_id(p.name.split(".")[0], taken), p.parent.parent.name, start))
    site = next((s for s in sites if s), None) or re.sub(r"[^A-Za-z0-9_.-]", "_", site_dir.name)[:64]
    check_id(site, "site")
    pick = set(np.random.default_rng(seed).choice(len(walks), size=n_survey, replace=False).tolist())
    surveys = tuple(w for i, w in enumerate(walks) if i in pick)
    clients = tuple(sorted((w for i, w in enumerate(walks) if i not in pick), key=lambda w: (w.t_start, w.path.name)))
    return CrowdPlan(site, tuple(chosen), surveys, clients)


def thirds(n: int) -> list[np.ndarray]:
    """The positions 0..n-1 (clients in time order) cut into three consecutive parts, sizes within one."""
    return [np.asarray(a, int) for a in np.array_split(np.arange(n), 3)]


# ------------------------------------------------------------------------------------------ scoring
def live_positions(poses, wp_t) -> np.ndarray:
    """(n, 2) the live position the phone showed at each waypoint time: the newest pose row (t, x, y,
    ...) at or before it (at equal times the later row); NaN before the first row."""
    wp_t = np.asarray(wp_t, float)
    xy = np.full((len(wp_t), 2), np.nan)
    # held_rows scores the waypoints after the first; a leading sentinel makes every waypoint one
    idx = held_rows(poses, np.concatenate([[-np.inf], wp_t]))
    ok = idx >= 0
    if ok.any():
        xy[ok] = np.array([[poses[i][1], poses[i][2]] for i in idx[ok]], float)
    return xy


def live_errors(poses, wp_t, wp_xy) -> np.ndarray:
    """Causal scoring of a live track at EVERY waypoint: the error of :func:`live_positions` there, as
    the phone showed it then; NaN at a waypoint before the first row (the filter starts from the
    client's first fix: not scored)."""
    return np.linalg.norm(live_positions(poses, wp_t) - np.asarray(wp_xy, float).reshape(-1, 2), axis=1)


def track_errors(tracks, wp_t, wp_xy) -> np.ndarray:
    """A corrected (smoothed) track scored at every waypoint: its position interpolated at the
    waypoint's time (:meth:`hybridloc.types.CorrectedTrack.at`), from the first of ``tracks`` whose span
    covers it (a device's walk may be stored as several); NaN where none does."""
    wp_t = np.asarray(wp_t, float)
    wp_xy = np.asarray(wp_xy, float)
    out = np.full(len(wp_t), np.nan)
    for k, t in enumerate(wp_t):
        for tr in tracks:
            got = tr.at(float(t))
            if got is not None:
                out[k] = float(np.linalg.norm(np.asarray(got[0], float) - wp_xy[k]))
                break
    return out


@dataclass
class ClientScore:
    walk: CrowdWalk
    order: int  # position in time order
    wp_t: np.ndarray  # the hidden waypoints (the truth stays in the harness; the client never sends them)
    wp_xy: np.ndarray
    live: np.ndarray  # per waypoint, m; NaN before the first fix
    corrected: np.ndarray | None = None  # per waypoint, m, after the final batch re-solve; NaN where no absolute corrected track covers it
    incremental: np.ndarray | None = None  # the same before it: the walk added one by one (and the batch runs the crowd triggered)
    walk_ids: tuple[int, ...] = ()
    slam_status: str = ""  # the walk's SLAM state ("corrected", "relative", "quarantined", "failed", "" none)
    map_grown: bool | None = None  # --grow-map: the server served its walk's labels as added (None: not grown)
    map_version: int | None = None  # the radio map version the server served when the client started
    fixes_received: int = 0
    fixes_accepted: int = 0
    unacked: int = 0  # batches the server had not acknowledged when the client closed
    wall: tuple[float, float] = (0.0, 0.0)  # (start, end) of its replay, time.monotonic()
    tracks_received: int = 0  # corrected tracks of the crowd SLAM the client heard while it walked
    tracks_applied: int = 0  # ... and re-anchored its filter with (its live rows after that include them)
    live_xy: np.ndarray | None = None  # (n, 2) the live position scored at each waypoint (NaN before the first fix)
    #: the survey-only baseline (:func:`survey_baseline`): per waypoint, m, the same client replayed offline
    #: with fixes from the survey map only, and with the map version it was served (NaN before its first fix)
    survey_only: np.ndarray | None = None
    replayed: np.ndarray | None = None

    @property
    def waypoints(self) -> int:
        return len(self.wp_t)

    @property
    def unscored(self) -> int:
        return int(np.isnan(self.live).sum())


def _stats(e) -> dict:
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"n": 0, "mean": float("nan"), "median": float("nan"), "p90": float("nan")}
    return {"n": int(e.size), "mean": float(e.mean()), "median": float(np.median(e)), "p90": float(np.percentile(e, 90))}


def _cat(arrays) -> np.ndarray:
    arrays = [np.asarray(a, float) for a in arrays]
    return np.concatenate(arrays) if arrays else np.zeros(0)


def _gain(x: float, ref: float) -> float:
    """1 - x / ref: the share by which x is below ref (NaN when either is undefined)."""
    return 1.0 - x / ref if math.isfinite(x) and math.isfinite(ref) and ref > 0 else float("nan")


# ---------------------------------------------------------------------------- the SLAM-dependent part
class _Slam:
    """What the evaluation asks of the server's crowd SLAM (``on`` False when the server runs none:
    then every corrected figure is undefined and printed as null)."""

    def __init__(self, server, site: str, on: bool):
        self.server, self.site, self.on = server, site, on

    def processed(self) -> set[int]:
        """Walk ids the server's SLAM has seen (a state row, whatever its outcome)."""
        return self.server.store.slam.processed_walks(self.site) if self.on else set()

    def summary(self) -> dict | None:
        return self.server.store.slam.summary(self.site) if self.on else None

    def tracks(self, walk_ids) -> tuple[dict, dict]:
        """(walk id -> current corrected track, walk id -> state) of ``walk_ids``."""
        if not self.on:
            return {}, {}
        ids = set(walk_ids)
        states = {k: v for k, v in self.server.store.slam.walk_states(self.site).items() if k in ids}
        return self.server.store.slam.tracks(self.site, walk_ids=sorted(ids)), states

    def last_batch_run(self) -> int:
        """Id of the site's newest batch run (0 before any)."""
        runs = self.server.store.slam.runs(self.site, kind="batch", limit=1) if self.on else []
        return runs[0].run_id if runs else 0

    def batch(self, timeout: float) -> tuple[bool, str]:
        """Ask the server for a batch re-solve of every floor (the smoother over all the walks) and wait
        for a run newer than the newest one before the request to end; (complete?, what happened)."""
        before = self.last_batch_run()
        self.server.request_batch(self.site)

        def ended() -> bool:
            runs = self.server.store.slam.runs(self.site, kind="batch", limit=1)
            return bool(runs) and runs[0].run_id > before and runs[0].status != "running"

        ok, _ = _wait_until(ended, timeout, poll=0.5)
        runs = self.server.store.slam.runs(self.site, kind="batch", limit=1)
        status = runs[0].status if runs and runs[0].run_id > before else "not started"
        return ok and status == "complete", status if ok else f"{status} (timed out after {timeout:g} s)"


def _start_server(endpoint: str, db: str, site: str, slam: bool = True, grow_map: bool = False):
    """The server, with its crowd SLAM worker on the site (unless ``slam`` is False: the survey map
    alone, the control without any learning; ``grow_map``: the worker's ``SlamOptions.grow_map``);
    (server, :class:`_Slam`)."""
    import importlib.util

    from .server.service import Server

    if not slam or importlib.util.find_spec("hybridloc.server.slam_worker") is None:  # the latter: a server without the worker
        server = Server(endpoint, db).start()
        return server, _Slam(server, site, on=False)
    from .server.slam_worker import SlamOptions

    # the worker's defaults, but its idle pause short: the crowd's time is compressed, and a worker
    # sleeping a second between walks would pace the replay, not the solves
    server = Server(endpoint, db, slam_sites=[site], slam_options=SlamOptions(poll_s=0.05, grow_map=grow_map)).start()
    return server, _Slam(server, site, on=True)


def _slam_processes() -> int:
    """The processes the server's batch re-solves spread their groups of floors over (the worker's default)."""
    from .server.slam_worker import SlamOptions

    return SlamOptions().batch_process_count()


def _wait_until(cond, timeout: float, poll: float = 0.1) -> tuple[bool, float]:
    """Poll ``cond()`` until true or ``timeout`` s; (true?, seconds waited). Never hangs."""
    t0 = time.monotonic()
    while True:
        if cond():
            return True, time.monotonic() - t0
        if time.monotonic() - t0 >= timeout:
            return False, time.monotonic() - t0
        time.sleep(poll)


# ---------------------------------------------------------------------------------------- replaying
@dataclass
class _Replayed:
    walk: CrowdWalk
    result: Any  # AgentResult; None when the recording could not be replayed
    waypoints: Any  # Waypoints
    t_end: float  # the recording's last record, s
    skipped: str = ""
    wall: tuple[float, float] = (0.0, 0.0)  # (start, end) of the replay, time.monotonic()
    close_error: str = ""  # closing the client's Zenoh session failed (the replay itself completed)


def _replay_walk(endpoint: str, site: str, walk: CrowdWalk, spool: Path, survey: bool, speed: float, axes: dict) -> _Replayed:
    """One walk through a real client session: a survey agent (marks on, unpaced) or a phone client
    (no marks, lock-step at ``speed``, 0 = as fast as the answers allow)."""
    from .clients.agent import Agent, PoseWriter, open_client, replay_phone
    from .fusion import LocalFusion
    from .io.msft import read_ilc_trace

    wall0 = time.monotonic()
    tr = read_ilc_trace(walk.path)
    ends = [float(tr.imu.t[-1])] if tr.imu is not None and len(tr.imu.t) else []
    ends += [s.t for s in tr.scans[-1:]] + [float(t) for t in tr.waypoints.t[-1:]]
    t_end = max(ends) if ends else walk.t_start
    if tr.imu is None or len(tr.imu.t) < 2:
        return _Replayed(walk, None, tr.waypoints, t_end, skipped="no IMU data", wall=(wall0, time.monotonic()))
    s = open_client(endpoint)
    close_error = ""
    try:
        ag = Agent(s, site, walk.device, spool / walk.device, PoseWriter(None), tr.device_model, fusion=LocalFusion(corridor_axes=axes))
        ag.uplink.wait_connected(10)
        replay_phone(ag, tr, speed, survey=survey, lockstep=not survey)
        res = ag.close(wait=30)
    finally:
        try:
            s.close()
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError "close operation timed out" on a starved machine: the walk is scored, the failure counted
            close_error = str(exc).splitlines()[0][:120] if str(exc) else type(exc).__name__
            print(f"[eval crowd] {walk.device}: closing its Zenoh session failed ({close_error}); its walk counts", file=sys.stderr, flush=True)
    return _Replayed(walk, res, tr.waypoints, t_end, wall=(wall0, time.monotonic()), close_error=close_error)


# ------------------------------------------------------------------------------------------ the run
@dataclass
class CrowdRun:
    plan: CrowdPlan
    clients: list[ClientScore]
    skipped: list[tuple[CrowdWalk, str]]
    survey_labels: int
    map_version_survey: int | None
    map_version_final: int | None
    slam_on: bool
    summary: dict | None
    seconds: dict = field(default_factory=dict)  # per phase
    pace_waits: int = 0  # client starts that waited for the server's SLAM
    pace_timeouts: int = 0  # ... and gave up after the timeout
    final_wait_ok: bool | None = None  # every finished walk processed before the corrected scoring
    final_batch_ok: bool | None = None  # the final batch re-solve completed
    final_batch: str = ""  # its outcome in words
    final_coverages: list = field(default_factory=list)  # the server's coverage after each batch re-solve after the crowd
    concurrency: int = 1
    close_errors: int = 0  # client sessions whose close failed (their walks count)
    out: Path | None = None  # the run's folder (server.db, spool/, clients.jsonl)
    axes: dict = field(default_factory=dict)  # the floors' corridor axes the clients' filters use
    baseline: bool = False  # the survey-only baseline was replayed (ClientScore.survey_only / replayed)
    grow_map: bool = False  # the served map grew at every added walk (SlamOptions.grow_map)
    walks_grown: int | None = None  # ... by this many walks' labels (the server's count; None: not grown)

    @property
    def final_batches(self) -> int:
        """Batch re-solves after the crowd (run_crowd: repeated while the coverage grows)."""
        return len(self.final_coverages)


def run_crowd(
    site_dir: str | Path,
    survey_fraction: float = 0.1,
    seed: int = 0,
    floors: list[str] | None = None,
    out: str | Path = "out/eval-crowd",
    concurrency: int = 3,
    speed: float = 0.0,
    wait_timeout: float = 600.0,
    progress: bool = True,
    slam: bool = True,
    baseline: bool = True,
    grow_map: bool = False,
) -> CrowdRun:
    """Replay the site as a crowd (module docstring) and score every client; returns the run.
    ``baseline``: also replay every client offline against the survey map only (:func:`survey_baseline`).
    ``grow_map``: the server serves each added walk's labels on top of its map version
    (``SlamOptions.grow_map``); the baseline's replay with the maps served then replays the stored
    versions alone, without those labels, so it no longer retraces the live run."""
    from . import geo
    from .io.msft import read_ilc_site
    from .progress import Progress
    from .server.rebuild import rebuild
    from .wire.zconfig import free_port

    if concurrency < 1:
        raise BadInput(f"--concurrency must be at least 1, got {concurrency}")
    if grow_map and not slam:
        raise BadInput("--grow-map needs the crowd SLAM (it serves the labels of the walks the SLAM adds): drop --no-slam")
    if not (math.isfinite(speed) and speed >= 0):
        raise BadInput(f"--speed must be 0 (unpaced) or positive, got {speed}")
    t0 = time.monotonic()
    plan = plan_crowd(site_dir, survey_fraction, seed, floors)
    fp = read_ilc_site(site_dir)
    axes = geo.corridor_axes(fp)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("spool", "rebuild-cache"):  # a fresh database: the spools and the rebuild cache of an earlier run go too
        shutil.rmtree(out / stale, ignore_errors=True)
    db = out / "server.db"
    for suffix in ("", "-wal", "-shm"):
        Path(str(db) + suffix).unlink(missing_ok=True)
    (out / "clients.jsonl").unlink(missing_ok=True)  # an earlier run's: written again only when this one completes
    say = (lambda *a: print(*a, flush=True)) if progress else (lambda *a: None)
    ep = f"tcp/127.0.0.1:{free_port()}"
    server, slam = _start_server(ep, str(db), plan.site, slam, grow_map)
    say(
        f"[eval crowd] server on {ep}, database {db} (crowd SLAM {'on' if slam.on else 'off: corrected figures undefined'}); "
        f"{len(plan.surveys)} surveys, {len(plan.clients)} clients on {', '.join(plan.floors)}"
    )
    skipped: list[tuple[CrowdWalk, str]] = []
    scores: list[ClientScore] = []
    secs: dict = {}
    run = CrowdRun(
        plan, scores, skipped, 0, None, None, slam.on, None, secs, concurrency=concurrency, out=out, axes=axes, grow_map=grow_map and slam.on
    )
    try:
        server.store.save_floor_plan(plan.site, fp)  # the operator's `floorplan import`
        # ------------------------------------------------------------------ phase 1: the surveys
        t1 = time.monotonic()
        bar = Progress("[eval crowd] surveys uploaded", len(plan.surveys), sys.stdout) if progress else None
        with cf.ThreadPoolExecutor(concurrency) as ex:
            futs = [ex.submit(_replay_walk, ep, plan.site, w, out / "spool", True, 0.0, axes) for w in plan.surveys]
            for i, f in enumerate(futs, 1):
                r = f.result()
                if r.skipped:
                    skipped.append((r.walk, r.skipped))
                if bar:
                    bar.update(i)
        version, n_lab, _ = rebuild(server.store, plan.site, out / "rebuild-cache")
        if version is None:
            raise ComputationFailed("no radio map could be built from the surveys")
        server.load_map(plan.site)
        run.survey_labels, run.map_version_survey = n_lab, version
        if slam.on:  # the operator's surveys are in before the crowd arrives: the server has seen them
            survey_ids = {w.walk_id for w in server.store.walks(plan.site, ended_only=True)}
            ok, _ = _wait_until(lambda: survey_ids <= slam.processed(), wait_timeout)
            run.pace_waits += 1
            run.pace_timeouts += not ok
        secs["surveys"] = time.monotonic() - t1
        say(f"[eval crowd] survey radio map version {version} from {n_lab} labelled scans; surveys {secs['surveys']:.0f} s")
        # ------------------------------------------------------------------ phase 2: the crowd
        t2 = time.monotonic()
        waited = 0.0
        cuts = {int(p[0]) for p in thirds(len(plan.clients))[1:] if len(p)}
        ended: list[tuple[float, tuple[int, ...]]] = []  # (recording end, walk ids) of finished clients
        started_version: dict[int, int | None] = {}
        bar = (
            Progress(f"[eval crowd] clients finished (lock-step, {'unpaced' if speed == 0 else f'{speed:g}x'})", len(plan.clients), sys.stdout)
            if progress
            else None
        )
        done: list[_Replayed] = []

        def collect(fs) -> None:
            for f in fs:
                r = running.pop(f)
                rep = f.result()
                done.append(rep)
                run.close_errors += bool(rep.close_error)
                if rep.skipped:
                    skipped.append((rep.walk, rep.skipped))
                else:
                    ids = tuple(w.walk_id for w in server.store.walks(plan.site, device=rep.walk.device))
                    ended.append((rep.t_end, ids))
                    scores.append(_score_live(rep, r, ids, started_version.get(r)))
                if bar:
                    bar.update(len(done))

        running: dict = {}
        with cf.ThreadPoolExecutor(concurrency) as ex:
            for i, w in enumerate(plan.clients):
                if i in cuts:  # a third starts when the previous one has finished
                    collect(list(cf.as_completed(list(running))))
                while len(running) >= concurrency:
                    fin, _ = cf.wait(list(running), return_when=cf.FIRST_COMPLETED)
                    collect(fin)
                if slam.on:
                    need = {wid for t_end, ids in ended if t_end < w.t_start for wid in ids}
                    if not need <= slam.processed():
                        ok, dt = _wait_until(lambda need=need: need <= slam.processed(), wait_timeout)
                        waited += dt
                        run.pace_waits += 1
                        run.pace_timeouts += not ok
                loc = server.locators.get(plan.site)
                started_version[i] = loc[0] if loc else None
                running[ex.submit(_replay_walk, ep, plan.site, w, out / "spool", False, speed, axes)] = i
            collect(list(cf.as_completed(list(running))))
        secs["clients"] = time.monotonic() - t2
        secs["waiting_for_slam"] = waited
        say(f"[eval crowd] {len(scores)} clients in {secs['clients']:.0f} s")
        # ------------------------------------------------------------------ the server's correction
        t3 = time.monotonic()
        if slam.on:
            # every finished walk processed (added one by one: the corrections the crowd lived with) ...
            ok, _ = _wait_until(lambda: (slam.summary() or {}).get("walks_pending", 0) == 0, wait_timeout, poll=0.5)
            run.final_wait_ok = ok
            ids = [wid for c in scores for wid in c.walk_ids]
            tracks, states = slam.tracks(ids)
            for c in scores:
                c.incremental = _corrected_errors(c, tracks, states)[0]
            # ... then the server's batch re-solves of every floor: the correction after the crowd. A
            # live server's next scheduled runs would follow in the minutes after the crowd, so the runs
            # are repeated while one lifts the coverage by at least FINAL_BATCH_MIN_GAIN, at most
            # FINAL_BATCHES times. (The server's kept SLAM state keeps its fixes' map between batches,
            # server/slam_child.py, but its floor vote reads each batch's crowd map, so a second run can
            # move walks between floors: site1, 79.6 -> 80.3 -> 80.3 %.)
            for _ in range(FINAL_BATCHES):
                run.final_batch_ok, run.final_batch = slam.batch(wait_timeout)
                cov = (slam.summary() or {}).get("coverage")
                covs = run.final_coverages
                covs.append(float("nan") if cov is None else float(cov))
                if not run.final_batch_ok or (len(covs) >= 2 and not covs[-1] - covs[-2] >= FINAL_BATCH_MIN_GAIN):
                    break
            tracks, states = slam.tracks(ids)
            for c in scores:
                c.corrected, c.slam_status = _corrected_errors(c, tracks, states)
        run.summary = slam.summary()
        if run.grow_map:
            grown = server.grown_walks.get(plan.site, set())
            run.walks_grown = len(grown)
            for c in scores:
                c.map_grown = any(str(w) in grown for w in c.walk_ids)
        loc = server.locators.get(plan.site)
        run.map_version_final = loc[0] if loc else None
        secs["correction"] = time.monotonic() - t3
    finally:
        server.stop()
    scores.sort(key=lambda c: c.order)
    if baseline and run.map_version_survey is not None:
        t4 = time.monotonic()
        say(f"[eval crowd] survey-only baseline: {len(scores)} clients replayed offline with the survey map and with the maps served")
        survey_baseline(run, f"sqlite:///{db}")
        secs["baseline"] = time.monotonic() - t4
    secs["total"] = time.monotonic() - t0
    write_clients(run, out / "clients.jsonl")
    return run


def _score_live(rep: _Replayed, order: int, walk_ids: tuple[int, ...], version: int | None) -> ClientScore:
    r = rep.result
    wp = rep.waypoints
    wp_xy = np.asarray(wp.pos_enu, float).reshape(-1, 2)
    live_xy = live_positions(r.poses, wp.t)
    return ClientScore(
        rep.walk,
        order,
        np.asarray(wp.t, float),
        wp_xy,
        np.linalg.norm(live_xy - wp_xy, axis=1),
        walk_ids=walk_ids,
        map_version=version,
        fixes_received=r.fixes_received,
        fixes_accepted=r.fixes_accepted,
        unacked=max(r.batches - r.acked, 0),
        wall=rep.wall,
        tracks_received=r.tracks_received,
        tracks_applied=r.tracks_applied,
        live_xy=live_xy,
    )


# ------------------------------------------------------------------------- the survey-only baseline
#: a worker's kNN locators: role ("survey", "served") -> ((database, site, map version), locator). One map
#: per role is held: the clients come in time order, so the versions they were served come in order too
_BASE_LOCATORS: dict[str, tuple] = {}


def _baseline_locator(db_url: str, site: str, version: int, role: str):
    """The server's locator (:func:`hybridloc.server.locate_pool.make_locator`, kNN) of one stored map
    version, read from the run's database; None when the version is not stored."""
    from .radio.radiomap import RadioMap
    from .server.locate_pool import make_locator
    from .server.store import Store

    key = (db_url, site, version)
    for held in _BASE_LOCATORS.values():
        if held[0] == key:
            _BASE_LOCATORS[role] = held
            return held[1]
    store = Store(db_url, migrate=False)
    try:
        data = store.map_version(site, version)
    finally:
        store.close()
    _BASE_LOCATORS[role] = (key, None if data is None else make_locator(RadioMap.load(io.BytesIO(data)), "knn"))
    return _BASE_LOCATORS[role][1]


def replay_offline(path: str | Path, wp_t, wp_xy, axes: dict, locators: list) -> list[np.ndarray]:
    """One phone recording replayed offline, once per locator of ``locators``: the phone PDR the client
    runs (:class:`~hybridloc.pdr.phone.PhonePdr`, default settings), a fix for every WiFi scan from the
    locator (the server's answer; None: no fixes), the client's Kalman filter
    (:class:`~hybridloc.fusion.LocalFusion` with the floors' corridor ``axes``) with each fix at its scan's
    time, as the lock-step replay delivers it; the causal error at every waypoint (:func:`live_errors`,
    NaN before the first fix)."""
    from .fusion import LocalFusion, run_fusion
    from .io.msft import read_ilc_trace
    from .pdr.phone import PhonePdr
    from .server.locate_pool import answers
    from .types import RfScan, Technology

    tr = read_ilc_trace(Path(path))
    imu = tr.imu
    nan = np.full(len(wp_t), np.nan)
    if imu is None or len(imu.t) < 2:
        return [nan.copy() for _ in locators]
    steps = PhonePdr(imu.rate_hz).process(imu)  # the samples in order, as replay_phone feeds them
    # the readings and ages the phone client sends (replay_phone)
    scans = [RfScan(sc.t, Technology.WIFI, sc.rssi_dbm, age_s=sc.age_s) for sc in tr.scans if sc.technology is Technology.WIFI]
    out = []
    for loc in locators:
        if loc is None or not steps:
            out.append(nan.copy())
            continue
        fixes = [f.fix for f in answers(loc, scans) if f.fix is not None] if scans else []
        est = run_fusion(LocalFusion(corridor_axes=axes), steps, fixes)
        out.append(live_errors([(e.t, float(e.pos[0]), float(e.pos[1]), e.floor) for e in est], wp_t, wp_xy))
    return out


def _baseline_client(job: tuple) -> tuple[np.ndarray, np.ndarray]:
    db_url, site, survey_v, served_v, path, wp_t, wp_xy, axes = job
    survey = _baseline_locator(db_url, site, survey_v, "survey")
    served = _baseline_locator(db_url, site, served_v, "served") if served_v is not None else None
    a, b = replay_offline(path, wp_t, wp_xy, axes, [survey, served])
    return a, b


def survey_baseline(run: CrowdRun, db_url: str, processes: int | None = None) -> None:
    """The plain method beside the crowd (``eval crowd`` prints both): every client of ``run`` replayed
    offline (:func:`replay_offline`) with fixes from the survey map only (version
    ``run.map_version_survey``: what the clients would get with no crowd SLAM), and with the map version
    the server served it when it started (the check that the offline replay is the live one: their
    per-third means agree with the live run's within a few tenths of a metre on site1). Fills each
    client's ``survey_only`` and ``replayed``; the clients spread over ``processes`` (default: the usable
    cores; each worker holds two maps)."""
    import multiprocessing as mp

    from .pools import process_pool
    from .server.slam_batch import usable_cores

    C = run.clients
    if not C or run.map_version_survey is None:
        return
    jobs = [(db_url, run.plan.site, run.map_version_survey, c.map_version, str(c.walk.path), c.wp_t, c.wp_xy, run.axes) for c in C]
    n = max(1, min(processes or usable_cores(), len(C)))
    if n == 1:
        res = [_baseline_client(j) for j in jobs]
        _BASE_LOCATORS.clear()
    else:
        with process_pool(n, mp.get_context("spawn")) as ex:
            res = list(ex.map(_baseline_client, jobs, chunksize=max(1, len(jobs) // (4 * n))))
    for c, (a, b) in zip(C, res):
        c.survey_only, c.replayed = a, b
    run.baseline = True


def _num(v) -> float | None:
    v = float(v)
    return round(v, 3) if math.isfinite(v) else None


def write_clients(run: CrowdRun, path: str | Path) -> Path:
    """``OUT/clients.jsonl``: one JSON object per client in time order, what the report sums up, per
    waypoint: the truth (t, x, y), the live position the phone showed then and its error, the corrected
    track's error after the final batches and before them (``null`` where unscored). Where a mean
    hides its outliers, this file names them (which client, which third, which map version)."""
    path = Path(path)
    cuts = thirds(len(run.clients))
    third = {int(i): k for k, part in enumerate(cuts) for i in part}
    with path.open("w") as f:
        for i, c in enumerate(run.clients):
            nan = np.full(c.waypoints, np.nan)
            lx = c.live_xy if c.live_xy is not None else np.full((c.waypoints, 2), np.nan)
            cor = c.corrected if c.corrected is not None else nan
            inc = c.incremental if c.incremental is not None else nan
            so = c.survey_only if c.survey_only is not None else nan
            rp = c.replayed if c.replayed is not None else nan
            rec = {
                "order": c.order,
                "third": ("first", "middle", "last")[third.get(i, 0)],
                "device": c.walk.device,
                "recording": c.walk.path.name,
                "floor": c.walk.floor,
                "walk_ids": list(c.walk_ids),
                "slam_status": c.slam_status,
                "map_grown": c.map_grown,
                "map_version": c.map_version,
                "fixes_received": c.fixes_received,
                "fixes_accepted": c.fixes_accepted,
                "tracks_received": c.tracks_received,
                "tracks_applied": c.tracks_applied,
                "waypoints": [
                    {
                        "t": float(c.wp_t[k]) if math.isfinite(c.wp_t[k]) else None,
                        "x": _num(c.wp_xy[k, 0]),
                        "y": _num(c.wp_xy[k, 1]),
                        "live_x": _num(lx[k, 0]),
                        "live_y": _num(lx[k, 1]),
                        "live_m": _num(c.live[k]),
                        "corrected_m": _num(cor[k]),
                        "incremental_m": _num(inc[k]),
                        "survey_only_m": _num(so[k]),
                        "replayed_m": _num(rp[k]),
                    }
                    for k in range(c.waypoints)
                ],
            }
            f.write(json.dumps(rec) + "\n")
    return path


def usable_track(track, state) -> bool:
    """Whether a walk's stored track is a position to score: its walk corrected (not quarantined or
    failed) and the track absolute (a relative track is a shape in its own frame)."""
    return track is not None and state is not None and state.status == "corrected" and track.anchored != "relative"


def _corrected_errors(c: ClientScore, tracks: dict, states: dict) -> tuple[np.ndarray, str]:
    """(errors of the client's corrected track(s) at its waypoints, its walk's SLAM status). Only the
    absolute tracks of corrected walks are positions: a relative track is a shape in its own frame, a
    quarantined one is kept out of the map; their waypoints are NaN."""
    st = sorted({states[w].status for w in c.walk_ids if w in states})
    usable = [tracks[w] for w in c.walk_ids if usable_track(tracks.get(w), states.get(w))]
    return (track_errors(usable, c.wp_t, c.wp_xy) if usable else np.full(c.waypoints, np.nan)), ",".join(st)


# ------------------------------------------------------------------------------------------- report
def _baseline_figures(run: CrowdRun, parts: list[np.ndarray]) -> dict | None:
    """Per third: the survey-only and replayed means (each on its own scored waypoints), the survey-only
    learning, and the served maps' gain over the survey map on the waypoints both scored."""
    C = run.clients
    if not run.baseline or not C:
        return None

    def gain(a: np.ndarray, b: np.ndarray) -> float:
        both = np.isfinite(a) & np.isfinite(b)
        return _gain(float(b[both].mean()), float(a[both].mean())) if both.any() else float("nan")

    with_both = [c for c in C if c.survey_only is not None and c.replayed is not None]
    sv, rp, g = [], [], []
    for part in parts:
        mine = [C[i] for i in part if C[i].survey_only is not None and C[i].replayed is not None]
        a, b = _cat(c.survey_only for c in mine), _cat(c.replayed for c in mine)
        sv.append(_stats(a)["mean"])
        rp.append(_stats(b)["mean"])
        g.append(gain(a, b))
    return {
        "survey_only": sv,
        "replayed": rp,
        "gain": g,
        "gain_all": gain(_cat(c.survey_only for c in with_both), _cat(c.replayed for c in with_both)),
        "survey_only_learning": _gain(sv[2], sv[0]) if len(sv) == 3 else float("nan"),
    }


def crowd_report(run: CrowdRun, out=None) -> dict:
    """Print the report of a run and return the headline figures (the JSON line)."""
    out = out if out is not None else sys.stdout
    plan, C = run.plan, run.clients

    def p(*a) -> None:
        print(*a, file=out)

    n_by = lambda ws: ", ".join(f"{f} {sum(w.floor == f for w in ws)}" for f in plan.floors)  # noqa: E731
    p(
        f"crowd evaluation of site {plan.site} ({', '.join(plan.floors)}): a real server (Zenoh on loopback, SQLite), crowd SLAM {'on' if run.slam_on else 'off'}"
        + (", the served map grown at every added walk (--grow-map)" if run.grow_map else "")
    )
    p(
        f"  survey walks (with their marks, before the crowd): {len(plan.surveys)} ({n_by(plan.surveys)}); {run.survey_labels} labelled scans -> radio map version {run.map_version_survey}"
    )
    p(f"  clients (no marks, in time order, {run.concurrency} at a time, lock-step): {len(C)} ({n_by([c.walk for c in C])})")
    if run.skipped:
        p(
            f"  skipped walks: {len(run.skipped)} ("
            + "; ".join(f"{w.path.name}: {why}" for w, why in run.skipped[:5])
            + (" ..." if len(run.skipped) > 5 else "")
            + ")"
        )
    n_wp = sum(c.waypoints for c in C)
    n_un = sum(c.unscored for c in C)
    p(f"  waypoints of the clients: {n_wp}; unscored (before the client's first fix): {n_un} ({100 * n_un / n_wp if n_wp else float('nan'):.1f} %)")
    if run.close_errors:
        p(f"  client sessions whose close failed (their walks count): {run.close_errors}")
    unacked = sum(c.unacked > 0 for c in C)
    if unacked:
        p(f"  clients with batches the server had not acknowledged at the end: {unacked}")
    parts = thirds(len(C))
    names = ("first", "middle", "last")
    live3 = [_stats(_cat(C[i].live for i in part)) for part in parts]
    corr3 = [_stats(_cat(C[i].corrected for i in part if C[i].corrected is not None)) for part in parts]
    p("  learning curve (clients in time order, by thirds; causal live error at waypoints / corrected track at waypoints):")
    for name, part, lv, co in zip(names, parts, live3, corr3):
        if not len(part):
            continue
        vers = sorted({C[i].map_version for i in part if C[i].map_version is not None})
        vtxt = f"map v{vers[0]}" + (f"-v{vers[-1]}" if len(vers) > 1 else "") if vers else "no map"
        ctxt = f"; corrected mean {co['mean']:.2f} m, median {co['median']:.2f} (n={co['n']})" if run.slam_on else ""
        p(
            f"    {name:<6} third: {len(part):3d} clients ({vtxt}); live mean {lv['mean']:.2f} m, median {lv['median']:.2f}, p90 {lv['p90']:.2f} (n={lv['n']}){ctxt}"
        )
    live_all = _stats(_cat(c.live for c in C))
    corr_all = _stats(_cat(c.corrected for c in C if c.corrected is not None))
    # live against corrected on the same waypoints of the same clients (both scored there)
    pairs = [(c.live, c.corrected) for c in C if c.corrected is not None]
    L = _cat(a for a, _ in pairs)
    K = _cat(b for _, b in pairs)
    both = np.isfinite(L) & np.isfinite(K)
    live_same, corr_same = _stats(L[both]), _stats(K[both])
    n_corr = sum(c.corrected is not None and bool(np.isfinite(c.corrected).any()) for c in C)
    p(f"  live, all clients: mean {live_all['mean']:.2f} m, median {live_all['median']:.2f}, p90 {live_all['p90']:.2f} (n={live_all['n']})")
    if run.slam_on:
        by_status: dict[str, int] = {}
        for c in C:
            by_status[c.slam_status or "none"] = by_status.get(c.slam_status or "none", 0) + 1
        p(
            f"  corrected after the server's correction: {n_corr} of {len(C)} clients with an absolute track "
            f"({', '.join(f'{k} {v}' for k, v in sorted(by_status.items()))}); mean {corr_all['mean']:.2f} m, median {corr_all['median']:.2f} (n={corr_all['n']})"
        )
        p(
            f"  live vs corrected on the same {live_same['n']} waypoints: live mean {live_same['mean']:.2f} m (median {live_same['median']:.2f}), "
            f"corrected mean {corr_same['mean']:.2f} m (median {corr_same['median']:.2f})"
        )
        inc = _cat(c.incremental for c in C if c.incremental is not None and c.corrected is not None)
        inc_same = _stats(inc[both & np.isfinite(inc)] if inc.size == both.size else np.zeros(0))
        p(
            f"  (corrected = after the server's final batch re-solves of every floor ({run.final_batches}, coverage after each "
            f"{', '.join(f'{100 * c:.1f} %' for c in run.final_coverages) or '-'}): {run.final_batch}; before them, the walks as added "
            f"one by one and the crowd's own batch runs: mean {_stats(inc)['mean']:.2f} m (n={_stats(inc)['n']}), on the same waypoints {inc_same['mean']:.2f} m)"
        )
        if run.final_wait_ok is False:
            p("  WARNING: the server had not processed every finished walk within the timeout; the corrected figures are of what it had")
        p(
            f"  corrected tracks the clients heard while walking: {sum(c.tracks_received for c in C)}, re-anchored their filter: "
            f"{sum(c.tracks_applied for c in C)} (the live figures above include them)"
        )
        if run.grow_map:
            p(f"  served map grown at every added walk (--grow-map): {run.walks_grown} walks' labels served on top of the map versions")
    else:
        p("  corrected: undefined (the server runs no crowd SLAM)")
    sm = run.summary or {}
    cov = sm.get("coverage")
    p(
        f"  server: coverage {'-' if cov is None else f'{100 * cov:.1f} %'} of the unmarked walks' scans, walks corrected {sm.get('walks_corrected', '-')}, "
        f"relative {sm.get('walks_relative', '-')}, quarantined {sm.get('walks_quarantined', '-')}, pending {sm.get('walks_pending', '-')}, "
        f"loops accepted {sm.get('loops_accepted', '-')} / rejected {sm.get('loops_rejected', '-')}; map version {run.map_version_survey} -> {run.map_version_final}"
    )
    s = run.seconds
    p(
        f"  time: surveys {s.get('surveys', 0):.0f} s, clients {s.get('clients', 0):.0f} s (of which waiting for the server's SLAM {s.get('waiting_for_slam', 0):.0f} s; "
        f"{run.pace_waits} waits, {run.pace_timeouts} timed out), correction {s.get('correction', 0):.0f} s, total {s.get('total', 0):.0f} s"
    )
    learning = _gain(live3[2]["mean"], live3[0]["mean"])
    correction = _gain(corr_same["mean"], live_same["mean"])

    def gain_txt(v) -> str:
        if v is None or not math.isfinite(v):
            return "undefined"
        return f"{100 * v:.0f} % below" if v >= 0 else f"{-100 * v:.0f} % ABOVE"

    base = _baseline_figures(run, parts)
    if base:
        sv, rp = base["survey_only"], base["replayed"]
        p(
            f"  survey-only baseline (the plain method: each client replayed offline with the same PDR and filter, fixes from the survey map "
            f"v{run.map_version_survey} only): first third {sv[0]:.2f} m, middle {sv[1]:.2f}, last {sv[2]:.2f}: the last third "
            f"{gain_txt(base['survey_only_learning'])} the first with no crowd at all (what the thirds' own floors and routes make of the learning figure)"
        )
        p(
            f"    the same replay with the maps the server served: {rp[0]:.2f} / {rp[1]:.2f} / {rp[2]:.2f} m "
            f"(the live run: {live3[0]['mean']:.2f} / {live3[1]['mean']:.2f} / {live3[2]['mean']:.2f} m)"
        )
        g = base["gain"]
        p(
            f"    the maps served against the survey map on the same waypoints: first third {gain_txt(g[0])}, middle {gain_txt(g[1])}, "
            f"last {gain_txt(g[2])}; all clients {gain_txt(base['gain_all'])}"
        )

    cov_txt = "undefined" if cov is None else f"{100 * cov:.0f} %"
    p(
        f"  goals: last third's live mean {gain_txt(learning)} the first third's (goal >= {100 * GOALS['learning_gain']:.0f} % below); "
        f"corrected {gain_txt(correction)} live on the same waypoints (goal >= {100 * GOALS['correction_gain']:.0f} % below); "
        f"coverage {cov_txt} (goal >= {100 * GOALS['coverage']:.0f} %)"
    )
    nan = float("nan")
    head = {
        "live_mean_m": live_all["mean"],
        "live_median_m": live_all["median"],
        "live_mean_first_third_m": live3[0]["mean"],
        "live_mean_middle_third_m": live3[1]["mean"],
        "live_mean_last_third_m": live3[2]["mean"],
        "corrected_mean_m": corr_all["mean"] if run.slam_on else nan,
        "corrected_median_m": corr_all["median"] if run.slam_on else nan,
        "corrected_mean_first_third_m": corr3[0]["mean"] if run.slam_on else nan,
        "corrected_mean_middle_third_m": corr3[1]["mean"] if run.slam_on else nan,
        "corrected_mean_last_third_m": corr3[2]["mean"] if run.slam_on else nan,
        "corrected_incremental_mean_m": _stats(_cat(c.incremental for c in C if c.incremental is not None))["mean"] if run.slam_on else nan,
        "live_mean_same_waypoints_m": live_same["mean"] if run.slam_on else nan,
        "corrected_mean_same_waypoints_m": corr_same["mean"] if run.slam_on else nan,
        "learning_gain": learning,
        "survey_only_mean_first_third_m": base["survey_only"][0] if base else nan,
        "survey_only_mean_middle_third_m": base["survey_only"][1] if base else nan,
        "survey_only_mean_last_third_m": base["survey_only"][2] if base else nan,
        "survey_only_learning_gain": base["survey_only_learning"] if base else nan,
        "replayed_mean_first_third_m": base["replayed"][0] if base else nan,
        "replayed_mean_last_third_m": base["replayed"][2] if base else nan,
        "crowd_map_gain": base["gain_all"] if base else nan,
        "crowd_map_gain_first_third": base["gain"][0] if base else nan,
        "crowd_map_gain_last_third": base["gain"][2] if base else nan,
        "correction_gain": correction if run.slam_on else nan,
        "coverage": cov if cov is not None else nan,
        "walks_quarantined": sm.get("walks_quarantined"),
        "walks_corrected": sm.get("walks_corrected"),
        "walks_pending": sm.get("walks_pending"),
        "walks_relative": sm.get("walks_relative"),
        "final_batch_complete": run.final_batch_ok,
        "final_batches": run.final_batches,
        "coverage_first_batch": run.final_coverages[0] if run.final_coverages else None,
        "loops_accepted": sm.get("loops_accepted"),
        "clients": len(C),
        "tracks_received": sum(c.tracks_received for c in C),
        "tracks_applied": sum(c.tracks_applied for c in C),
        "clients_corrected": n_corr if run.slam_on else None,
        "survey_walks": len(plan.surveys),
        "skipped_walks": len(run.skipped),
        "waypoints": n_wp,
        "unscored_waypoints": n_un,
        "map_version_survey": run.map_version_survey,
        "map_version_final": run.map_version_final,
        "map_versions": len({c.map_version for c in C if c.map_version is not None}),
        "survey_fraction": None,  # filled by the caller (the options)
        "seed": None,
        "concurrency": run.concurrency,
        "slam_processes": _slam_processes() if run.slam_on else None,
        "grow_map": run.grow_map,
        "walks_grown": run.walks_grown,
        "session_close_errors": run.close_errors,
        "seconds_surveys": s.get("surveys"),
        "seconds_clients": s.get("clients"),
        "seconds_waiting_for_slam": s.get("waiting_for_slam"),
        "seconds_correction": s.get("correction"),
        "seconds_baseline": s.get("baseline"),
        "seconds": s.get("total"),
    }
    return head


def run_crowd_eval(
    site_dir: str | Path,
    survey_fraction: float = 0.1,
    seed: int = 0,
    floors: list[str] | None = None,
    out: str | Path = "out/eval-crowd",
    concurrency: int = 3,
    speed: float = 0.0,
    wait_timeout: float = 600.0,
    slam: bool = True,
    grow_map: bool = False,
) -> dict:
    """``hybridloc eval crowd``: run (:func:`run_crowd`), print the report, return the JSON line's figures."""
    run = run_crowd(site_dir, survey_fraction, seed, floors, out, concurrency, speed, wait_timeout, slam=slam, grow_map=grow_map)
    head = crowd_report(run)
    print(f"  per client and waypoint (live and corrected errors, live positions): {Path(out) / 'clients.jsonl'}")
    head.update(survey_fraction=survey_fraction, seed=seed)
    return head


__all__ = [
    "GOALS",
    "ClientScore",
    "CrowdPlan",
    "CrowdRun",
    "CrowdWalk",
    "crowd_report",
    "live_errors",
    "live_positions",
    "plan_crowd",
    "run_crowd",
    "run_crowd_eval",
    "thirds",
    "track_errors",
    "write_clients",
]

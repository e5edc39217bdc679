"""Client agents: a phone, a foot-mounted IMU or a surveying operator, talking to the server over Zenoh.

An agent runs its PDR locally, batches steps (and scans, and survey marks for a surveyor) into the
reliable :class:`~.uplink.Uplink` (disk spool, acknowledgements, resend), receives the fixes the
server pushes, fuses them with its steps (:class:`hybridloc.fusion.LocalFusion`) and writes its live
pose - one row per step or fix, each the estimate available at that moment - as CSV
(``t,x,y,floor,sigma_x,sigma_y``), JSON lines or NMEA-0183, and publishes it on its ``pose`` key.
When the server is down it keeps dead reckoning; the spool catches up after.

The crowd SLAM talks back (docs/protocol.md): the agent subscribes to its own ``track`` key and to its
site's ``map/version``. A corrected track of its current walk re-anchors the filter
(``fusion.reanchor``: the filter's estimate at the track's latest time is replaced by the smoothed one,
the steps since are re-applied, heading bias and step scale taken where the filter holds them), so the
live pose improves after every correction; a new map version is fetched (a get on ``map``, never
waiting in a Zenoh callback) when the agent was given a ``map_refresh`` hook. Callbacks only queue
bytes; everything is decoded and applied on the agent's thread, in :meth:`Agent.drain_fixes`.

Replay (``--replay FILE --speed K``) feeds a recording at K times real time: the agent sleeps so that
recording time t is reached at wall time (t - t0) / K.
"""

from __future__ import annotations

import json
import math
import queue
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh

from hybridloc.fusion import Estimate, GpsDifferencer, LocalFusion
from hybridloc.geo import GeodeticOrigin
from hybridloc.io.writers import gga_sentence
from hybridloc.pdr.phone import PhonePdr, PhonePdrConfig
from hybridloc.types import RSSI_MAX_DBM, RSSI_MIN_DBM, AbsoluteFix, DisplacementFix, Pose, RfScan, StepEvent, SurveyMark, Technology, rssi_in_range
from hybridloc.units import DEG
from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import MapInfo, MapVersion, Track

from .uplink import Uplink

#: An agent's batches of at least this many steps go with their steps in the columnar form (Uplink's
#: ``step_columns_from``): a long batch period or a backlog (a bulk upload of a recording), never the
#: live batch of a second's steps, whose bytes stay today's
STEP_COLUMNS_FROM = 256


def open_client(endpoint: str, security=None, log=None) -> zenoh.Session:
    """A client-mode Zenoh session to a server endpoint (scouting off; see hybridloc.wire.zconfig).

    A client-mode session cannot open while nothing listens at the endpoint; an agent must still
    work then (dead reckoning, spooling), so it falls back to a peer-mode session that keeps trying
    the endpoint and connects when the server appears (its spool is resent then).
    """
    from hybridloc.wire.zconfig import client_config, zenoh_reason

    try:
        return zenoh.open(client_config(endpoint, security))
    except zenoh.ZError as exc:
        if log:
            log(f"server at {endpoint} unreachable ({zenoh_reason(exc, 120, security)}): working offline, connecting when it appears")
        conf = client_config(endpoint, security)
        conf.insert_json5("mode", '"peer"')
        return zenoh.open(conf)


class PoseWriter:
    """Live pose output: CSV (``t,x,y,floor,sigma_x,sigma_y``), JSON lines, or NMEA GGA (needs an origin)."""

    def __init__(self, path: str | Path | None, fmt: str | None = None, origin: GeodeticOrigin | None = None):
        self.path = Path(path) if path else None
        self.fmt = fmt or (
            ("jsonl" if self.path.suffix in (".jsonl", ".json") else "nmea" if self.path.suffix == ".nmea" else "csv") if self.path else "csv"
        )
        if self.fmt == "nmea" and origin is None:
            raise ValueError("NMEA output needs the site's geodetic origin")
        self.origin = origin
        self.rows: list[tuple] = []
        self._f = open(self.path, "w", encoding="utf-8", newline="") if self.path else None
        if self._f and self.fmt == "csv":
            self._f.write("t,x,y,floor,sigma_x,sigma_y,kind\n")

    def write(self, e: Estimate) -> None:
        sx, sy = math.sqrt(max(e.cov[0, 0], 0.0)), math.sqrt(max(e.cov[1, 1], 0.0))
        self.rows.append((e.t, float(e.pos[0]), float(e.pos[1]), e.floor, sx, sy, e.kind))
        if self._f is None:
            return
        if self.fmt == "csv":
            self._f.write(f"{e.t:.3f},{e.pos[0]:.3f},{e.pos[1]:.3f},{e.floor or ''},{sx:.3f},{sy:.3f},{e.kind}\n")
        elif self.fmt == "jsonl":
            self._f.write(
                json.dumps({"t": e.t, "x": float(e.pos[0]), "y": float(e.pos[1]), "floor": e.floor, "sigma_x": sx, "sigma_y": sy, "kind": e.kind})
                + "\n"
            )
        else:
            lat, lon, h = self.origin.enu_to_geodetic(np.array([e.pos[0], e.pos[1]]))
            self._f.write(gga_sentence(e.t, float(lat) / DEG, float(lon) / DEG, float(h), hdop=max(sx, sy) / 3.0) + "\r\n")
        self._f.flush()

    def close(self) -> None:
        if self._f:
            self._f.close()


@dataclass
class AgentResult:
    device: str
    steps: int
    fixes_received: int
    fixes_accepted: int
    batches: int
    acked: int
    poses: list = field(default_factory=list)
    step_events: list = field(default_factory=list)
    fix_lags: list = field(default_factory=list)  # recording-clock seconds from scan to fix use
    fix_log: list = field(default_factory=list)  # (steps processed when it arrived, AbsoluteFix), for fusion.run_fusion
    local_fixes: int = 0  # the device's own GPS / RFID fixes offered, accepted, and GPS displacements used
    local_accepted: int = 0
    displacements: int = 0
    # the crowd SLAM's corrected tracks: received (every payload), applied (re-anchored the filter),
    # ignored (well formed, not applicable; by reason in track_ignored), rejected (refused by the codec)
    tracks_received: int = 0
    tracks_applied: int = 0
    tracks_ignored: int = 0
    tracks_rejected: int = 0
    track_ignored: dict = field(default_factory=dict)  # reason -> count
    walk_id: int | None = None  # the server's id of this walk (from the first track taken)
    map_version: int | None = None  # the newest map version announced (or held at the start)
    maps_fetched: int = 0  # new map versions fetched and handed to the map-refresh hook
    spool_dropped: dict = field(default_factory=dict)  # what a full spool dropped (Uplink.dropped): batches, steps, scans, marks, unspooled
    fix_regions: list = field(default_factory=list)  # the 95 % ContainmentRegion the server sent with each fix of fix_log (None when not sent)

    @property
    def raw_fixes(self) -> list[tuple]:
        """(t, x, y, floor) of every server fix received, before fusion."""
        return [(f.t, float(f.pos_enu[0]), float(f.pos_enu[1]), f.floor) for _, f in self.fix_log]


class Agent:
    """A client's core: uplink, fix subscription, fusion, pose output, liveliness.

    Its drivers (:func:`replay_phone`, :func:`live_phone`, :func:`replay_foot`, or your own) use only
    this public API:

    * :meth:`add_step`, :meth:`add_scan`, :meth:`add_mark`: the device's records as they happen (a step
      is fused at once; scans and marks wait for the next batch);
    * :meth:`add_fix`: a fix from the device's own sensors (GPS, RFID), fused at once;
    * :meth:`tick` (recording time has reached t: send what is due, hear the server), :meth:`flush`
      (send everything now), :meth:`drain_fixes` (fuse the server's answers that arrived),
      :meth:`wait_answers` (lock-step);
    * :attr:`estimate` (the newest pose), :meth:`close` (-> :class:`AgentResult`).

    The server's corrected tracks and map versions arrive by themselves (subscriptions) and are applied
    in :meth:`drain_fixes`; ``map_refresh(payload, info)`` (optional) is called on the agent's thread
    with each new map version's file (npz bytes) and its :class:`~hybridloc.wire.messages.MapInfo`,
    e.g. :func:`walk_prior_refresh` for the particle filter; ``map_version`` is the version the agent
    holds at the start (None: none or unknown). ``step_columns_from``: batches of at least this many
    steps go in the columnar form (:data:`STEP_COLUMNS_FROM`; None: never), which servers before it refuse.
    """

    def __init__(
        self,
        session: zenoh.Session,
        site: str,
        device: str,
        spool: str | Path,
        pose: PoseWriter,
        device_model: str = "",
        batch_period: float = 1.0,
        init: tuple[float, float, float] | None = None,
        fusion=None,
        floor: str | None = None,
        map_refresh: Callable[[bytes, MapInfo | None], None] | None = None,
        map_version: int | None = None,
        map_timeout: float = 10.0,
        max_spool_bytes: int | None = None,
        step_columns_from: int | None = STEP_COLUMNS_FROM,
    ):
        self.session = session
        self.site, self.device = site, device
        self.uplink = Uplink(session, site, device, spool, device_model, max_spool_bytes=max_spool_bytes, step_columns_from=step_columns_from)
        # any filter with the predict/correct step API (hybridloc.fusion); by default LocalFusion, our Kalman filter
        self.fusion = fusion if fusion is not None else LocalFusion(init=init, floor=floor)
        self.pose = pose
        self.batch_period = batch_period
        self.fixes: queue.Queue = queue.Queue()
        self._fix_sub = session.declare_subscriber(P.key_fix(site, device), lambda s: self.fixes.put(s.payload.to_bytes()))
        # the crowd SLAM's messages: the callbacks only queue the bytes (decoded on the agent's thread);
        # remote origin only: the server announces, never this session
        self.inbox: queue.Queue = queue.Queue()
        remote = zenoh.Locality.REMOTE
        self._track_sub = session.declare_subscriber(
            P.key_track(site, device), lambda s: self.inbox.put(("track", s.payload.to_bytes())), allowed_origin=remote
        )
        self._version_sub = session.declare_subscriber(
            P.key_map_version(site), lambda s: self.inbox.put(("map-version", s.payload.to_bytes())), allowed_origin=remote
        )
        self._token = session.liveliness().declare_token(P.key_alive(site, device))
        self.map_refresh = map_refresh
        self.map_timeout = map_timeout
        self.map_version = map_version  # newest announced (or held at the start)
        self._map_applied = map_version  # newest handed to map_refresh
        self.maps_fetched = self.map_fetch_failed = self.map_refresh_failed = 0
        self.map_versions_rejected = 0
        self.walk_id: int | None = None  # the server's id of this walk, from the first track taken
        self._track_run = 0  # the newest SLAM run whose track was applied
        self.tracks_received = self.tracks_applied = 0
        self.track_ignored: Counter = Counter()  # reason -> count (well formed, not applied)
        self.track_rejected: Counter = Counter()  # codec reason -> count
        self._t_first = math.inf  # the first step or fix this agent took: its walk's start
        self.n_accepted = 0
        self.n_answers = 0  # server answers (fix or "no fix") received
        self.n_local = self.n_local_accepted = self.n_displacements = 0  # the device's own GPS / RFID fixes
        self._gps_diff = GpsDifferencer()
        self.n_asked = 0  # batches sent with a WiFi scan (each gets one answer)
        self._answers_flowing = True
        self._steps: list = []
        self._scans: list = []
        self._marks: list = []
        self._last_flush = -math.inf
        self._estimate: Pose | None = None
        self.all_steps: list = []
        self.fix_lags: list = []  # how late each fix was used: newest step time - scan time, s
        self.fix_log: list = []  # (steps processed when the fix arrived, fix)
        self.fix_regions: list = []  # the containment region sent with each fix of fix_log, or None

    # ------------------------------------------------------------ public API
    def add_step(self, step: StepEvent) -> None:
        """A step (or stride): fused at once, the new pose written and published, and queued for the next batch."""
        self._steps.append(step)
        self.all_steps.append(step)
        self._t_first = min(self._t_first, step.t)
        e = self.fusion.predict(step)
        if self.fusion.initialised:
            self._write(e)
            self.session.put(P.key_pose(self.site, self.device), C.POSE.encode(self._estimate), encoding=C.POSE.encoding)

    on_step = add_step  # the name drivers used before

    def add_scan(self, scan: RfScan) -> None:
        """A radio scan, sent with the next batch (the server answers the newest WiFi scan of each batch)."""
        self._scans.append(scan)

    def add_mark(self, mark: SurveyMark) -> None:
        """A survey mark ("I am here"), sent with the next batch."""
        self._marks.append(mark)

    @property
    def estimate(self) -> Pose | None:
        """The newest pose (after the latest step or accepted fix); None before the filter is initialised."""
        return self._estimate

    def flush(self, t: float) -> None:
        """Send everything queued now (recording time ``t``)."""
        self.maybe_flush(t, force=True)

    def _write(self, e) -> None:
        self.pose.write(e)
        self._estimate = Pose(e.t, float(e.pos[0]), float(e.pos[1]), e.floor, np.asarray(e.cov)[:2, :2])

    def drain_fixes(self) -> None:
        """Apply what the server sent: corrected tracks, map versions and fetched maps first, then fixes."""
        while True:
            try:
                kind, *item = self.inbox.get_nowait()
            except queue.Empty:
                break
            if kind == "track":
                self._handle_track(item[0])
            elif kind == "map-version":
                self._handle_map_version(item[0])
            elif kind == "map":
                self._handle_map(*item)
            elif kind == "map-failed":
                self.map_fetch_failed += 1
        while True:
            try:
                raw = self.fixes.get_nowait()
            except queue.Empty:
                return
            self._handle(raw)

    # ------------------------------------------------------------ the crowd SLAM's messages
    def _ignore_track(self, reason: str) -> None:
        self.track_ignored[reason] += 1

    def _handle_track(self, raw: bytes) -> None:
        """A corrected track: re-anchor the filter from its latest point when it is this walk's and new.

        The agent learns its walk's id from the server's tracks only: the first one taken after the agent
        started is its walk (a track ending before the agent's first step or fix is an earlier walk's);
        later tracks apply when they name that walk and come from a newer SLAM run.
        """
        self.tracks_received += 1
        try:
            msg: Track = C.TRACK.decode(raw, self.site, self.device)
        except P.Rejected as exc:
            self.track_rejected[exc.reason] += 1
            return
        tr = msg.track
        if len(tr) == 0:
            return self._ignore_track("empty")
        if tr.anchored == "relative":  # a shape in its own frame, never a position (types.TRACK_ANCHORS)
            return self._ignore_track("relative")
        if not tr.t[-1] >= self._t_first:  # ends before this agent's walk began (or nothing began yet)
            return self._ignore_track("before-start")
        if self.walk_id is not None and msg.walk_id != self.walk_id:
            return self._ignore_track("other-walk")
        if msg.run <= self._track_run:
            return self._ignore_track("old-run")
        reanchor = getattr(self.fusion, "reanchor", None)
        if reanchor is None:
            return self._ignore_track("filter-cannot-reanchor")
        try:
            e = reanchor(float(tr.t[-1]), tr.pos_enu[-1], tr.cov[-1], tr.floor[-1] or None, heading_bias=tr.heading_bias, scale=tr.scale)
        except ValueError:  # older than the steps the filter keeps, or a cold particle cloud without a covariance
            return self._ignore_track("too-old")
        self.walk_id = msg.walk_id
        self._track_run = msg.run
        self.tracks_applied += 1
        self._write(e)

    def _handle_map_version(self, raw: bytes) -> None:
        """A new map version: recorded, and fetched (a get on ``map`` with a timeout, its replies queued by
        the get's callback) when the agent has a map-refresh hook."""
        try:
            mv: MapVersion = C.MAP_VERSION.decode(raw)
        except P.Rejected:
            self.map_versions_rejected += 1
            return
        if mv.site != self.site or (self.map_version is not None and mv.version <= self.map_version):
            return
        self.map_version = mv.version
        if self.map_refresh is None:
            return
        got = []

        def on_reply(r) -> None:  # a Zenoh thread: only queue
            if r.ok is not None:
                att = r.ok.attachment
                got.append(True)
                self.inbox.put(("map", r.ok.payload.to_bytes(), att.to_bytes() if att is not None else None, mv.version))

        def on_done() -> None:  # the get is over (all replies, or the timeout)
            if not got:
                self.inbox.put(("map-failed",))

        self.session.get(P.key_map(self.site), zenoh.handlers.Callback(on_reply, on_done), timeout=self.map_timeout)

    def _handle_map(self, payload: bytes, attachment: bytes | None, announced: int) -> None:
        """A fetched map: handed to the hook once per version (its attachment's; the announced one if none)."""
        info = None
        if attachment is not None:
            try:
                info = C.MAP_INFO.decode(attachment)
            except P.Rejected:
                info = None
        version = info.version if info is not None else announced
        if self._map_applied is not None and version <= self._map_applied:
            return
        if self.map_refresh is None:
            return
        try:
            self.map_refresh(payload, info)
        except Exception:  # noqa: BLE001 - a map the hook cannot use (corrupt file ...) never stops the agent
            self.map_refresh_failed += 1
            return
        self._map_applied = version
        self.maps_fetched += 1

    def _handle(self, raw: bytes) -> None:
        """One server answer: a fix is fused; "no fix" is only counted."""
        try:
            answer = C.FIX.decode(raw)
        except P.Rejected:
            return
        fix = answer.fix
        self.n_answers += 1
        self._answers_flowing = True
        if fix is None:
            return
        self._t_first = min(self._t_first, fix.t)
        self.fix_lags.append(max(self.fusion.t - fix.t, 0.0) if math.isfinite(self.fusion.t) else 0.0)
        self.fix_log.append((len(self.all_steps), fix))
        self.fix_regions.append(answer.region)
        # a filter that starts inside the server's containment region takes the whole answer (the
        # particle filter: :meth:`hybridloc.fusion.ParticleFusion.correct`); the others the fix
        ok, e = self.fusion.correct(answer if getattr(self.fusion, "takes_regions", False) else fix)
        if ok:
            self.n_accepted += 1
            self._write(e)

    def add_fix(self, fix: AbsoluteFix, sigma_random: float | None = None) -> bool:
        """A fix from the device's own sensors (GPS receiver, an RFID reader's detection): fused at once;
        pairs of accepted GPS fixes a few seconds apart also give a displacement (Kourogi's GPS
        differential mode, :class:`hybridloc.fusion.GpsDifferencer`)."""
        self.n_local += 1
        self._t_first = min(self._t_first, fix.t)
        ok, e = self.fusion.correct(fix)
        if ok:
            self.n_local_accepted += 1
            self._write(e)
        disp: DisplacementFix | None = self._gps_diff.push(fix, sigma_random, ok)
        if disp is not None:
            ok_d, e = self.fusion.correct(disp)
            if ok_d:
                self.n_displacements += 1
                self._write(e)
        return ok

    local_fix = add_fix  # the name drivers used before

    def end_walk(self, t: float) -> None:
        """The walk ends (its replay or live input ended): send what is queued, the last batch marked
        ``end_of_walk`` (an empty marker batch when nothing is queued), so the server closes the walk now."""
        self.maybe_flush(t, force=True, end_of_walk=True)

    def maybe_flush(self, t: float, force: bool = False, end_of_walk: bool = False) -> None:
        """Send what is queued when a batch period has passed since the last batch (``force``: now);
        ``end_of_walk`` marks the last batch sent (see :meth:`end_walk`)."""
        if not force and t - self._last_flush < self.batch_period:
            return
        # keep batches under the protocol size limit: scans are the big items
        marked = False
        while self._steps or self._scans or self._marks:
            scans, self._scans = self._scans[:8], self._scans[8:]
            steps, self._steps = self._steps, []
            marks, self._marks = self._marks, []
            last = not (self._steps or self._scans or self._marks)
            self.uplink.send(steps=steps, scans=scans, marks=marks, end_of_walk=end_of_walk and last)
            marked = marked or (end_of_walk and last)
            self.n_asked += any(sc.technology is Technology.WIFI for sc in scans)
        if end_of_walk and not marked:
            self.uplink.send(end_of_walk=True)
        self._last_flush = t

    def tick(self, t: float, lockstep: bool = False) -> None:
        """Recording time has reached t: send what is due, hear the server (in lock-step: wait for it)."""
        self.maybe_flush(t)
        if lockstep:
            self.wait_answers()
        self.drain_fixes()

    def wait_answers(self, timeout: float = 2.0) -> bool:
        """Lock-step replay: block until the server has answered every scan sent, fusing the fixes.

        Replaying K times faster than real time multiplies every wall-clock delay by K on the
        recording's clock; waiting here makes the fixes reach the filter as they would live (network
        and server latency a small fraction of a step). If the server stays silent for ``timeout`` the
        agent stops waiting (dead reckoning on) until answers flow again.
        """
        deadline = time.monotonic() + timeout
        while True:
            self.drain_fixes()
            if self.n_answers >= self.n_asked:
                return True
            if not self._answers_flowing or time.monotonic() >= deadline:
                self._answers_flowing = False
                return False
            try:
                self._handle(self.fixes.get(timeout=min(0.05, max(deadline - time.monotonic(), 0.001))))
            except queue.Empty:
                pass

    def close(self, wait: float = 10.0) -> AgentResult:
        self.uplink.wait_acked(timeout=wait)
        self.drain_fixes()
        for e in (self._fix_sub, self._track_sub, self._version_sub, self._token):
            try:
                e.undeclare()
            except Exception:  # noqa: BLE001
                pass
        self.uplink.close()
        self.pose.close()
        return AgentResult(
            self.device,
            len(self.all_steps),
            len(self.fix_log),
            self.n_accepted,
            self.uplink.next_seq - 1,
            self.uplink.acked,
            list(self.pose.rows),
            list(self.all_steps),
            list(self.fix_lags),
            list(self.fix_log),
            self.n_local,
            self.n_local_accepted,
            self.n_displacements,
            self.tracks_received,
            self.tracks_applied,
            sum(self.track_ignored.values()),
            sum(self.track_rejected.values()),
            dict(self.track_ignored),
            self.walk_id,
            self.map_version,
            self.maps_fetched,
            dict(self.uplink.dropped),
            list(self.fix_regions),
        )


def fetch_walk_prior(session: zenoh.Session, site: str, plan=None, timeout: float = 10.0):
    """The site's radio map from the server (``map`` queryable) turned into a walk prior for
    :class:`hybridloc.fusion.ParticleFusion`; None when the server has no map for the site."""
    got = fetch_map(session, site, timeout)
    return walk_prior(got[0], plan) if got is not None else None


def walk_prior(payload: bytes, plan=None):
    """The walk prior of a radio map file (npz bytes) for :class:`hybridloc.fusion.ParticleFusion`."""
    import io

    from hybridloc.fusion import WalkPrior
    from hybridloc.radio.radiomap import RadioMap

    return WalkPrior.from_radio_map(RadioMap.load(io.BytesIO(payload)), plan)


def walk_prior_refresh(fusion, plan=None) -> Callable[[bytes, MapInfo | None], None]:
    """A map-refresh hook for :class:`Agent`: each new radio map version becomes the particle filter's
    walk prior (:meth:`hybridloc.fusion.ParticleFusion.set_prior`)."""

    def refresh(payload: bytes, info: MapInfo | None) -> None:
        fusion.set_prior(walk_prior(payload, plan))

    return refresh


def fetch_map(session: zenoh.Session, site: str, timeout: float = 10.0) -> tuple[bytes, MapInfo | None] | None:
    """The site's current radio map file (npz bytes) and its attachment; None when the server has none."""
    for r in session.get(P.key_map(site), timeout=timeout):
        if r.ok:
            att = r.ok.attachment
            try:
                info = C.MAP_INFO.decode(att.to_bytes()) if att is not None else None
            except P.Rejected:
                info = None
            return r.ok.payload.to_bytes(), info
    return None


def replay_phone(
    agent: Agent,
    trace,
    speed: float = 1.0,
    survey: bool = False,
    chunk: float = 0.25,
    lockstep: bool = False,
    local_fixes: list | None = None,
    length_model=None,
    pdr_config: PhonePdrConfig | None = None,
) -> PhonePdr:
    """Feed an Indoor Location Competition trace through the phone PDR into ``agent`` at ``speed``x
    (``lockstep``: wait for the server's answer to each scan before going on, :meth:`Agent.wait_answers`;
    ``local_fixes``: [(AbsoluteFix, sigma_random or None)] from the device's own GPS / RFID, fused at their times;
    ``length_model``: the device's calibrated step-length model; ``pdr_config``: the PDR's settings, e.g. the
    walking offset of a phone carried in a pocket). Returns the PDR (its steps and features)."""
    local = sorted(local_fixes or [], key=lambda a: a[0].t)
    i_local = 0
    imu = trace.imu
    if imu is None:
        raise ValueError(f"{trace.path}: no IMU data to replay")
    pdr = PhonePdr(imu.rate_hz, length_model, pdr_config)
    scans = [s for s in trace.scans if s.technology is Technology.WIFI]
    wps = trace.waypoints
    marks = [(t, xy, wps.floor_of(i) or "") for i, (t, xy) in enumerate(zip(wps.t, wps.pos_enu))] if survey else []
    t0 = float(imu.t[0])
    wall0 = time.monotonic()
    i_scan = i_mark = 0
    acc, gyr = imu.accel_body.tolist(), imu.gyro_body.tolist()
    mag = imu.mag_body.tolist() if imu.mag_body is not None else None
    ts = imu.t.tolist()
    k = 0
    n = len(ts)
    while k < n:
        t_chunk_end = ts[k] + chunk
        while k < n and ts[k] < t_chunk_end:
            for st in pdr.update(ts[k], acc[k], gyr[k], mag[k] if mag is not None else None):
                agent.add_step(st)
            k += 1
        t_now = ts[k - 1]
        while i_scan < len(scans) and scans[i_scan].t <= t_now:
            s = scans[i_scan]
            # readings and their ages, as the phone client has always sent them (no frequencies)
            agent.add_scan(RfScan(s.t, Technology.WIFI, s.rssi_dbm, age_s=s.age_s))
            i_scan += 1
        while i_local < len(local) and local[i_local][0].t <= t_now:
            agent.add_fix(*local[i_local])
            i_local += 1
        while i_mark < len(marks) and marks[i_mark][0] <= t_now:
            tm, xy, floor = marks[i_mark]
            agent.add_mark(SurveyMark(float(tm), float(xy[0]), float(xy[1]), floor))
            i_mark += 1
        agent.tick(t_now, lockstep)
        if speed > 0:
            lag = (t_now - t0) / speed - (time.monotonic() - wall0)
            if lag > 0:
                time.sleep(lag)
    for tm, xy, floor in marks[i_mark:]:
        agent.add_mark(SurveyMark(float(tm), float(xy[0]), float(xy[1]), floor))
    agent.end_walk(ts[-1])
    return pdr


LIVE_FORMAT = """Live phone input: one record per line, as the sensors produce them (a pipe, a FIFO, stdin):

    t,ax,ay,az,gx,gy,gz[,mx,my,mz]          an IMU sample (s, m/s^2, rad/s, T), the plain IMU CSV row
    wifi,t,BSSID=RSSI;BSSID=RSSI;...        a WiFi scan (s, dBm)

The header line (``t,ax,...``) and lines starting with # are skipped. Malformed lines are counted and skipped; samples
out of time order are rejected by the PDR (counted); the stream ends at end of file.
"""


@dataclass
class LiveStats:
    samples: int = 0
    scans: int = 0
    bad_lines: int = 0
    first_bad: str = ""
    pdr: PhonePdr | None = None  # its steps and features, e.g. for the device's step-length calibration


def live_phone(agent: Agent, lines, rate_hz: float, lockstep: bool = False, length_model=None, pdr_config: PhonePdrConfig | None = None) -> LiveStats:
    """Run the phone PDR on a live line stream (:data:`LIVE_FORMAT`) into ``agent`` as it arrives
    (``length_model``, ``pdr_config`` as in :func:`replay_phone`)."""
    pdr = PhonePdr(rate_hz, length_model, pdr_config)
    st = LiveStats(pdr=pdr)
    acc_checked: list[float] = []
    units_error = ""
    t_now = -math.inf
    for raw in lines:
        line = raw.strip()
        if not line or line.startswith("#") or line.startswith("t,"):  # blank, comment, the CSV header
            continue
        try:
            if line.startswith("wifi,"):
                _, t_txt, body = line.split(",", 2)
                rssi = {}
                for item in filter(None, body.split(";")):
                    k, v = item.split("=")
                    rssi[k.strip().lower()] = float(v)
                t = float(t_txt)
                if not (math.isfinite(t) and rssi and all(rssi_in_range(v) for v in rssi.values())):
                    raise ValueError(f"a scan needs a finite time and readings in [{RSSI_MIN_DBM:g}, {RSSI_MAX_DBM:g}] dBm")
                agent.add_scan(RfScan(t, Technology.WIFI, rssi))
                st.scans += 1
            else:
                v = [float(x) for x in line.split(",")]
                if len(v) not in (7, 10):
                    raise ValueError(f"{len(v)} fields (7 or 10 expected)")
                if len(acc_checked) < 100 and all(map(math.isfinite, v[1:4])):
                    acc_checked.append(math.sqrt(v[1] ** 2 + v[2] ** 2 + v[3] ** 2))
                    if len(acc_checked) == 100 and float(np.median(acc_checked)) < 3.0:
                        units_error = "live input: the accelerometer magnitude is ~1: the stream is in g, hybridloc expects m/s^2"
                        break
                t = v[0]
                for step in pdr.update(t, v[1:4], v[4:7], v[7:10] if len(v) == 10 else None):
                    agent.add_step(step)
                st.samples += 1
        except ValueError as exc:
            st.bad_lines += 1
            st.first_bad = st.first_bad or f"{line[:60]!r}: {exc}"
            continue
        if math.isfinite(t) and t > t_now:
            t_now = t
            agent.tick(t_now, lockstep)
    if units_error:
        raise ValueError(units_error)
    if math.isfinite(t_now):
        agent.end_walk(t_now)
    agent.drain_fixes()
    return st


def replay_foot(agent: Agent, imu, speed: float = 1.0) -> None:
    """A foot-mounted IMU recording: the INS runs over it and its strides are sent as steps (paced)."""
    from hybridloc.ins.foot import run_foot_ins, strides

    res = run_foot_ins(imu)
    t0 = float(imu.t[0])
    wall0 = time.monotonic()
    for st in strides(res):
        if speed > 0:
            lag = (st.t - t0) / speed - (time.monotonic() - wall0)
            if lag > 0:
                time.sleep(lag)
        agent.add_step(st)
        agent.tick(st.t)
    agent.end_walk(float(imu.t[-1]))

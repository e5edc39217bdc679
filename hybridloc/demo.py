"""``hybridloc demo``: the whole platform on one machine, in one command.

1. starts a server (Zenoh router on a loopback port, SQLite file) in this process;
2. replays some traces of the bundled real sample (Indoor Location Competition site1, floor F1) as
   operator surveys (steps, scans and waypoint marks) through real client sessions, concurrently;
3. rebuilds the site's radio map from the stored surveys (``map rebuild``) and serves it;
4. replays the other traces as concurrent phone clients at accelerated speed: each runs its PDR,
   uploads steps and scans, receives the fixes the server pushes and fuses them;
5. prints, per client and overall, the error at the waypoints of PDR alone (started at the first
   waypoint, its heading aligned on the first segment) versus fused (causal, started by the first fix),
   and writes ``demo.png`` (floor plan, true waypoints, tracks, containment regions) and ``demo.geojson``.

``--sim`` runs the same on a simulated building (generated, written in the same formats).
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import geo
from .errors import ComputationFailed, MissingData
from .fusion import run_fusion
from .io.msft import find_ilc_traces, read_ilc_site, read_ilc_trace
from .metrics import causal_errors as _fused_errors
from .metrics import first_leg_rotation, oracle_start_errors, summarize_errors
from .metrics import held_rows as _held
from .pdr.deadreckoning import DeadReckoning
from .progress import Progress
from .samples import ILC_SITE1_F1
from .units import wrap_angle


def _pdr_track_at(steps, wp_t) -> np.ndarray:
    return DeadReckoning.from_steps(steps, covariance=False).position_at(wp_t)  # from (0, 0) one second before the first step


def _first_leg_rotation(steps, wp_t, wp_xy) -> float:
    """Rotation (rad) turning the PDR's first waypoint leg onto the true one: the "oracle start heading"."""
    return first_leg_rotation(_pdr_track_at(steps, wp_t[:2]), wp_xy[:2])


def _pdr_only_errors(steps, wp_t, wp_xy) -> np.ndarray:
    """PDR alone from the first waypoint, heading aligned on the first waypoint segment."""
    if len(steps) < 2 or len(wp_t) < 2:
        return np.zeros(0)
    return oracle_start_errors(_pdr_track_at(steps, wp_t), wp_xy)


@dataclass
class CrowdOutcome:
    """What the server's crowd SLAM made of a pipeline's walks (:func:`run_platform` with ``slam``)."""

    tracks: dict  # phone device -> its walk's current corrected track (absolute ones only; none when relative or quarantined)
    states: dict  # phone device -> its walk's SLAM state ("corrected", "relative", "quarantined", "failed", "" none)
    summary: dict  # the site's SLAM summary (:meth:`~hybridloc.server.slam_store.SlamStore.summary`)
    batch: str  # the outcome of the final batch re-solve, in words ("complete" when it completed)
    maps: list  # [(version, source, RadioMap)] of every map version the site got, oldest first
    crowd_walks: frozenset = frozenset()  # the phone clients' walk ids, as the labels' ``source`` names them

    @property
    def baseline(self) -> tuple:
        """The map the crowd's coverage is measured against: the operator's survey map (the first version
        from the surveys; a SLAM batch over the survey walks can publish a version before it), else the
        oldest."""
        return next((m for m in self.maps if m[1] == "survey"), self.maps[0])


@dataclass
class PlatformRun:
    results: list  # [(trace, AgentResult)] of the phone clients, by device
    crowd: CrowdOutcome | None  # None when the server ran no crowd SLAM


def run_pipeline(survey: list, others: list, out: Path, speed: float, workers: int = 4, progress: bool = True, corridor_axes: dict | None = None):
    """Server + survey clients + map rebuild + phone clients, all real (Zenoh on loopback, SQLite), the
    server without its crowd SLAM (:func:`run_platform` for the one with it). ``corridor_axes`` (floor ->
    grid direction, :func:`hybridloc.geo.corridor_axes`) go to the phones' Kalman filters.

    Returns [(trace, AgentResult)] of the phone clients.
    """
    return run_platform(survey, others, out, speed, workers, progress, corridor_axes).results


def run_platform(
    survey: list,
    others: list,
    out: Path,
    speed: float,
    workers: int = 4,
    progress: bool = True,
    corridor_axes: dict | None = None,
    plan=None,
    slam: bool = False,
    wait_timeout: float = 300.0,
    beside=None,
) -> PlatformRun:
    """:func:`run_pipeline`, and with ``slam`` the server's crowd SLAM worker on the site as ``hybridloc
    serve`` runs it: the floor plan ``plan`` stored first (what ``floorplan import`` does), every walk
    added to the graph when it ends (the surveys with their marks, the phone clients without), the
    clients hearing their walks' provisional corrections and new map versions while they walk; after
    the clients, a batch re-solve of every floor on demand (what ``slam rebuild`` does), whose corrected
    tracks and crowd map the returned :class:`CrowdOutcome` holds. ``beside(server)``, when given, starts
    something that lives with the server (the demo's dashboard) and returns its ``stop``."""
    import shutil

    from .clients.agent import Agent, PoseWriter, open_client, replay_phone
    from .crowd_eval import _start_server, _wait_until
    from .fusion import LocalFusion
    from .server.rebuild import rebuild
    from .wire.zconfig import free_port

    out.mkdir(parents=True, exist_ok=True)
    # a fresh database, so the clients' spools and the rebuild cache of an earlier run must go too
    for stale in ("spool", "rebuild-cache", "poses"):
        shutil.rmtree(out / stale, ignore_errors=True)
    (out / "poses").mkdir(exist_ok=True)
    site = read_ilc_trace(survey[0]).site or "site"
    db = out / "server.db"
    for suffix in ("", "-wal", "-shm"):
        Path(str(db) + suffix).unlink(missing_ok=True)
    ep = f"tcp/127.0.0.1:{free_port()}"
    say = print if progress else (lambda *a, **k: None)
    say(
        f"[pipeline] server on {ep}, database {db}{', crowd SLAM on' if slam else ''}; {len(survey)} survey traces, {len(others)} phone clients",
        flush=True,
    )
    if slam and plan is None:
        raise ValueError("run_platform: the crowd SLAM needs the site's floor plan")
    server, crowd_slam = _start_server(ep, str(db), site, slam)
    crowd = None
    stop_beside = None
    try:
        if slam or (beside is not None and plan is not None):
            server.store.save_floor_plan(site, plan)  # the operator's `floorplan import`
        if beside is not None:
            stop_beside = beside(server)

        def run_agent(path, kind, spd):
            tr = read_ilc_trace(path)
            dev = f"{kind}-{Path(path).name.split('.')[0][:40]}"
            with open_client(ep) as s:
                ag = Agent(
                    s,
                    site,
                    dev,
                    out / "spool" / dev,
                    PoseWriter(out / "poses" / f"{dev}.csv" if kind == "phone" else None),
                    tr.device_model,
                    fusion=LocalFusion(corridor_axes=corridor_axes),
                )
                ag.uplink.wait_connected(10)
                # the device's own GPS / RFID fixes where the recording has them (the simulator writes
                # <walk>_fixes.csv beside each trace)
                local = None
                fx_csv = Path(path).with_name(Path(path).name.split(".")[0] + "_fixes.csv")
                if kind == "phone" and fx_csv.is_file():
                    from .io.fixes import read_fixes_csv

                    local = read_fixes_csv(fx_csv)[0]
                # phone clients in lock-step: at K x real time every wall-clock delay of the answers
                # would grow K-fold on the recording's clock (16 s median at 20x with 4 clients)
                replay_phone(ag, tr, spd, survey=kind == "survey", lockstep=kind == "phone", local_fixes=local)
                return tr, ag.close(wait=30)

        bar = Progress("[pipeline] surveys uploaded", len(survey), sys.stdout) if progress else None
        with cf.ThreadPoolExecutor(workers) as ex:
            for i, _ in enumerate(ex.map(lambda p: run_agent(p, "survey", 0.0), survey), 1):
                if bar:
                    bar.update(i)
        v, n_lab, _ = rebuild(server.store, site, out / "rebuild-cache")
        if v is None:
            raise ComputationFailed("no radio map could be built from the surveys")
        server.load_map(site)
        say(f"[pipeline] radio map version {v} rebuilt from {n_lab} labelled scans of the stored surveys", flush=True)
        if crowd_slam.on:  # the surveys are in the graph before the phones walk (as a live server would have them)
            ids = {w.walk_id for w in server.store.walks(site, ended_only=True)}
            _wait_until(lambda: ids <= crowd_slam.processed(), wait_timeout)
        results = []
        bar = Progress(f"[pipeline] phone clients (replayed at {speed:g}x) finished", len(others), sys.stdout) if progress else None
        with cf.ThreadPoolExecutor(workers) as ex:
            futs = [ex.submit(run_agent, p, "phone", speed) for p in others]
            for i, f in enumerate(cf.as_completed(futs), 1):
                results.append(f.result())
                if bar:
                    bar.update(i)
        results.sort(key=lambda x: x[1].device)
        if crowd_slam.on:
            crowd = _crowd_outcome(server, crowd_slam, site, [r.device for _, r in results], wait_timeout, say)
    finally:
        if stop_beside is not None:
            stop_beside()
        server.stop()
    return PlatformRun(results, crowd)


def _crowd_outcome(server, crowd_slam, site: str, devices: list[str], timeout: float, say) -> CrowdOutcome:
    """After the clients: every ended walk processed, then a batch re-solve of every floor; the phone
    walks' corrected tracks and every map version of the site."""
    import io

    from .crowd_eval import _wait_until, usable_track
    from .radio.radiomap import RadioMap

    _wait_until(lambda: (crowd_slam.summary() or {}).get("walks_pending", 0) == 0, timeout, poll=0.2)
    say("[pipeline] every walk added to the crowd graph; batch re-solve of every floor ...", flush=True)
    _, what = crowd_slam.batch(timeout)
    walk_of = {w.walk_id: w.device for d in devices for w in server.store.walks(site, device=d)}
    tracks, states = crowd_slam.tracks(list(walk_of))
    by_dev: dict = {}
    state_of: dict = {}
    for wid, dev in sorted(walk_of.items()):  # a device's newest walk last
        st = states.get(wid)
        state_of[dev] = st.status if st is not None else ""
        if usable_track(tracks.get(wid), st):
            by_dev[dev] = tracks[wid]
    rows = server.store.map_versions(site)
    maps = [(int(v), str(src), RadioMap.load(io.BytesIO(data))) for v, src, data in rows]
    return CrowdOutcome(by_dev, state_of, crowd_slam.summary() or {}, what, maps, frozenset(str(w) for w in walk_of))


def bundled_split(sample: Path = ILC_SITE1_F1):
    """(surveys, clients, plan) of the bundled sample: the walks listed in its ``clients.txt`` (the
    four longest, see scripts/make_demo_sample.py) are the phone clients, all others the surveys."""
    traces = find_ilc_traces(sample)
    listed = sample / "clients.txt"
    names = set(listed.read_text().split()) if listed.is_file() else set()
    others = [t for t in traces if t.name in names] or traces[3::4]
    return [t for t in traces if t not in others], others, read_ilc_site(sample)


def _dashboard_beside(listen: str):
    """``beside`` for :func:`run_platform`: the operator dashboard on the demo's server (``demo
    --dashboard HOST:PORT``), its URL with a fresh token printed; returns its stop."""

    def start(server):
        from .server.dashboard.auth import Access, new_token
        from .server.dashboard.run import Dashboard, parse_listen

        host, port = parse_listen(listen)
        token = new_token()
        dash = Dashboard(server.session, server.store, Access({token: None}), host, port).start()
        print(f"[demo] dashboard on {dash.url}?token={token} (up while the replay runs)", flush=True)
        return dash.stop

    return start


def run_demo(
    out: Path, sim: bool = False, speed: float = 20.0, workers: int = 4, sample: Path = ILC_SITE1_F1, slam: bool = True, dashboard: str | None = None
) -> int:
    t_start = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    if sim:
        from .sim.run import load_world, make_world, simulate_walks

        site_dir = out / "sim-world"
        make_world(7, 2, str(site_dir))
        walks_dir = out / "sim-walks"
        simulate_walks(load_world(str(site_dir)), 12, 3.0, "phone", str(walks_dir), seed=7)
        traces = sorted(walks_dir.glob("w*.txt.gz"))
        plan = read_ilc_site(site_dir)
        survey, others = traces[::2] + traces[1::4], traces[3::4]
    else:
        survey, others, plan = bundled_split(sample)
    axes = geo.corridor_axes(plan)
    beside = _dashboard_beside(dashboard) if dashboard else None
    run = run_platform(survey, others, out, speed, workers, corridor_axes=axes, plan=plan, slam=slam, beside=beside)
    results, crowd = run.results, run.crowd
    from .fusion import LocalFusion

    all_pdr, all_fused, all_known = [], [], []
    live_same, corr_same = [], []  # fused live and corrected, on the waypoints both answer
    corr_head = f" {'corrected':>10}" if crowd is not None else ""
    print(
        f"{'client':<22} {'waypoints':>9} {'PDR alone':>10} {'fused':>7}{corr_head} {'fused, start known':>18} {'fixes used':>11} {'own GPS/RFID used':>18}"
    )
    for tr, r in results:
        wt, wxy = tr.waypoints.t, tr.waypoints.pos_enu
        e_p = _pdr_only_errors(r.step_events, wt, wxy)
        e_f = _fused_errors(r.poses, wt, wxy)
        # the same steps and server fixes, the filter started at the pose PDR alone is given
        start = _known_start(r, tr)
        e_k = _fused_errors(_replay(LocalFusion(**start, corridor_axes=axes), r), wt, wxy) if start else np.full(len(e_f), np.nan)
        all_pdr += e_p.tolist()
        all_fused += e_f.tolist()
        all_known += e_k.tolist()
        own = f"{r.local_accepted}/{r.local_fixes} (+{r.displacements} diff.)" if r.local_fixes else "-"
        mean = lambda e: float(np.nanmean(e)) if np.isfinite(e).any() else float("nan")  # noqa: E731
        corr = ""
        if crowd is not None:
            # the corrected (smoothed) track at the same waypoints as the live score: after the first
            e_c = _corrected_at(crowd.tracks.get(r.device), wt, wxy)
            both = np.isfinite(e_c) & np.isfinite(e_f)
            live_same += e_f[both].tolist()
            corr_same += e_c[both].tolist()
            corr = f" {mean(e_c):9.2f}m" if np.isfinite(e_c).any() else f" {crowd.states.get(r.device) or 'none':>10}"
        print(
            f"{r.device[:22]:<22} {len(wt) - 1:9d} {mean(e_p):9.2f}m {mean(e_f):6.2f}m{corr} {mean(e_k):17.2f}m "
            f"{r.fixes_accepted:5d}/{r.fixes_received:<5d} {own:>18}"
        )
    sp, sf, sk = summarize_errors(all_pdr), summarize_errors(all_fused), summarize_errors(all_known)
    print(
        f"overall at {sf.n} waypoints: PDR alone mean {sp.mean:.2f} m (p75 {sp.p75:.2f}; started at the true pose), fused mean "
        f"{sf.mean:.2f} m (p75 {sf.p75:.2f}; started by the fixes), fused from PDR alone's start pose mean {sk.mean:.2f} m (p75 {sk.p75:.2f})"
    )
    cover = None
    if crowd is not None:
        # walkable area within reach of the survey map's labels and of the newest map's
        cover = (map_coverage(plan, crowd.baseline[2]), map_coverage(plan, crowd.maps[-1][2])) if crowd.maps else None
        _crowd_lines(results, crowd, live_same, corr_same, cover)
    _write_outputs(out, plan, results, crowd, cover)
    print(f"[demo] done in {time.monotonic() - t_start:.1f} s; outputs in {out} (demo.png, demo.geojson, poses/)")
    return 0


#: radius of a radio-map label's reach in the demo's coverage figure, m: the bundled sample was chosen
#: by 4 m cells of walked path (hybridloc/data/ilc_site1_F1/README.md), and a kNN fix from labels
#: farther than this is an extrapolation
COVERAGE_RADIUS_M = 4.0


def _corrected_at(track, wp_t, wp_xy) -> np.ndarray:
    """A corrected track's error at each waypoint after the first (the waypoints the live score uses);
    NaN where it has no position (no track, or outside its span)."""
    from .crowd_eval import track_errors

    n = max(len(wp_t) - 1, 0)
    if track is None or n == 0:
        return np.full(n, np.nan)
    return track_errors([track], np.asarray(wp_t, float)[1:], np.asarray(wp_xy, float).reshape(-1, 2)[1:])


def map_coverage(plan, rmap, radius_m: float = COVERAGE_RADIUS_M) -> float:
    """Share of the site's walkable area (every floor of ``plan``) within ``radius_m`` of one of the radio
    map's labelled scans on that floor (:func:`hybridloc.metrics.walkable_coverage`, area-weighted)."""
    from .metrics import walkable_coverage

    num = den = 0.0
    for fl in plan.floors:
        area = fl.walkable.area if fl.walkable is not None else 0.0
        if not area > 0:
            continue
        xy = [ls.pos_enu for ls in rmap.references if ls.floor == fl.name]
        num += area * walkable_coverage(fl.walkable, np.asarray(xy, float).reshape(-1, 2), radius_m)
        den += area
    return num / den if den else float("nan")


def _crowd_lines(results, crowd: CrowdOutcome, live_same: list, corr_same: list, cover: tuple | None) -> None:
    """The demo's crowd-SLAM report: live versus corrected, what the crowd added to the map."""
    sm = crowd.summary
    n_corr = sum(r.device in crowd.tracks for _, r in results)
    lv, co = summarize_errors(live_same), summarize_errors(corr_same)
    gain = 100.0 * (1.0 - co.mean / lv.mean) if lv.n and lv.mean > 0 else float("nan")
    heard = sum(r.tracks_received for _, r in results)
    applied = sum(r.tracks_applied for _, r in results)
    print(
        f"crowd SLAM on the server: {n_corr} of {len(results)} clients' walks corrected (batch re-solve of every floor: {crowd.batch}); "
        f"on the {co.n} waypoints both answer: fused live mean {lv.mean:.2f} m (p75 {lv.p75:.2f}), corrected mean {co.mean:.2f} m "
        f"(p75 {co.p75:.2f}), {abs(gain):.0f} % {'below' if gain >= 0 else 'ABOVE'} live; the clients heard {heard} provisional "
        f"corrections while walking and re-anchored their filters with {applied}"
    )
    if cover is not None:
        v0, src0, m0 = crowd.baseline
        v1, src1, m1 = crowd.maps[-1]
        c0, c1 = cover
        cov = sm.get("coverage")
        print(
            f"coverage the crowd added: walkable area within {COVERAGE_RADIUS_M:g} m of a radio-map label {100 * c0:.1f} % "
            f"(map v{v0}, {src0}, {len(m0.references)} labelled scans) -> {100 * c1:.1f} % (map v{v1}, {src1}, {len(m1.references)} "
            f"labelled scans); {'-' if cov is None else f'{100 * cov:.0f} %'} of the crowd walks' scans have an absolute corrected position; "
            f"loops accepted {sm.get('loops_accepted', '-')}, rejected {sm.get('loops_rejected', '-')}, walks quarantined {sm.get('walks_quarantined', '-')}"
        )


def _true_motion_average_errors(fixes, wp_t, wp_xy, window_s: float) -> np.ndarray:
    """At each waypoint (after the first), the mean of the fixes of the last ``window_s`` seconds, each
    moved by the TRUE motion since it was taken (the waypoints interpolated in time, as a perfect PDR
    would give it). No fusion of these fixes with any dead reckoning does better than this on average
    for long: it measures what the radio map's errors, correlated for tens of seconds along a walk,
    leave. NaN where no fix falls in the window after the first waypoint."""
    wt, wxy = np.asarray(wp_t, float), np.asarray(wp_xy, float)
    out = np.full(max(len(wt) - 1, 0), np.nan)
    if not fixes or len(wt) < 2:
        return out
    f = np.array([[x[0], x[1], x[2]] for x in fixes], float)
    truth = np.column_stack([np.interp(f[:, 0], wt, wxy[:, 0]), np.interp(f[:, 0], wt, wxy[:, 1])])
    for i in range(1, len(wt)):
        m = (f[:, 0] >= max(wt[0], wt[i] - window_s)) & (f[:, 0] <= wt[i])
        if m.any():
            moved = f[m, 1:3] + (wxy[i] - truth[m])
            out[i - 1] = float(np.linalg.norm(moved.mean(axis=0) - wxy[i]))
    return out


def true_motion_steps(steps, wp_t, wp_xy, sigma_length: float = 0.05, sigma_heading: float = math.radians(2.0)) -> list:
    """A perfect PDR: the same step times, each step's length and heading taken from the TRUE motion
    (the waypoints interpolated in time, as :func:`_true_motion_average_errors` moves the fixes), with
    small sigmas. Fed through a filter with the client's own fixes, in the order they reached it, it
    shows what that filter and the radio map leave when dead reckoning has no error at all. Steps
    outside the waypoints' time span do not move."""
    wt, wxy = np.asarray(wp_t, float), np.asarray(wp_xy, float)
    if not steps or len(wt) < 2:
        return []
    ts = np.clip([s.t for s in steps], wt[0], wt[-1])
    p = np.column_stack([np.interp(ts, wt, wxy[:, 0]), np.interp(ts, wt, wxy[:, 1])])
    d = np.diff(p, axis=0, prepend=p[:1])
    heading = np.arctan2(d[:, 1], d[:, 0])
    out, prev = [], None
    for s, (dx, dy), h in zip(steps, d, heading):
        turn = None if prev is None else float(wrap_angle(h - prev))
        out.append(
            dataclasses.replace(
                s,
                length=float(math.hypot(dx, dy)),
                heading=float(h),
                sigma_length=sigma_length,
                sigma_heading=sigma_heading,
                heading_change=turn,
                sigma_heading_change=None if turn is None else sigma_heading,
                degraded="",
            )
        )
        prev = h
    return out


def _floor_hits(poses, waypoints) -> list[bool]:
    """At each waypoint after the first (where an estimate is held): is it on that mark's floor?"""
    return [poses[i][3] == waypoints.floor_of(k + 1) for k, i in enumerate(_held(poses, waypoints.t)) if i >= 0]


def _known_start(r, tr) -> dict | None:
    """Filter arguments for the start pose PDR alone is given: the first waypoint (1 m) and the first
    leg's heading (5 deg); None when the walk is too short to have one."""
    wt, wxy = tr.waypoints.t, tr.waypoints.pos_enu
    if len(r.step_events) < 2 or len(wt) < 2:
        return None
    return {
        "init": (float(wxy[0][0]), float(wxy[0][1]), 1.0),
        "floor": tr.waypoints.floor_of(0),
        "heading_bias": (_first_leg_rotation(r.step_events, wt, wxy), math.radians(5.0)),
    }


def _replay(filt, r, steps=None) -> list[tuple]:
    """A client's steps (or ``steps`` in their place, same times) and server fixes, in the order
    they reached it, through another filter."""
    est = run_fusion(filt, r.step_events if steps is None else steps, [f for _, f in r.fix_log], [a for a, _ in r.fix_log])
    return [(e.t, float(e.pos[0]), float(e.pos[1]), e.floor) for e in est]


def _rel(x: float, ref: float) -> str:
    """'12% below' / '5% above': x against ref, in words (a signed percentage reads both ways)."""
    r = 100.0 * (x / ref - 1.0)
    return f"{abs(r):.0f}% {'below' if r < 0 else 'above'}"


def run_fusion_eval(
    site_dir: str, out: Path, replay_every: int = 4, every: int = 1, workers: int = 4, speed: float = 20.0, kld_epsilons=None
) -> dict:
    """``hybridloc eval fusion``: surveys build the map; every ``replay_every``-th trace is a phone client.
    Prints its report and returns the headline figures (the JSON line's: ``cold_mean_m``, ``wifi_mean_m``...).

    The phone clients run our Kalman filter (:class:`~hybridloc.fusion.LocalFusion`) live, in lock-step
    with the server's answers. The same steps and fixes, in the order they reached each client, are
    then replayed (:func:`hybridloc.fusion.run_fusion`) through the particle filter with the site's map
    and through Kourogi et al.'s own filter (:class:`~hybridloc.fusion.KourogiFusion`, the reference),
    cold and started at the first waypoint (a known start, e.g. an entrance, as PDR only has), and
    through the particle filter without any map (what the floor plan and the walk prior add).
    """
    from .fusion import KourogiFusion, LocalFusion, ParticleFusion, WalkPrior
    from .io.msft import read_ilc_site
    from .radio.radiomap import RadioMap
    from .server.store import Store

    traces = find_ilc_traces(site_dir)[::every]
    if len(traces) < 4:
        raise MissingData(f"too few Indoor Location Competition traces under {site_dir}")
    others = traces[::replay_every]
    survey = [t for t in traces if t not in set(others)]
    t0 = time.monotonic()
    plan = read_ilc_site(site_dir)
    axes = geo.corridor_axes(plan)
    results = run_pipeline(survey, others, out, speed=speed, workers=workers, corridor_axes=axes)
    import io

    site = read_ilc_trace(survey[0]).site or "site"
    store = Store(str(out / "server.db"))
    got = store.load_map(site)
    store.close()
    rmap = RadioMap.load(io.BytesIO(got[1]))
    prior = WalkPrior.from_radio_map(rmap, plan)
    names = [
        "PDR only (oracle start pose)",
        "WiFi only (server fixes)",
        "fused, Kalman, live",
        "fused, particle + map",
        "fused, Kalman, start pose known",
        "fused, particle, start pose known",
        "Kourogi x/y/vx/vy (paper), cold",
        "Kourogi x/y/vx/vy, start known",
        "fused, particle, no map",
    ]
    errs: dict[str, list] = {k: [] for k in names}  # per waypoint after the first, NaN where a method has no answer
    floors: dict[str, list] = {k: [] for k in names[2:]}
    perfect: dict[str, list] = {"Kalman": [], "particle + map": []}  # a perfect PDR through the same filters, cold
    lags = []
    since: list[float] = []  # per waypoint (after the first): seconds since the walk's first waypoint
    for tr, r in results:
        wt, wxy = tr.waypoints.t, tr.waypoints.pos_enu
        nw = max(len(wt) - 1, 0)
        e_pdr = _pdr_only_errors(r.step_events, wt, wxy)
        errs[names[0]] += (e_pdr if e_pdr.size == nw else np.full(nw, np.nan)).tolist()
        errs[names[1]] += _fused_errors(r.raw_fixes, wt, wxy).tolist()  # the fixes alone, scored alike
        lags += r.fix_lags
        since += (np.asarray(wt[1:]) - wt[0]).tolist()
        variants = {
            names[2]: r.poses,
            names[3]: _replay(ParticleFusion(prior, corridor_axes=axes), r),
            names[6]: _replay(KourogiFusion(), r),
            names[8]: _replay(ParticleFusion(), r),
        }  # what the floor plan and walk prior add
        start = _known_start(r, tr)
        if start:
            variants[names[4]] = _replay(LocalFusion(**start, corridor_axes=axes), r)
            variants[names[5]] = _replay(ParticleFusion(prior, **start, corridor_axes=axes), r)
            variants[names[7]] = _replay(KourogiFusion(**start), r)
        ideal = true_motion_steps(r.step_events, wt, wxy)
        perfect["Kalman"] += _fused_errors(_replay(LocalFusion(corridor_axes=axes), r, ideal), wt, wxy).tolist()
        perfect["particle + map"] += _fused_errors(_replay(ParticleFusion(prior, corridor_axes=axes), r, ideal), wt, wxy).tolist()
        for k in names[2:]:
            poses = variants.get(k, [])
            errs[k] += _fused_errors(poses, wt, wxy).tolist()
            floors[k] += _floor_hits(poses, tr.waypoints)
    print(
        f"fusion through the real client and server path (Zenoh loopback, SQLite): {len(survey)} survey traces -> radio map; "
        f"{len(results)} phone clients replayed in lock-step (fix lag on the recording's clock: median {np.median(lags) if lags else float('nan'):.1f} s), "
        f"causal, {time.monotonic() - t0:.0f} s"
    )
    summ = {k: summarize_errors(v) for k, v in errs.items()}
    for k, sm in summ.items():
        fl = f", floor hit {100 * np.mean(floors[k]):.1f}%" if floors.get(k) else ""
        print(f"  {k:<30} at waypoints: mean {sm.mean:5.2f} m, median {sm.median:5.2f}, p75 {sm.p75:5.2f}, p95 {sm.p95:5.2f} (n={sm.n}){fl}")
    # ratios on the same waypoints: those where PDR only, WiFi only and the variant all answer
    E = {k: np.asarray(v, float) for k, v in errs.items()}
    for k in names[2:]:
        m = np.isfinite(E[names[0]]) & np.isfinite(E[names[1]]) & np.isfinite(E[k])
        if m.any():
            mp, mw, mf = E[names[0]][m].mean(), E[names[1]][m].mean(), E[k][m].mean()
            print(
                f"  on the {int(m.sum())} waypoints all three answer: {k} {mf:.2f} m, {_rel(mf, mw)} WiFi only ({mw:.2f}), "
                f"{_rel(mf, mp)} PDR only ({mp:.2f})"
            )
    # PDR drifts with time, WiFi does not: the same means by how long the walk had been going
    T = np.asarray(since)
    bins = ((0, 10), (10, 20), (20, 40), (40, math.inf))
    in_bin = [(T >= a) & (T < b) for a, b in bins]
    print(
        "  mean error by time since the walk's first waypoint (s): "
        + "  ".join(f"{a:g}-{b:g}" for a, b in bins)
        + "   (waypoints: "
        + ", ".join(str(int(m.sum())) for m in in_bin)
        + ")"
    )
    for k in (names[0], names[1], names[2], names[4]):
        print(f"    {k:<32}" + "  ".join(f"{np.nanmean(E[k][m]):6.2f}" if np.isfinite(E[k][m]).any() else "     -" for m in in_bin))
    # What the radio map leaves: its errors stay correlated for tens of seconds along a walk, so even
    # a perfect PDR cannot average them away (see _true_motion_average_errors).
    windows = (10.0, 20.0, 40.0, math.inf)
    floor_of_map = [
        np.concatenate([_true_motion_average_errors(r.raw_fixes, tr.waypoints.t, tr.waypoints.pos_enu, w) for tr, r in results]) for w in windows
    ]
    print(
        "  the radio map's floor: the WiFi fixes of the last 10 s / 20 s / 40 s / whole walk, each moved by the TRUE motion (a perfect PDR) "
        "and averaged: " + " / ".join(f"{np.nanmean(e):.2f}" for e in floor_of_map) + " m at waypoints; a cold start beats it only with more "
        "than the fixes (a known start, the floor plan)"
    )
    print(
        "  a perfect PDR (each step's length and heading from the TRUE motion, same step times, same fixes in the same order) through the "
        "same filters, cold: "
        + ", ".join(f"{k} {np.nanmean(v):.2f} m" for k, v in perfect.items())
        + f"; against WiFi only ({np.nanmean(E[names[1]]):.2f} m): "
        + ", ".join(_rel(np.nanmean(v), np.nanmean(E[names[1]])) for v in perfect.values())
        + ". What a cold start leaves above this is the PDR's; the rest is the radio map's"
    )
    # Surveyors walked some routes more than once with the same marks: a client whose route is also
    # among the surveys walks a path the map has seen walked; the others walk new paths.
    seen = _routes_walked_by_surveys(traces, survey)
    on_seen = np.concatenate([np.full(max(len(tr.waypoints.t) - 1, 0), str(tr.path) in seen) for tr, _ in results]).astype(bool)
    n_seen = sum(str(tr.path) in seen for tr, _ in results)
    for label, m, n in (("on a route a survey also walked", on_seen, n_seen), ("on a route no survey walked", ~on_seen, len(results) - n_seen)):
        if m.any():
            print(
                f"  clients {label} ({n} clients, {int(m.sum())} waypoints): mean error "
                + ", ".join(f"{k} {np.nanmean(E[k][m]):.2f} m" for k in (names[0], names[1], names[2], names[4]))
            )
    print("  goal: fused mean <= 3 m, floor >= 97 %, fused >= 30 % below WiFi-only and below PDR-only")
    cold = _cold_start_report(results, prior, axes, KLD_EPSILONS if kld_epsilons is None else kld_epsilons)
    cold.update(_kalman_settings_held_out(results, axes))
    keys = (
        "pdr_mean_m",
        "wifi_mean_m",
        "cold_mean_m",
        "particle_cold_mean_m",
        "known_start_mean_m",
        "particle_known_start_mean_m",
        "kourogi_cold_mean_m",
        "kourogi_known_start_mean_m",
        "particle_no_map_mean_m",
    )
    head: dict = {key: summ[k].mean for key, k in zip(keys, names)}
    head.update(
        cold_p95_m=summ[names[2]].p95,
        particle_cold_p95_m=summ[names[3]].p95,
        floor_hit_pct=100 * float(np.mean(floors[names[2]])) if floors[names[2]] else float("nan"),
        particle_floor_hit_pct=100 * float(np.mean(floors[names[3]])) if floors[names[3]] else float("nan"),
        fix_lag_median_s=float(np.median(lags)) if lags else float("nan"),
        waypoints=summ[names[2]].n,
        clients=len(results),
    )
    head.update(cold)
    return head


class _Timed:
    """A step filter's ``predict`` / ``correct`` timed (wall seconds, summed) and its particle count
    read after every step: what ``eval fusion`` prints as particles used and time per step."""

    def __init__(self, filt):
        self.filt, self.seconds, self.counts = filt, 0.0, []

    @property
    def initialised(self) -> bool:
        return self.filt.initialised

    def predict(self, step):
        t = time.perf_counter()
        e = self.filt.predict(step)
        self.seconds += time.perf_counter() - t
        if self.filt.initialised:
            self.counts.append(self.filt.n_particles)
        return e

    def correct(self, fix):
        t = time.perf_counter()
        out = self.filt.correct(fix)
        self.seconds += time.perf_counter() - t
        return out


#: The cold-start goal (Woodman and Harle; issue 24 point 4): within this error ...
COLD_RADIUS_M = 5.0
#: ... within this many seconds of the walk's first mark, on this share of walks, with at most N_MAX particles
COLD_WINDOW_S = 30.0
COLD_SHARE = 0.9
COLD_N_MAX = 50_000
#: Fox's epsilon for KLD-sampling, the candidates ``eval fusion`` chooses from (leave one floor out)
KLD_EPSILONS = (0.05, 0.15, 0.4)


#: The Kalman filter's settings fitted on ILC site1 (FusionConfig's comments) that ``eval fusion`` holds
#: out by floor: the successive WiFi fixes' error correlation and the corridor heading's sigma (deg)
KALMAN_GRID = {"fix_correlation": (0.0, 0.25, 0.5, 0.75), "corridor_sigma_deg": (5.0, 10.0, 20.0)}


def _kalman_settings_held_out(results, axes) -> dict:
    """The live Kalman filter's tuned settings (:data:`KALMAN_GRID`) chosen leave one floor out: each
    client's steps and fixes, in the order they reached it, replayed cold through every candidate; for
    each floor the candidate with the lowest mean error at the other floors' waypoints is scored on
    it. Prints the held-out mean beside the fitted one (the candidate best on every floor) and the
    default's; returns the JSON line's ``kalman_cold_*`` keys."""
    from itertools import product

    from .fusion import FusionConfig, LocalFusion

    cands = list(product(KALMAN_GRID["fix_correlation"], KALMAN_GRID["corridor_sigma_deg"]))
    floor_of = [tr.waypoints.floor_of(0) or "" for tr, _ in results]
    floors = sorted(set(floor_of))
    errs: dict[tuple, dict[str, list]] = {}
    for rho, sig in cands:
        cfg = FusionConfig(fix_correlation={"wifi": rho, "ble": rho}, corridor_sigma=math.radians(sig))
        per: dict[str, list] = {f: [] for f in floors}
        for (tr, r), f in zip(results, floor_of):
            per[f] += _fused_errors(_replay(LocalFusion(cfg, corridor_axes=axes), r), tr.waypoints.t, tr.waypoints.pos_enu).tolist()
        errs[(rho, sig)] = per

    def mean_on(c, fl) -> float:
        v = [e for f in fl for e in errs[c][f]]
        return float(np.nanmean(v)) if np.isfinite(v).any() else math.inf

    chosen = {f: min(cands, key=lambda c: mean_on(c, [g for g in floors if g != f] or floors)) for f in floors}
    held = [e for f in floors for e in errs[chosen[f]][f]]
    fitted = min(cands, key=lambda c: mean_on(c, floors))
    d = FusionConfig()
    default = (d.fix_correlation["wifi"], round(math.degrees(d.corridor_sigma), 6))
    print(
        "  the live Kalman filter's fitted settings held out by floor (cold replays; fix error correlation x corridor heading sigma, "
        + " x ".join("/".join(f"{v:g}" for v in vals) for vals in KALMAN_GRID.values())
        + " deg): chosen on the other floors "
        + ", ".join(f"{f} {chosen[f][0]:g}/{chosen[f][1]:g}" for f in floors)
        + f"; held out {np.nanmean(held):.2f} m, fitted ({fitted[0]:g}/{fitted[1]:g} on every floor) {mean_on(fitted, floors):.2f} m, "
        f"the default ({default[0]:g}/{default[1]:g}) {mean_on(default, floors) if default in errs else float('nan'):.2f} m"
    )
    return {
        "kalman_cold_held_out_mean_m": float(np.nanmean(held)),
        "kalman_cold_fitted_mean_m": mean_on(fitted, floors),
        "kalman_cold_default_mean_m": mean_on(default, floors) if default in errs else float("nan"),
    }


def _cold_walks(results, prior, axes, cfg) -> list[dict]:
    """Each client's steps and fixes, in the order they reached it, through the particle filter with
    the map under ``cfg``: per walk its floor, seconds to within COLD_RADIUS_M (inf: not within
    COLD_WINDOW_S), particles used (mean and most over its steps) and filter seconds per step."""
    from .fusion import ParticleFusion
    from .metrics import time_to_within

    out = []
    for tr, r in results:
        wp = tr.waypoints
        filt = _Timed(ParticleFusion(prior, config=cfg, corridor_axes=axes))
        est = run_fusion(filt, r.step_events, [f for _, f in r.fix_log], [a for a, _ in r.fix_log])
        poses = [(e.t, float(e.pos[0]), float(e.pos[1]), e.floor) for e in est]
        floors = [wp.floor_of(k) for k in range(len(wp.t))]
        out.append(
            {
                "floor": wp.floor_of(0) or "",
                "ttw": time_to_within(poses, wp.t, wp.pos_enu, COLD_RADIUS_M, COLD_WINDOW_S, floors),
                "n_mean": float(np.mean(filt.counts)) if filt.counts else float("nan"),
                "n_max": max(filt.counts, default=0),
                "s_per_step": filt.seconds / max(len(r.step_events), 1),
                "short": (wp.t[-1] - wp.t[0]) < COLD_WINDOW_S if len(wp.t) else True,
            }
        )
    return out


def _cold_share(walks: list[dict]) -> float:
    return float(np.mean([np.isfinite(w["ttw"]) for w in walks])) if walks else float("nan")


def _cold_start_report(results, prior, axes, epsilons=KLD_EPSILONS) -> dict:
    """The particle filter from a cold start: KLD-sampling (Fox 2003) started uniform in the first
    fix's 95 % region (containment start), scored by how soon each walk's track comes within 5 m of
    the truth (:func:`hybridloc.metrics.time_to_within`) - against the fixed-count, Gaussian-start
    filter above on the same walks. Fox's epsilon is chosen leave one floor out: for each floor, the
    epsilon with the largest share within 5 m on the other floors (fewest particles on a tie) is
    scored on that floor; the fitted figure (the best epsilon on all floors) is printed beside it.
    Prints per floor: walks, share within 5 m in 30 s, median seconds to it, particles used (mean,
    most), milliseconds per step. Returns the JSON line's ``cold_*`` keys."""
    from .fusion import ParticleConfig

    eps = tuple(float(e) for e in epsilons)
    runs = {e: _cold_walks(results, prior, axes, ParticleConfig(kld_epsilon=e, start="containment", n_max=COLD_N_MAX)) for e in eps}
    plain = _cold_walks(results, prior, axes, ParticleConfig())
    floors = sorted({w["floor"] for w in plain})

    def key(walks):  # larger share first, then fewer particles
        return (_cold_share(walks), -float(np.nanmean([w["n_mean"] for w in walks])) if walks else 0.0)

    held: list[dict] = []
    chosen: dict[str, float] = {}
    for f in floors:
        train = {e: [w for w in runs[e] if w["floor"] != f] for e in eps}
        best = max(eps, key=lambda e: key(train[e])) if len(floors) > 1 else eps[0]
        chosen[f] = best
        held += [w for w in runs[best] if w["floor"] == f]
    fitted_eps = max(eps, key=lambda e: key(runs[e]))
    print(
        f"  cold start, particle filter + map (KLD-sampling, start uniform in the first fix's 95 % region, <= {COLD_N_MAX:,} particles); "
        f"goal: within {COLD_RADIUS_M:g} m of the truth within {COLD_WINDOW_S:g} s on >= {100 * COLD_SHARE:.0f} % of walks, every floor"
    )
    print(
        "    Fox's epsilon per held-out floor (chosen on the other floors from "
        + ", ".join(f"{e:g}" for e in eps)
        + "): "
        + ", ".join(f"{f} {chosen[f]:g}" for f in floors)
    )

    def row(label, walks):
        t = np.array([w["ttw"] for w in walks], float)
        fin = t[np.isfinite(t)]
        nm = np.array([w["n_mean"] for w in walks], float)
        print(
            f"    {label:<44} {len(walks):4d} walks ({sum(w['short'] for w in walks)} shorter than {COLD_WINDOW_S:g} s): "
            f"within {COLD_RADIUS_M:g} m in {COLD_WINDOW_S:g} s {100 * _cold_share(walks):5.1f} %, median {np.median(fin) if fin.size else float('nan'):4.1f} s; "
            f"particles mean {np.nanmean(nm) if nm.size else float('nan'):7.0f}, most {max((w['n_max'] for w in walks), default=0):6d}; "
            f"{1e3 * np.mean([w['s_per_step'] for w in walks]) if walks else float('nan'):6.2f} ms per step"
        )

    for f in floors:
        row(f"{f}, held out (KLD, containment start)", [w for w in held if w["floor"] == f])
        row(f"{f}, fixed {ParticleConfig().n_particles} particles, Gaussian start", [w for w in plain if w["floor"] == f])
    row("all floors, held out", held)
    row(f"all floors, fitted (epsilon {fitted_eps:g} on every floor)", runs[fitted_eps])
    row("all floors, fixed-count Gaussian start", plain)
    per_floor = {f: _cold_share([w for w in held if w["floor"] == f]) for f in floors}
    nm_held = [w["n_mean"] for w in held]
    sp_held = [w["s_per_step"] for w in held]
    plain_sp = float(np.mean([w["s_per_step"] for w in plain])) if plain else float("nan")
    if held and plain_sp > 0:
        print(f"    time per step, held out against the fixed-count filter: x{np.mean(sp_held) / plain_sp:.2f}")
    return {
        "cold_within_5m_30s_pct": 100 * _cold_share(held),
        "cold_within_5m_30s_worst_floor_pct": 100 * min(per_floor.values()) if per_floor else float("nan"),
        "cold_within_5m_30s_fitted_pct": 100 * _cold_share(runs[fitted_eps]),
        "cold_within_5m_30s_fixed_pct": 100 * _cold_share(plain),
        "cold_particles_mean": float(np.nanmean(nm_held)) if nm_held else float("nan"),
        "cold_particles_max": max((w["n_max"] for w in held), default=0),
        "cold_ms_per_step": 1e3 * float(np.mean(sp_held)) if sp_held else float("nan"),
    }


def _routes_walked_by_surveys(traces: list, survey: list) -> set[str]:
    """Paths (as str) of the traces whose route (:func:`hybridloc.radio.evaluate.route_groups`) one of
    the ``survey`` traces also walked."""
    from types import SimpleNamespace

    from .io.msft import read_ilc_waypoints
    from .radio.evaluate import route_groups

    wps = [read_ilc_waypoints(p) for p in traces]
    groups = route_groups([SimpleNamespace(floor=w.floor or "", wp_xy=w.pos_enu) for w in wps])
    surveyed = {str(p) for p in survey}
    walked = {g for p, g in zip(traces, groups) if str(p) in surveyed}
    return {str(p) for p, g in zip(traces, groups) if g in walked and str(p) not in surveyed}


def _write_outputs(out: Path, plan, results, crowd: CrowdOutcome | None = None, cover: tuple | None = None) -> None:
    """``demo.png`` (:func:`plot_demo`, and with the crowd SLAM :func:`plot_coverage` beside it) and
    ``demo.geojson`` (:func:`demo_features`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io.writers import write_geojson

    if crowd is None or cover is None:
        fig, ax = plt.subplots(figsize=(11, 8))
        plot_demo(ax, plan, results, crowd)
    else:
        fig, (ax, ax2) = plt.subplots(1, 2, figsize=(20, 8))
        plot_demo(ax, plan, results, crowd)
        plot_coverage(ax2, plan, crowd, cover)
    fig.tight_layout()
    fig.savefig(out / "demo.png", dpi=90)
    plt.close(fig)
    write_geojson(out / "demo.geojson", demo_features(plan, results, crowd))


def _draw_floor(ax, fl) -> None:
    for poly in fl.outline.geoms:
        ax.plot(*poly.exterior.xy, color="0.3", lw=1)
    for _, room in fl.rooms:
        ax.fill(*room.exterior.xy, color="0.9", ec="0.75", lw=0.5)


def plot_demo(ax, plan, results, crowd: CrowdOutcome | None = None) -> None:
    """The demo's figure into ``ax``: the first floor's outline and rooms, each client's true waypoints
    (dashed), fused live track (solid) and, with the crowd SLAM, its corrected track (dash-dot), and a
    95 % disc at its last fix."""
    from matplotlib import colormaps
    from matplotlib.patches import Circle

    _draw_floor(ax, plan.floors[0])
    colors = colormaps["tab10"].colors
    for i, (tr, r) in enumerate(results):
        c = colors[i % len(colors)]
        wp = tr.waypoints.pos_enu
        ax.plot(wp[:, 0], wp[:, 1], "o--", color=c, ms=4, lw=0.8, alpha=0.6)
        if r.poses:
            xy = np.array([[p[1], p[2]] for p in r.poses])
            ax.plot(xy[:, 0], xy[:, 1], "-", color=c, lw=1.6, label=r.device if crowd is None else f"{r.device} live")
            # a containment-style disc of 2 sigma at the last fix, for the eye
            last = r.poses[-1]
            ax.add_patch(Circle((last[1], last[2]), 2.45 * max(last[4], last[5]), color=c, alpha=0.15))
        ct = crowd.tracks.get(r.device) if crowd is not None else None
        if ct is not None:
            ax.plot(ct.pos_enu[:, 0], ct.pos_enu[:, 1], "-.", color=c, lw=1.4, alpha=0.9, label=f"{r.device} corrected")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if crowd is None:
        ax.set_title("hybridloc demo: fused tracks (solid), true waypoints (dashed), 95 % regions at the last fix")
    else:
        ax.set_title(
            "hybridloc demo: fused live tracks (solid), corrected by the crowd SLAM (dash-dot), true waypoints (dashed), 95 % regions at the last fix",
            fontsize=9,
        )
    ax.legend(fontsize=7, loc="upper right")


def plot_coverage(ax, plan, crowd: CrowdOutcome, cover: tuple[float, float], radius_m: float = COVERAGE_RADIUS_M) -> None:
    """The coverage panel: the first floor's walkable area within ``radius_m`` of the survey map's labels
    (grey) and of the labels the crowd added in the newest map (green), the labels as dots; ``cover``:
    the site's coverage by the survey map and by the newest one (:func:`map_coverage` at ``radius_m``),
    in the title."""
    from .metrics import walkable_reach

    fl = plan.floors[0]
    _draw_floor(ax, fl)
    v0, _, m0 = crowd.baseline
    v1, src1, m1 = crowd.maps[-1]
    p0 = np.array([ls.pos_enu for ls in m0.references if ls.floor == fl.name], float).reshape(-1, 2)
    # the crowd's labels in the newest map: its scans of the phone clients' walks (the map's survey
    # walks are labelled there too, from their corrected tracks: the grey area is the survey map's own)
    p1 = np.array([ls.pos_enu for ls in m1.references if ls.floor == fl.name and ls.source in crowd.crowd_walks], float).reshape(-1, 2)

    def fill(geom, color, label):
        if geom.is_empty:
            return
        polys = getattr(geom, "geoms", [geom])
        for k, g in enumerate(polys):
            if g.geom_type == "Polygon":
                ax.fill(*g.exterior.xy, color=color, alpha=0.45, lw=0, label=label if k == 0 else None)

    r0 = walkable_reach(fl.walkable, p0, radius_m)
    r1 = walkable_reach(fl.walkable, np.vstack([p0, p1]), radius_m)
    fill(r1.difference(r0), "tab:green", f"added by the crowd (map v{v1}, {src1})")
    fill(r0, "0.55", f"survey map v{v0}")
    if len(p0):
        ax.plot(p0[:, 0], p0[:, 1], ".", color="0.25", ms=2)
    if len(p1):
        ax.plot(p1[:, 0], p1[:, 1], ".", color="darkgreen", ms=2)
    c0, c1 = cover
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_title(f"walkable area within {radius_m:g} m of a radio-map label: survey {100 * c0:.0f} %, with the crowd {100 * c1:.0f} %", fontsize=9)
    ax.legend(fontsize=7, loc="upper right")


def demo_features(plan, results, crowd: CrowdOutcome | None = None) -> list[dict]:
    """GeoJSON features of the demo: the floor plan, each client's fused track (time-ordered, one
    point per time), its corrected track (kind "corrected_track", with the crowd SLAM) and its true
    waypoints."""
    from .io.writers import floorplan_features, point_features

    feats = floorplan_features(plan)
    for tr, r in results:
        if r.poses:
            xy = np.array([[p[1], p[2]] for p in r.poses])
            t = np.array([p[0] for p in r.poses])
            order = np.argsort(t, kind="stable")
            tt, idx = np.unique(t[order], return_index=True)
            feats.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "LineString", "coordinates": xy[order][idx].round(3).tolist()},
                    "properties": {"kind": "track", "device": r.device},
                }
            )
        ct = crowd.tracks.get(r.device) if crowd is not None else None
        if ct is not None and len(ct.t) >= 2:
            feats.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "LineString", "coordinates": ct.pos_enu.round(3).tolist()},
                    "properties": {"kind": "corrected_track", "device": r.device, "anchored": ct.anchored, "scale": round(float(ct.scale), 4)},
                }
            )
        feats += point_features(tr.waypoints.t, tr.waypoints.pos_enu, kind="true_waypoint", trace=Path(tr.path).name)
    return feats

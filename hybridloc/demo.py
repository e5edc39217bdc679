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
import math
import time
from pathlib import Path

import numpy as np

from .io.msft import find_ilc_traces, read_ilc_site, read_ilc_trace
from .metrics import interpolate_positions, summarize_errors
from .samples import ILC_SITE1_F1



def _pdr_only_errors(steps, wp_t, wp_xy) -> np.ndarray:
    """PDR alone from the first waypoint, heading aligned on the first waypoint segment."""
    if len(steps) < 2 or len(wp_t) < 2:
        return np.zeros(0)
    t = np.array([steps[0].t - 1.0] + [s.t for s in steps])
    d = np.array([s.displacement_enu for s in steps])
    p = np.vstack([[0.0, 0.0], np.cumsum(d, axis=0)])
    est = np.column_stack([np.interp(wp_t, t, p[:, 0]), np.interp(wp_t, t, p[:, 1])])
    de, dt_ = est[1] - est[0], wp_xy[1] - wp_xy[0]
    rot = math.atan2(dt_[1], dt_[0]) - math.atan2(de[1], de[0]) if np.linalg.norm(de) > 0.1 else 0.0
    c, s = math.cos(rot), math.sin(rot)
    al = (est - est[0]) @ np.array([[c, s], [-s, c]]) + wp_xy[0]
    return np.linalg.norm(al[1:] - wp_xy[1:], axis=1)


def _fused_errors(poses, wp_t, wp_xy) -> np.ndarray:
    if len(poses) < 2:
        return np.full(max(len(wp_t) - 1, 0), np.nan)
    pts = sorted({p[0]: p for p in poses}.values())
    t = np.array([p[0] for p in pts])
    xy = np.array([[p[1], p[2]] for p in pts])
    est = interpolate_positions(t, xy, wp_t[1:])
    return np.linalg.norm(est - wp_xy[1:], axis=1)


def run_pipeline(survey: list, others: list, out: Path, speed: float, workers: int = 4, progress: bool = True):
    """Server + survey clients + map rebuild + phone clients, all real (Zenoh on loopback, SQLite).

    Returns [(trace, AgentResult)] of the phone clients.
    """
    import shutil

    from .clients.agent import Agent, PoseWriter, open_client, replay_phone
    from .server.rebuild import rebuild
    from .server.service import Server
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
    say(f"[pipeline] server on {ep}, database {db}; {len(survey)} survey traces, {len(others)} phone clients", flush=True)
    server = Server(ep, str(db)).start()
    try:
        def run_agent(path, kind, spd):
            tr = read_ilc_trace(path)
            dev = f"{kind}-{Path(path).name.split('.')[0][:40]}"
            with open_client(ep) as s:
                ag = Agent(s, site, dev, out / "spool" / dev, PoseWriter(out / "poses" / f"{dev}.csv" if kind == "phone" else None), tr.device_model)
                ag.uplink.wait_connected(10)
                replay_phone(ag, tr, spd, survey=kind == "survey")
                return tr, ag.close(wait=30)

        with cf.ThreadPoolExecutor(workers) as ex:
            for i, _ in enumerate(ex.map(lambda p: run_agent(p, "survey", 0.0), survey), 1):
                say(f"\r[pipeline] surveys uploaded {i}/{len(survey)}", end="", flush=True)
        say(flush=True)
        v, n_lab, _ = rebuild(server.store, site, out / "rebuild-cache")
        if v is None:
            raise RuntimeError("no radio map could be built from the surveys")
        server.load_map(site)
        say(f"[pipeline] radio map version {v} rebuilt from {n_lab} labelled scans of the stored surveys", flush=True)
        results = []
        with cf.ThreadPoolExecutor(workers) as ex:
            futs = [ex.submit(run_agent, p, "phone", speed) for p in others]
            for i, f in enumerate(cf.as_completed(futs), 1):
                results.append(f.result())
                say(f"\r[pipeline] phone clients finished {i}/{len(others)} (replayed at {speed:g}x)", end="", flush=True)
        say(flush=True)
    finally:
        server.stop()
    return sorted(results, key=lambda x: x[1].device)


def _wifi_errors(raw_fixes, wp_t, wp_xy) -> np.ndarray:
    return _fused_errors([(f[0], f[1], f[2]) for f in raw_fixes], wp_t, wp_xy)


def run_demo(out: Path, sim: bool = False, speed: float = 20.0, workers: int = 4) -> int:
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
    else:
        traces = find_ilc_traces(ILC_SITE1_F1)
        plan = read_ilc_site(ILC_SITE1_F1)
    survey, others = traces[::2] + traces[1::4], traces[3::4]
    results = run_pipeline(survey, others, out, speed, workers)
    all_pdr, all_fused = [], []
    print(f"{'client':<28} {'waypoints':>9} {'PDR alone mean':>15} {'fused mean':>11} {'fixes used':>11}")
    for tr, r in results:
        e_p = _pdr_only_errors(r.step_events, tr.waypoints.t, tr.waypoints.pos_enu)
        e_f = _fused_errors(r.poses, tr.waypoints.t, tr.waypoints.pos_enu)
        all_pdr += e_p.tolist()
        all_fused += e_f.tolist()
        print(f"{r.device:<28} {len(tr.waypoints) - 1:9d} {np.nanmean(e_p) if e_p.size else float('nan'):14.2f}m {np.nanmean(e_f):10.2f}m {r.fixes_accepted:5d}/{r.fixes_received:<5d}")
    sp, sf = summarize_errors(all_pdr), summarize_errors(all_fused)
    print(f"overall at {sf.n} waypoints: PDR alone mean {sp.mean:.2f} m (p75 {sp.p75:.2f}), fused mean {sf.mean:.2f} m (p75 {sf.p75:.2f})")
    _write_outputs(out, plan, results)
    print(f"[demo] done in {time.monotonic() - t_start:.1f} s; outputs in {out} (demo.png, demo.geojson, poses/)")
    return 0


def run_fusion_eval(site_dir: str, out: Path, replay_every: int = 4, every: int = 1, workers: int = 4, speed: float = 20.0) -> int:
    """``hybridloc eval fusion``: surveys build the map; every ``replay_every``-th trace is a phone client."""
    traces = find_ilc_traces(site_dir)[::every]
    if len(traces) < 4:
        raise ValueError(f"too few Indoor Location Competition traces under {site_dir}")
    others = traces[::replay_every]
    survey = [t for t in traces if t not in set(others)]
    t0 = time.monotonic()
    results = run_pipeline(survey, others, out, speed=speed, workers=workers)
    e_pdr, e_wifi, e_fused, floor_hits = [], [], [], []
    for tr, r in results:
        wt, wxy = tr.waypoints.t, tr.waypoints.pos_enu
        e_pdr += _pdr_only_errors(r.step_events, wt, wxy).tolist()
        e_wifi += _wifi_errors(r.raw_fixes, wt, wxy).tolist()
        e_fused += _fused_errors(r.poses, wt, wxy).tolist()
        if r.poses:
            pt = np.array([p[0] for p in r.poses])
            for t in wt[1:]:
                k = int(np.searchsorted(pt, t, side="right")) - 1
                if k >= 0:
                    floor_hits.append(r.poses[k][3] == tr.floor)
    sp, sw, sf = summarize_errors(e_pdr), summarize_errors(e_wifi), summarize_errors(e_fused)
    print(f"fusion through the real client and server path (Zenoh loopback, SQLite): {len(survey)} survey traces -> radio map; "
          f"{len(results)} phone clients replayed, causal, {time.monotonic() - t0:.0f} s")
    for name, s in (("PDR only (oracle start pose)", sp), ("WiFi only (server fixes)", sw), ("fused (causal)", sf)):
        print(f"  {name:<30} at waypoints: mean {s.mean:.2f} m, median {s.median:.2f}, p75 {s.p75:.2f}, p95 {s.p95:.2f} (n={s.n})")
    print(f"  fused floor hit {100 * np.mean(floor_hits):.1f}% (n={len(floor_hits)}); goal: fused mean <= 3 m, floor >= 97 %, "
          f"fused >= 30 % below WiFi-only ({100 * (1 - sf.mean / sw.mean):+.0f}%) and below PDR-only ({100 * (1 - sf.mean / sp.mean):+.0f}%)")
    return 0


def _write_outputs(out: Path, plan, results) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .io.writers import floorplan_features, point_features, write_geojson
    from .types import Trajectory

    fig, ax = plt.subplots(figsize=(11, 8))
    fl = plan.floors[0]
    for poly in fl.outline.geoms:
        ax.plot(*poly.exterior.xy, color="0.3", lw=1)
    for _, room in fl.rooms:
        ax.fill(*room.exterior.xy, color="0.9", ec="0.75", lw=0.5)
    feats = floorplan_features(plan)
    colors = plt.cm.tab10.colors
    for i, (tr, r) in enumerate(results):
        c = colors[i % len(colors)]
        wp = tr.waypoints.pos_enu
        ax.plot(wp[:, 0], wp[:, 1], "o--", color=c, ms=4, lw=0.8, alpha=0.6)
        if r.poses:
            xy = np.array([[p[1], p[2]] for p in r.poses])
            ax.plot(xy[:, 0], xy[:, 1], "-", color=c, lw=1.6, label=r.device)
            t = np.array([p[0] for p in r.poses])
            order = np.argsort(t, kind="stable")
            tt, idx = np.unique(t[order], return_index=True)
            feats.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": xy[order][idx].round(3).tolist()},
                          "properties": {"kind": "track", "device": r.device}})
            # a containment-style disc of 2 sigma at the last fix, for the eye
            last = r.poses[-1]
            circ = plt.Circle((last[1], last[2]), 2.45 * max(last[4], last[5]), color=c, alpha=0.15)
            ax.add_patch(circ)
        feats += point_features(tr.waypoints.t, wp, kind="true_waypoint", trace=Path(tr.path).name)
        _ = Trajectory
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("hybridloc demo: fused tracks (solid), true waypoints (dashed), 95 % regions at the last fix")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(out / "demo.png", dpi=90)
    plt.close(fig)
    write_geojson(out / "demo.geojson", feats)

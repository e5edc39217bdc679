"""``hybridloc slam run`` and ``hybridloc slam show``: crowd SLAM over recording files."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ..errors import BadInput, MissingData
from ._common import add_batch_arguments


def _cmd_slam_run(args: argparse.Namespace) -> int:
    from ..io.msft import find_ilc_traces, read_ilc_site
    from ..progress import Progress
    from ..radio.radiomap import RadioMap
    from ..slam.output import write_outputs
    from ..slam.pipeline import RELATIVE, run_slam
    from ..slam.walkgraph import walks_from_files

    site_dir = Path(args.site_dir)
    if not site_dir.is_dir():
        raise MissingData(f"{site_dir}: {'not a folder' if site_dir.exists() else 'no such folder'} (a site folder of recordings and floor plans)")
    paths = find_ilc_traces(site_dir)
    if not paths:
        raise MissingData(f"no Indoor Location Competition recordings under {site_dir}")
    plan = None
    try:
        plan = read_ilc_site(site_dir if any((d / "geojson_map.json").is_file() for d in site_dir.iterdir() if d.is_dir()) else site_dir.parent)
    except Exception:  # noqa: BLE001 - a site without plans still runs (no plan anchoring)
        plan = None
    rmap = RadioMap.load(args.map) if args.map else None
    t0 = time.monotonic()
    bar = Progress("[slam] reading walks", len(paths))
    loaded = walks_from_files(paths, marks=args.marks == "keep", workers=args.workers, progress=lambda i, n: bar.update(i))
    bar.close()
    walks = [w for w, _ in loaded]
    names = [p.name.split(".")[0] for p in paths]
    stages: dict = {}

    def progress(stage: str, floor: str, done: int, total: int) -> None:
        if stage not in stages:
            stages[stage] = Progress(f"[slam] {stage}", total)
        stages[stage].update(done, floor)

    res = run_slam(walks, plan, rmap, names=names, progress=progress)
    for p in stages.values():
        p.close()
    site = walks[0].site if walks else site_dir.name
    n_scans = len(res.labels)
    res.stats = {
        "site_dir": str(site_dir.resolve()),
        "walks": len(walks),
        "marks": args.marks,
        "map": args.map or "",
        "labelled_scans": n_scans,
        "loops": len(res.loops),
        "loops_accepted": sum(lp.accepted for lp in res.loops),
        "seconds": time.monotonic() - t0,
    }
    got = write_outputs(args.out, res, plan, site)
    print(
        f"crowd SLAM of {len(walks)} walks of {site_dir} ({args.marks} marks{', map ' + args.map if args.map else ''}) in {time.monotonic() - t0:.0f} s -> {args.out}"
    )
    for fname, fs in sorted(res.floors.items()):
        st = [s for s in fs.status]
        n_anch = sum(s != RELATIVE for s in st)
        acc = sum(lp.accepted for lp in fs.loops)
        by = {k: st.count(k) for k in sorted(set(st))}
        print(f"  floor {fname}: {len(st)} walks, anchored {n_anch} ({by}), loops {len(fs.loops)} candidates, {acc} accepted")
    print(
        f"  files: tracks.csv ({got['track_rows']} rows), raw.csv, tracks.geojson, loops.csv ({got['loops']} loops), "
        + ", ".join(Path(p).name for p in got["maps"].values())
    )
    print(
        json.dumps(
            {
                "walks": len(walks),
                "labelled_scans": n_scans,
                "loops": len(res.loops),
                "loops_accepted": res.stats["loops_accepted"],
                "seconds": round(res.stats["seconds"], 1),
            }
        )
    )
    return 0


def _db_tracks(args: argparse.Namespace):
    """(tracks, raw, loops, plan) of ``slam show --db URL --site S`` in the shapes :func:`plot_slam` reads:
    the walks' current corrected tracks, their dead reckoning started where the corrected track starts,
    the current loop audit, the floor plan stored with ``floorplan import``."""
    import numpy as np

    from ..pdr.deadreckoning import DeadReckoning
    from ..server.store import Store
    from ._common import check_db_driver

    check_db_driver(args.db)
    st = Store(args.db)
    try:
        if args.site not in {w.site for w in st.walks(args.site)}:
            raise MissingData(f"no walks of site {args.site!r} in {args.db}")
        stored = st.slam.tracks(args.site)
        if not stored:
            raise MissingData(
                f"no corrected tracks of site {args.site!r} in {args.db} (is a server with SLAM running? 'hybridloc slam rebuild --db {args.db} --site {args.site}')"
            )
        loops = [
            {
                "walk_a": str(lp.walk_a),
                "t_a": lp.t_a,
                "walk_b": str(lp.walk_b),
                "t_b": lp.t_b,
                "accepted": "1" if lp.accepted else "0",
                "reason": lp.reason,
                "floor": lp.floor,
            }
            for lp in st.slam.loops(args.site)
        ]
        tracks, raw = {}, {}
        for wid, tr in stored.items():
            walk = st.read_walk(wid)
            dr = DeadReckoning.from_steps(list(walk.steps), covariance=False) if len(walk.steps) >= 1 else None
            fl = np.asarray(tr.floor)
            for f in dict.fromkeys(tr.floor):
                sel = fl == f
                key = f"{wid}\0{f}"
                tracks[key] = {"walk": str(wid), "t": tr.t[sel], "xy": tr.pos_enu[sel], "floor": f, "anchored": tr.anchored}
                if dr is not None:
                    q = dr.position_at(tr.t[sel])[:, :2]
                    raw[key] = {"walk": str(wid), "t": tr.t[sel], "xy": q - q[0] + tr.pos_enu[sel][0], "floor": f, "anchored": tr.anchored}
        plan = st.load_floor_plan(args.site)
    finally:
        st.close()
    if args.floorplan:
        from ..io.msft import read_ilc_site

        plan = read_ilc_site(args.floorplan)
    return tracks, raw, loops, plan


def _cmd_slam_show(args: argparse.Namespace) -> int:
    from ..io.msft import read_ilc_site
    from ..slam.output import read_loops_csv, read_tracks_csv

    if args.db is not None or args.dir is None:
        if args.db is None or args.site is None or args.dir is not None:
            raise BadInput("slam show takes a 'slam run' folder DIR, or --db URL --site S (not both)")
        tracks, raw, loops, plan = _db_tracks(args)
        floors = sorted({v["floor"] for v in tracks.values()})
        if args.floor not in floors:
            raise BadInput(f"floor {args.floor!r} has no corrected track of site {args.site!r} (floors: {floors})")
        return _plot(args, plan, tracks, raw, loops)
    d = Path(args.dir)
    if not (d / "tracks.csv").is_file():
        raise MissingData(f"{d}: no tracks.csv (run 'hybridloc slam run SITE_DIR --out {d}' first)")
    tracks = read_tracks_csv(d / "tracks.csv")
    raw = read_tracks_csv(d / "raw.csv") if (d / "raw.csv").is_file() else None
    loops = read_loops_csv(d / "loops.csv") if (d / "loops.csv").is_file() else []
    floors = sorted({v["floor"] for v in tracks.values()})
    if args.floor not in floors:
        raise BadInput(f"floor {args.floor!r} is not in {d}/tracks.csv (floors: {floors})")
    plan = None
    site_dir = args.floorplan
    if site_dir is None and (d / "summary.json").is_file():
        site_dir = json.loads((d / "summary.json").read_text(encoding="utf-8")).get("site_dir")
    if site_dir and Path(site_dir).is_dir():
        plan = read_ilc_site(site_dir)
    return _plot(args, plan, tracks, raw, loops)


def _plot(args: argparse.Namespace, plan, tracks: dict, raw: dict | None, loops: list[dict]) -> int:
    from ..slam.output import plot_slam
    from ._common import pyplot

    plt = pyplot("slam show")
    fig, ax = plt.subplots(figsize=(11, 9))
    try:
        got = plot_slam(ax, plan, tracks, raw, loops, args.floor)
        fig.tight_layout()
        fig.savefig(args.out, dpi=args.dpi)
    finally:
        plt.close(fig)
    print(f"floor {args.floor}: {got['walks']} walks, {got['accepted']} accepted and {got['rejected']} rejected loops -> {args.out}")
    return 0


def _cmd_slam_rebuild(args: argparse.Namespace) -> int:
    from ._common import batch_client, check_batch_arguments, check_db_driver, executor_of

    check_batch_arguments(args)
    if args.processes is not None and not args.serial:
        raise BadInput("--processes spreads a --serial run's groups of floors over forked processes: it needs --serial")
    if args.processes is not None and args.processes < 1:
        raise BadInput(f"--processes must be at least 1 (got {args.processes})")
    check_db_driver(args.db)
    from ..server.db import sqlite_path
    from ..server.slam_batch import site_floors, sites_with_walks
    from ..server.store import Store

    path = sqlite_path(args.db)
    if path is not None and not Path(path).is_file():
        raise MissingData(f"{path}: no such database (the server's SQLite file, or a database URL)")
    st = Store(args.db)
    try:
        sites = [args.site] if args.site else sites_with_walks(st)
        if not sites:
            raise MissingData(f"no ended walks in {args.db}: nothing to re-solve")
        known = site_floors(st, args.site) if args.site else []
        if args.site and not known:
            raise BadInput(f"site {args.site!r} has no ended walks with a floor in {args.db}")
        if args.floor and args.site is None:
            raise BadInput("--floor needs --site")
        if args.floor and args.floor not in known:  # before any cluster starts (run_batch says the same)
            raise BadInput(f"site {args.site!r} has no walks on floor(s) {args.floor} (floors: {', '.join(known)})")
        with batch_client(args, "[slam rebuild]") as client:
            out = _rebuild_sites(st, sites, args, client)
            executor = executor_of(args, client)
            if args.processes is not None:
                executor["processes"] = args.processes
    finally:
        st.close()
    print(json.dumps({"sites": out, "executor": executor}))
    return 0


def _rebuild_sites(st, sites: list[str], args: argparse.Namespace, client) -> list[dict]:
    from ..progress import Progress
    from ..server.slam_batch import run_batch

    out = []
    for site in sites:
        bars: dict[str, Progress] = {}

        def progress(stage: str, floor: str, done: int, total: int, site: str = site, bars: dict = bars) -> None:
            label = " ".join(x for x in ("[slam rebuild]", site, "" if stage == "floors" else floor, stage) if x)
            if stage == "done":
                return
            bar = bars.get(label)
            if bar is None:
                bar = bars[label] = Progress(label, total, bar_width=30 if stage == "floors" else 0)
            bar.total = total
            bar.update(done, floor if stage == "floors" else "")

        t0 = time.monotonic()
        sm = run_batch(st, site, [args.floor] if args.floor else None, progress, client=client, processes=args.processes or 1)
        for b in bars.values():
            b.close()
        summary = st.slam.summary(site)
        how = f"resumed run {sm.run_id} after floor(s) {', '.join(sm.floors_skipped)}" if sm.floors_skipped else f"run {sm.run_id}"
        if sm.resumed and not sm.floors_skipped:
            how = f"resumed run {sm.run_id} (no floor was finished)"
        mv = f"radio map version {sm.map_version}" if sm.map_version is not None else "no new radio map (too few labelled scans)"
        cov = f"{100 * sm.coverage:.0f} %" if sm.coverage is not None else "-"
        print(
            f"site {site}: {mv} ({how}, floors {', '.join(sm.floors)}, {time.monotonic() - t0:.0f} s); "
            f"walks corrected {sm.walks.get('corrected', 0)}, relative {sm.walks.get('relative', 0)}, quarantined {len(sm.quarantined)}; "
            f"loops accepted {sm.loops_accepted}, rejected {sm.loops_rejected}; coverage {cov}"
        )
        out.append(
            {
                "site": site,
                "run": sm.run_id,
                "resumed": sm.resumed,
                "floors": sm.floors,
                "floors_skipped": sm.floors_skipped,
                "map_version": sm.map_version,
                "walks_corrected": sm.walks.get("corrected", 0),
                "walks_relative": sm.walks.get("relative", 0),
                "walks_quarantined": len(sm.quarantined),
                "loops_accepted": sm.loops_accepted,
                "loops_rejected": sm.loops_rejected,
                "coverage": sm.coverage,
                "site_walks_corrected": summary["walks_corrected"],
                "seconds": round(time.monotonic() - t0, 1),
            }
        )
    return out


def register(sub) -> None:
    sp = sub.add_parser("slam", help="crowd SLAM: drift-corrected walks, loop closures and a crowd radio map")
    ssub = sp.add_subparsers(dest="slam_command", required=True)
    r = ssub.add_parser("run", help="crowd SLAM over the recordings of a site folder")
    r.add_argument("site_dir", help="Indoor Location Competition site folder (floor folders with path_data_files and plans)")
    r.add_argument("--out", required=True, help="output folder (tracks.csv, tracks.geojson, loops.csv, crowdmap_<technology>.npz)")
    r.add_argument(
        "--marks", choices=("keep", "strip"), default="keep", help="use the survey marks found in the files (keep) or drop them first (strip)"
    )
    r.add_argument("--map", metavar="FILE", help="an existing radio map whose fixes anchor the walks (heavy-tailed)")
    r.add_argument("--workers", type=int, default=2, help="processes for reading the walks (phone PDR)")
    r.set_defaults(func=_cmd_slam_run)
    s = ssub.add_parser("show", help="raw and corrected walks and loops of one floor over its plan (from a 'slam run' folder or the server database)")
    s.add_argument("dir", nargs="?", help="a 'slam run' output folder (or give --db and --site)")
    s.add_argument("--db", help="the server database (SQLite file or URL): its current corrected tracks and loop audit")
    s.add_argument("--site", help="the site, with --db")
    s.add_argument("--floor", required=True)
    s.add_argument("--out", required=True, help="PNG file")
    s.add_argument("--floorplan", metavar="SITE_DIR", help="site folder of the plan (default: the one slam run read)")
    s.add_argument("--dpi", type=int, default=130)
    s.set_defaults(func=_cmd_slam_show)
    rb = ssub.add_parser(
        "rebuild",
        help="re-solve a site's stored walks in batch and store a new crowd radio map (resumable per floor, atomic; the server loads it)",
    )
    rb.add_argument("--db", help="the server database (SQLite file or URL)")
    rb.add_argument("--site", help="the site (default: every site with ended walks)")
    rb.add_argument("--floor", help="re-solve this floor only (needs --site)")
    add_batch_arguments(rb)
    rb.add_argument(
        "--processes",
        type=int,
        metavar="N",
        help="with --serial: the site's connected groups of floors side by side in this process and N-1 forked copies of it (the same results)",
    )
    rb.set_defaults(func=_cmd_slam_rebuild, _parser=rb, _required=("db",), _settings={"db": "db"})

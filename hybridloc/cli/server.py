"""The server side: ``serve``, ``db upgrade``, ``status`` and the database's ``map import / export / rebuild``."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from ..errors import BadInput, MissingData
from ..progress import Progress
from ._common import add_batch_arguments, batch_client, check_batch_arguments, check_db_driver, security


def _dashboard_access(args: argparse.Namespace):
    """(Access, the URL's query: ``?token=...`` for a generated token, else "") of the --http-token /
    --http-tokens options (or the settings); no token at all: one is generated and printed."""
    from ..server.dashboard.auth import Access, check_token, new_token, read_tokens_file

    tokens: dict = {}
    query = ""
    if args.http_tokens:
        tokens.update(read_tokens_file(args.http_tokens))
    if args.http_token:
        tokens[check_token(args.http_token, "--http-token")] = None
    if not tokens:
        token = new_token()
        tokens[token] = None
        query = f"?token={token}"
    return Access(tokens), query


def _dashboard_options(args: argparse.Namespace) -> tuple[str, int]:
    from ..server.dashboard.run import parse_listen

    host, port = parse_listen(args.http)
    for name, v in (("--http-stale", args.http_stale), ("--http-lost", args.http_lost)):
        if not v > 0:
            raise BadInput(f"{name} must be > 0 s, got {v:g}")
    if args.http_lost <= args.http_stale:
        raise BadInput(f"--http-lost ({args.http_lost:g} s) must be longer than --http-stale ({args.http_stale:g} s)")
    if host not in ("127.0.0.1", "localhost", "::1"):
        print(
            f"warning: the dashboard serves plain HTTP on {host}, beyond loopback: its token and data cross the network in clear "
            "(put a TLS proxy in front of it)",
            file=sys.stderr,
        )
    return host, port


def _start_dashboard(args: argparse.Namespace, session, store, access, query: str):
    from ..server.dashboard.run import Dashboard

    host, port = _dashboard_options(args)
    dash = Dashboard(session, store, access, host, port, stale_after_s=args.http_stale, lost_after_s=args.http_lost).start()
    how = "" if query else " (open it as /?token=TOKEN with your token)"
    print(f"hybridloc dashboard on {dash.url}{query}{how}", flush=True)
    return dash


def _count_or_auto(text: str) -> int | str:
    """``--ingest-workers``: a whole number >= 0 or ``auto``."""
    if text == "auto":
        return text
    try:
        return int(text)  # a negative count is refused with the other options' checks, in one line
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0 or auto, got {text!r}") from None


def _cmd_serve(args: argparse.Namespace) -> int:
    check_db_driver(args.db)
    from ..server.service import Server, serve_forever

    dashboard = None
    if args.http:
        _dashboard_options(args)  # refuse bad options before anything starts
        access, query = _dashboard_access(args)

        def dashboard(server):
            return _start_dashboard(args, server.session, server.store, access, query)

    if args.locate_workers < 0:
        raise BadInput(f"--locate-workers must be >= 0, got {args.locate_workers}")
    from ..server.ingest_pool import resolve_ingest_workers

    if isinstance(args.ingest_workers, int) and args.ingest_workers < 0:
        raise BadInput(f"--ingest-workers must be >= 0, got {args.ingest_workers}")
    try:
        ingest_workers = resolve_ingest_workers(args.ingest_workers, str(args.db))
    except ValueError as exc:
        raise BadInput(f"--ingest-workers: {exc}") from None
    slam_sites, slam_options = [], None
    if args.slam is not False and args.site:
        from ..server.slam_worker import SlamOptions

        for name, v in (("--slam-idle", args.slam_idle), ("--slam-interval", args.slam_interval)):
            if v < 0:
                raise BadInput(f"{name} must be >= 0 s, got {v:g}")
        if args.slam_batch_every < 0:
            raise BadInput(f"--slam-batch-every must be >= 0, got {args.slam_batch_every}")
        if not math.isfinite(args.slam_batch_share) or not 0.0 <= args.slam_batch_share <= 10.0:
            raise BadInput(f"--slam-batch-share must be a share between 0 and 10, got {args.slam_batch_share:g}")
        if args.slam_processes < 0:
            raise BadInput(f"--slam-processes must be >= 0 (0: the usable cores), got {args.slam_processes}")
        if args.slam_grow_map and args.method == "prob":
            raise BadInput(
                "--slam-grow-map ([slam] grow_map) serves walks' labels to the kNN locator; the cell likelihood (--method prob) is built from a whole map"
            )
        slam_sites = list(args.site)
        slam_options = SlamOptions(
            idle_timeout_s=args.slam_idle,
            batch_every_walks=args.slam_batch_every,
            batch_share=args.slam_batch_share,
            batch_interval_s=args.slam_interval,
            batch_processes=args.slam_processes,
            grow_map=bool(args.slam_grow_map),
        )
    server = Server(
        args.endpoint,
        args.db,
        security(args),
        method=args.method,
        slam_sites=slam_sites,
        slam_options=slam_options,
        sites=args.site,
        connect=args.connect,
        locate_workers=args.locate_workers,
        ingest_workers=ingest_workers,
    )
    for spec in args.map or []:
        site, _, path = spec.partition("=")
        if not path:
            raise BadInput(f"--map expects SITE=FILE, got {spec!r}")
        server.load_map(site, Path(path).read_bytes())
    for site in args.site or []:
        if server.load_map(site) is None:
            print(f"warning: no stored radio map for site {site!r}", file=sys.stderr)
    for site in slam_sites:
        assert slam_options is not None
        print(
            f"crowd SLAM of site {site}: walks end after {slam_options.idle_timeout_s:g} s idle; batch re-solve every "
            f"{slam_options.batch_every_walks or '-'} walks or {slam_options.batch_interval_s:g} s"
            + ("; the served map grows at every added walk" if slam_options.grow_map else ""),
            file=sys.stderr,
        )
    serve_forever(server, dashboard)
    return 0


def _cmd_dashboard(args: argparse.Namespace) -> int:
    """The dashboard beside a running server: a Zenoh client (an operator user under --acl-devices)
    and the server's database, read only."""
    import signal
    import threading

    check_db_driver(args.db)
    if not args.http:
        raise BadInput("hybridloc dashboard needs --http HOST:PORT (or http.listen in the settings)")
    _dashboard_options(args)
    access, query = _dashboard_access(args)
    db = str(args.db)
    if "://" not in db and not Path(db).is_file():
        raise MissingData(f"{db}: no such database (the running server's --db)")
    from ..server.dashboard.run import open_session
    from ..server.store import Store

    store = Store(db, migrate=False)  # the server owns the schema
    try:
        session = open_session(args.endpoint, security(args))
    except OSError as exc:
        store.close()
        raise BadInput(str(exc)) from None
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    dash = None
    try:
        dash = _start_dashboard(args, session, store, access, query)
        while not stop.is_set():
            stop.wait(0.5)
    finally:
        if dash is not None:
            dash.stop()
        session.close()
        store.close()
    return 0


def _add_http_options(p: argparse.ArgumentParser, serve: bool) -> None:
    p.add_argument(
        "--http",
        metavar="HOST:PORT",
        help=("also serve the operator dashboard on HOST:PORT (off unless given; " if serve else "serve the dashboard on HOST:PORT (")
        + "port 0: any free port; see docs/dashboard.md)",
    )
    p.add_argument("--http-token", metavar="TOKEN", help="the dashboard's token for every site (default: one generated and printed in the URL)")
    p.add_argument("--http-tokens", metavar="FILE", help="dashboard tokens limited to sites: lines 'token: site1,site2' ('token: *': every site)")
    p.add_argument("--http-stale", type=float, metavar="S", help="the page draws a device stale S seconds after its newest pose or fix (default 10)")
    p.add_argument("--http-lost", type=float, metavar="S", help="... and lost after S seconds (default 60)")


def _cmd_db_upgrade(args: argparse.Namespace) -> int:
    check_db_driver(args.db)
    from ..server.db import make_engine
    from ..server.migrate import current_revision, upgrade

    eng = make_engine(args.db)
    upgrade(eng)
    print(f"{args.db}: schema at revision {current_revision(eng)}")
    eng.dispose()
    return 0


def _cmd_status(args: argparse.Namespace) -> int:
    from ..clients.status import query_statuses

    every = query_statuses(args.endpoint, security(args), args.timeout)
    if not every:
        print(f"no server answered on {args.endpoint}", file=sys.stderr)
        return 1
    for i, st in enumerate(sorted(every, key=lambda d: d.get("sites") or [])):
        if i:
            print()
        _print_status(st)
    return 0


def _print_status(st: dict) -> None:
    if st.get("sites"):
        print(f"server process of sites: {', '.join(st['sites'])}")
    print(f"devices online ({len(st['online'])}): {', '.join(st['online']) or '-'}")
    print("database: " + ", ".join(f"{k} {v}" for k, v in st["db"].items() if k not in ("rejections", "maps")))
    print("messages: " + ", ".join(f"{k} {v}" for k, v in sorted(st["counts"].items())))
    print("rejections stored: " + (", ".join(f"{k} {v}" for k, v in st["db"]["rejections"].items()) or "none"))
    print("radio maps: " + (", ".join(f"{k} v{v}" for k, v in st["db"]["maps"].items()) or "none"))
    by_device = st.get("rejections") or {}
    if by_device:
        print(
            "rejections by device: "
            + "; ".join(f"{dev} ({', '.join(f'{r} {n}' for r, n in sorted(by.items()))})" for dev, by in sorted(by_device.items()))
        )
    slam = st.get("slam") or {}
    for site, sm in sorted(slam.items()):
        cov = f"{100 * sm['coverage']:.0f} %" if sm.get("coverage") is not None else "-"
        mv = f"v{sm['map_version']} ({sm['map_source']})" if sm.get("map_version") is not None else "none"
        print(
            f"slam {site}: walks corrected {sm['walks_corrected']}, relative {sm['walks_relative']}, quarantined {sm['walks_quarantined']}, "
            f"failed {sm['walks_failed']}, pending {sm['walks_pending']}; loops accepted {sm['loops_accepted']}, rejected {sm['loops_rejected']}; "
            f"coverage {cov}; map {mv}"
        )
        w = sm.get("worker") or {}
        c = w.get("counts", {})
        err = w.get("last_error")
        print(
            f"  worker: added {c.get('walks_added', 0)}, quarantined {c.get('walks_quarantined', 0)}, errors {c.get('walk_errors', 0) + c.get('errors', 0)}, "
            f"batch runs {c.get('batch_runs', 0)}"
            + (f", grown into the served map {c['map_walks_grown']}" if c.get("map_walks_grown") else "")
            + (f", busy: {w['busy']}" if w.get("busy") else "")
            + (f"; last error{' (walk ' + str(err['walk']) + ')' if err.get('walk') is not None else ''}: {err['error']}" if err else "")
        )


def _cmd_map_import(args: argparse.Namespace) -> int:
    check_db_driver(args.db)
    from ..radio.radiomap import RadioMap
    from ..server.store import Store

    RadioMap.load(args.map_file)  # refuse anything that is not a radio map
    st = Store(args.db)
    v = st.save_map(args.site, Path(args.map_file).read_bytes())
    st.close()
    print(f"{args.map_file} -> site {args.site} radio map version {v} in {args.db}")
    return 0


def _cmd_map_export(args: argparse.Namespace) -> int:
    check_db_driver(args.db)
    from ..server.store import Store

    st = Store(args.db)
    got = st.load_map(args.site)
    st.close()
    if got is None:
        raise MissingData(f"no radio map stored for site {args.site!r}")
    Path(args.out).write_bytes(got[1])
    print(f"site {args.site} radio map version {got[0]} -> {args.out}")
    return 0


def _cmd_map_rebuild(args: argparse.Namespace) -> int:
    check_batch_arguments(args)
    check_db_driver(args.db)
    from ..server.rebuild import rebuild
    from ..server.store import Store

    st = Store(args.db)
    bar = Progress("[rebuild] devices", 0, bar_width=30)  # the device count comes with each update

    def progress(i, n, dev):
        bar.total = n
        bar.update(i, f"({dev})")

    try:
        with batch_client(args, "[rebuild]") as client:
            v, n, relabelled = rebuild(st, args.site, args.cache or (str(args.db) + ".rebuild"), progress, client=client)
    finally:
        st.close()
    if v is None:
        print(f"site {args.site}: no survey (devices with at least two marks) in {args.db}; no map built", file=sys.stderr)
        return 1
    print(f"site {args.site}: radio map version {v} from {n} labelled scans ({relabelled} device(s) relabelled, the rest from the cache)")
    return 0


def register(sub) -> None:
    sv = sub.add_parser("serve", help="run the server: Zenoh router + ingest + locate/map/status services")
    sv.add_argument("--endpoint", help="Zenoh endpoint to listen on (default tcp/127.0.0.1:7447)")
    sv.add_argument("--db", help="SQLite file or database URL (postgresql+psycopg://...)")
    sv.add_argument("--map", action="append", metavar="SITE=FILE", help="load a radio map file for a site (stored as a new version)")
    sv.add_argument(
        "--site",
        action="append",
        help="serve this site only (repeatable): its ingest, locate, newest stored radio map and crowd SLAM (default: every site's ingest and locate)",
    )
    sv.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="join another server's router (repeatable): processes serving different sites on one mesh",
    )
    sv.add_argument("--method", choices=("knn", "prob"), help="positioning method of the locate service (default knn)")
    sv.add_argument(
        "--locate-workers",
        type=int,
        metavar="N",
        help="worker processes that answer the stored scans beside ingest (default 0: the server's own locate thread)",
    )
    sv.add_argument(
        "--ingest-workers",
        type=_count_or_auto,
        metavar="N|auto",
        help="worker processes that decode and store the batches, each device's in one of them, in order "
        "(0: the server's own ingest thread; default auto: 2 when the server may use 2 cores or more and its "
        "database is a file or a server, else 0)",
    )
    sv.add_argument("--users", help="user:password dictionary file (enables authentication)")
    sv.add_argument("--user", help="with --connect under authentication: the server user this process presents to the other routers")
    sv.add_argument("--password", help="... and its password")
    sv.add_argument("--acl-devices", help="file listing device ids (one per line, or the users file): each may use only its own keys")
    sv.add_argument(
        "--acl-operator",
        action="append",
        metavar="USER",
        help="with --acl-devices: a read-only operator user (repeatable; default operator): may hear poses, fixes, tracks, "
        "progress and map versions and ask the status and maps, never a batch or an ack (hybridloc dashboard --user USER)",
    )
    sv.add_argument("--tls-cert", help="server certificate (PEM) for tls/ endpoints")
    sv.add_argument("--tls-key", help="server private key (PEM)")
    sv.add_argument("--no-slam", dest="slam", action="store_const", const=False, help="no crowd-SLAM worker for the --site sites")
    sv.add_argument("--slam-idle", type=float, metavar="S", help="a walk whose device sent nothing for S seconds is finished (default 180)")
    sv.add_argument("--slam-batch-every", type=int, metavar="N", help="re-solve the site in batch after N new walks (default 25; 0: not by count)")
    sv.add_argument(
        "--slam-batch-share",
        type=float,
        metavar="F",
        help="... and at least F times the walks the last batch solved (default 0: N alone; 0.25: batches at geometrically spaced site sizes)",
    )
    sv.add_argument("--slam-interval", type=float, metavar="S", help="... or S seconds after the last batch run (default 3600; 0: not by time)")
    sv.add_argument(
        "--slam-processes",
        type=int,
        metavar="N",
        help="a batch re-solve's connected groups of floors solved side by side in N processes (default 0: the usable cores; same results)",
    )
    sv.add_argument(
        "--slam-grow-map",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the served map grows at every added walk: its scans at their corrected positions answer scans on top of the map version "
        "until a batch's version holds them (kNN only; default off: docs/slam.md)",
    )
    _add_http_options(sv, serve=True)
    sv.set_defaults(
        func=_cmd_serve,
        _settings={
            "http": "http.listen",
            "http_token": "http.token",
            "http_tokens": "http.tokens_file",
            "http_stale": "http.stale_s",
            "http_lost": "http.lost_s",
            "endpoint": "endpoint",
            "db": "db",
            "site": "site[]",
            "method": "method",
            "locate_workers": "locate_workers",
            "ingest_workers": "ingest_workers",
            "users": "security.users",
            "acl_devices": "security.acl_devices",
            "tls_cert": "security.tls_cert",
            "tls_key": "security.tls_key",
            "slam": "slam.enabled",
            "slam_idle": "slam.idle_s",
            "slam_batch_every": "slam.batch_every",
            "slam_batch_share": "slam.batch_share",
            "slam_interval": "slam.interval_s",
            "slam_processes": "slam.processes",
            "slam_grow_map": "slam.grow_map",
        },
    )

    dp = sub.add_parser("dashboard", help="the operator dashboard beside a running server (a live web page; see docs/dashboard.md)")
    dp.add_argument("--endpoint", help="the server's Zenoh endpoint")
    dp.add_argument("--db", help="the server's database (read only)")
    _add_http_options(dp, serve=False)
    dp.add_argument("--user", help="Zenoh user (under --acl-devices: a read-only operator user, default name operator)")
    dp.add_argument("--password")
    dp.add_argument("--tls-ca", help="CA of the server's certificate for tls/ endpoints")
    dp.set_defaults(
        func=_cmd_dashboard,
        _settings={
            "endpoint": "endpoint",
            "db": "db",
            "http": "http.listen",
            "http_token": "http.token",
            "http_tokens": "http.tokens_file",
            "http_stale": "http.stale_s",
            "http_lost": "http.lost_s",
            "user": "security.user",
            "password": "security.password",
            "tls_ca": "security.tls_ca",
        },
    )

    dbp = sub.add_parser("db", help="database maintenance")
    dbsub = dbp.add_subparsers(dest="db_command", required=True)
    du = dbsub.add_parser("upgrade", help="apply the Alembic migrations up to the newest schema")
    du.add_argument("--db")
    du.set_defaults(func=_cmd_db_upgrade, _settings={"db": "db"})

    stp = sub.add_parser("status", help="ask a running server: devices online, message and rejection counts, map versions")
    stp.add_argument("--endpoint")
    stp.add_argument("--user")
    stp.add_argument("--password")
    stp.add_argument("--tls-ca")
    stp.add_argument("--timeout", type=float, default=5.0)
    stp.set_defaults(
        func=_cmd_status, _settings={"endpoint": "endpoint", "user": "security.user", "password": "security.password", "tls_ca": "security.tls_ca"}
    )


def register_map(msub) -> None:
    """``map import``, ``map export``, ``map rebuild``: radio maps in the server's database."""
    mi = msub.add_parser("import", help="store a radio map file as the site's newest version on the server database")
    mi.add_argument("map_file", metavar="MAP")
    mi.add_argument("--site")
    mi.add_argument("--db", help="database file or URL (default hybridloc.db)")
    mi.set_defaults(func=_cmd_map_import, _parser=mi, _required=("site",), _settings={"site": "site", "db": "db"})
    me = msub.add_parser("export", help="write the site's newest radio map from the server database to a file")
    me.add_argument("--site")
    me.add_argument("--db")
    me.add_argument("--out", required=True, metavar="MAP")
    me.set_defaults(func=_cmd_map_export, _parser=me, _required=("site",), _settings={"site": "site", "db": "db"})

    mr = msub.add_parser("rebuild", help="rebuild a site's radio map from the surveys stored in the database (incremental, resumable)")
    mr.add_argument("--site")
    mr.add_argument("--db")
    mr.add_argument("--cache", help="folder for per-device labelled scans (default <db>.rebuild)")
    add_batch_arguments(mr)
    mr.set_defaults(func=_cmd_map_rebuild, _parser=mr, _required=("site",), _settings={"site": "site", "db": "db"})

"""``hybridloc client phone|foot|survey``: a client agent replaying a recording (or a live stream) against a server."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import BadInput, MissingData, check_input_file
from ._common import load_imu, open_calibration, parse_floats, security, stem_safe


def _cmd_client(args: argparse.Namespace) -> int:
    from ..clients.agent import (
        Agent,
        PoseWriter,
        open_client,
        replay_foot,
        replay_phone,
    )

    if bool(args.replay) == bool(args.live):
        raise BadInput("give one input: --replay FILE (a recording) or --live SOURCE (a live line stream, - for stdin)")
    if args.live and args.kind != "phone":
        raise BadInput("--live is for phone clients (IMU samples and WiFi scans as lines); foot and survey clients replay recordings")
    if args.live and not args.rate:
        raise BadInput("--live needs the IMU sample rate: --rate HZ")
    device = args.device or f"{args.kind}-{stem_safe(args.replay) if args.replay else 'live'}"
    spool = args.spool or f".hybridloc-spool/{device}"
    spool_cap = None if args.spool_max_mb is None else int(args.spool_max_mb * 1e6)
    from ..clients.uplink import MIN_SPOOL_BYTES  # here: the uplink imports zenoh, slow for every other command

    if spool_cap is not None and spool_cap < MIN_SPOOL_BYTES:
        raise BadInput(f"--spool-max-mb {args.spool_max_mb} is below one batch ({MIN_SPOOL_BYTES / 1e6:g} MB)")
    pose = PoseWriter(args.pose_out, args.pose_format)
    init = parse_floats(args.start, 3, "--start x,y,sigma") if args.start else None
    # a phone's or survey's step-length calibration (foot clients have no such options)
    cal, cal_path = open_calibration(getattr(args, "calibration", None), getattr(args, "update_calibration", False), "height")
    length_model = cal.model if cal is not None else None
    pdr_config = None
    if args.kind != "foot":
        from ..pdr import PhonePdrConfig

        pdr_config = PhonePdrConfig(walking_offset=args.offset, estimate_offset=args.estimate_offset)
    # every input file is read before the session opens: a bad one is one line, not a half-run client
    plan = None
    if args.floorplan:
        from ..io.msft import read_ilc_site

        plan = read_ilc_site(args.floorplan)
    imu = tr = local = None
    if args.replay:
        check_input_file(args.replay, "recording")
    if args.replay and args.kind == "foot":
        imu, *_ = load_imu(args.replay, args.format, args.rate)
    elif args.replay:
        from ..io.msft import read_ilc_trace

        tr = read_ilc_trace(args.replay)
        if tr.imu is None:
            raise MissingData(f"{args.replay}: no IMU data to replay ({tr.report.summary()})")
        if args.fixes:
            from ..io.fixes import read_fixes_csv

            local, rep = read_fixes_csv(args.fixes)
            if not rep.ok:
                print(f"{args.fixes}: {rep.summary()}", file=sys.stderr)
    pdr = None
    with open_client(args.endpoint, security(args), log=lambda m: print(f"{device}: {m}", file=sys.stderr)) as s:
        fusion = None
        live_map: dict = {}  # the particle filter follows the site's new map versions (map/version key)
        if args.filter == "particle":
            from ..clients.agent import fetch_map, walk_prior, walk_prior_refresh
            from ..fusion import ParticleFusion

            got = fetch_map(s, args.site)
            prior = walk_prior(got[0], plan) if got is not None else None
            if prior is None:
                print(f"{device}: the server has no radio map for {args.site!r}: the particle filter runs without a walk prior", file=sys.stderr)
            from ..geo import corridor_axes

            fusion = ParticleFusion(prior, init=init, floor=args.floor, corridor_axes=corridor_axes(plan))
            live_map = {"map_refresh": walk_prior_refresh(fusion, plan), "map_version": got[1].version if got is not None and got[1] else None}
        elif args.filter == "kourogi":
            from ..fusion import KourogiFusion

            fusion = KourogiFusion(init=init, floor=args.floor)
        elif args.floorplan:  # our Kalman filter, with the floors' grid directions (heuristic drift elimination)
            from ..fusion import LocalFusion
            from ..geo import corridor_axes

            fusion = LocalFusion(init=init, floor=args.floor, corridor_axes=corridor_axes(plan))
        if args.live:
            from ..clients.agent import live_phone

            agent = Agent(s, args.site, device, spool, pose, init=init, fusion=fusion, floor=args.floor, **live_map, max_spool_bytes=spool_cap)
            src = sys.stdin if args.live == "-" else open(args.live, encoding="utf-8")
            try:
                ls = live_phone(agent, src, args.rate, lockstep=args.lockstep, length_model=length_model, pdr_config=pdr_config)
                pdr = ls.pdr
            finally:
                if src is not sys.stdin:
                    src.close()
            print(
                f"{device}: live input: {ls.samples} IMU samples, {ls.scans} scans, {ls.bad_lines} malformed lines skipped"
                + (f" (first: {ls.first_bad})" if ls.first_bad else "")
            )
        elif args.kind == "foot":
            agent = Agent(s, args.site, device, spool, pose, init=init, fusion=fusion, floor=args.floor, **live_map, max_spool_bytes=spool_cap)
            replay_foot(agent, imu, args.speed)
        else:
            agent = Agent(
                s, args.site, device, spool, pose, tr.device_model, init=init, fusion=fusion, floor=args.floor, **live_map, max_spool_bytes=spool_cap
            )
            pdr = replay_phone(
                agent,
                tr,
                args.speed,
                survey=args.kind == "survey",
                lockstep=args.lockstep,
                local_fixes=local,
                length_model=length_model,
                pdr_config=pdr_config,
            )
        r = agent.close(wait=args.ack_timeout)
    if args.kind != "foot" and args.update_calibration and pdr is not None:
        _client_update_calibration(device, args, cal, cal_path, pdr, agent.fusion, tr if args.replay else None)
    print(
        f"{device}: {r.steps} steps, {r.batches} batches ({r.acked} acknowledged; the rest stay in the spool {spool}), "
        f"{r.fixes_received} fixes received, {r.fixes_accepted} accepted"
        + (f", {r.tracks_applied} of {r.tracks_received} corrected tracks applied" if r.tracks_received else "")
        + (f", {r.maps_fetched} new map versions" if r.maps_fetched else "")
        + (
            f"; spool full: the data of {r.spool_dropped.get('batches', 0)} oldest batches dropped "
            f"({r.spool_dropped.get('steps', 0)} steps, {r.spool_dropped.get('scans', 0)} scans, {r.spool_dropped.get('marks', 0)} marks)"
            + (f", {r.spool_dropped['unspooled']} batches held in memory only" if r.spool_dropped.get("unspooled") else "")
            if r.spool_dropped
            else ""
        )
        + (f" -> {args.pose_out}" if args.pose_out else "")
    )
    return 0


def _client_update_calibration(device: str, args: argparse.Namespace, cal, cal_path: Path, pdr, fusion, trace) -> None:
    """A survey teaches the calibration from its marks, a phone from the scale its Kalman filter learned."""
    import math

    import numpy as np

    from ..fusion import LocalFusion
    from ..pdr.steplength import calibrate_from_marks, calibrate_from_scale

    before = [float(c) for c in cal.model.coef]
    if args.kind == "survey" and trace is not None and len(trace.waypoints) >= 2:
        n = calibrate_from_marks(cal, np.array([s.t for s in pdr.steps]), pdr.features, trace.waypoints.t, trace.waypoints.pos_enu)
        how = f"{n} marked segments"
        learned = n > 0
    elif isinstance(fusion, LocalFusion):
        scale, sigma = float(fusion.x[3]), math.sqrt(max(float(fusion.P[3, 3]), 0.0))
        learned = calibrate_from_scale(cal, pdr.features, scale, sigma)
        how = f"the fused step scale {scale:.3f} +- {sigma:.3f}" + ("" if learned else " (not pinned by the fixes)")
    else:
        learned, how = False, f"no step scale from the {args.filter} filter"
    if learned:
        cal.save(cal_path)
    print(
        f"{device}: calibration {cal_path}: {how}: {cal.model.name} {before} -> {[float(c) for c in cal.model.coef]}"
        + ("" if learned else " (not updated)")
    )


def register(sub) -> None:
    cl = sub.add_parser("client", help="client agents: phone, foot or survey, replaying a recording against a server")
    csub = cl.add_subparsers(dest="kind", required=True)
    for kind, helptext in (
        ("phone", "a phone: step-and-heading PDR, WiFi scans, fused fixes"),
        ("foot", "a foot-mounted IMU: ZUPT INS strides, fused fixes"),
        ("survey", "an operator surveying by walking: steps, scans and survey marks (waypoints)"),
    ):
        c = csub.add_parser(kind, help=helptext)
        c.add_argument("--endpoint")
        c.add_argument("--site")
        c.add_argument("--device", help="device id (default: from the recording's name)")
        c.add_argument("--replay", metavar="FILE", help="recording to replay (ILC trace for phone/survey; IMU file for foot)")
        c.add_argument(
            "--live",
            metavar="SOURCE",
            help="phone: read live IMU samples and WiFi scans as lines from SOURCE (a pipe or FIFO; - for "
            "stdin): 't,ax,ay,az,gx,gy,gz[,mx,my,mz]' and 'wifi,t,BSSID=RSSI;...' (needs --rate)",
        )
        c.add_argument("--speed", type=float, help="replay speed factor K (0 = as fast as possible)")
        c.add_argument(
            "--fixes",
            metavar="CSV",
            help="the device's own GPS / RFID fixes for the replay (t,x,y,floor,sigma,source[,sigma_random]; "
            "the simulator writes them beside each walk): fused at their times, GPS pairs also in differential mode",
        )
        c.add_argument(
            "--filter",
            choices=("kalman", "particle", "kourogi"),
            help="local fusion: our Kalman filter (position, heading bias, step scale), a particle filter with the site's walls "
            "and walk prior, or Kourogi et al.'s own (position and velocity; the reference) (default kalman)",
        )
        c.add_argument(
            "--floorplan",
            metavar="DIR",
            help="site folder with the floor plans (Indoor Location Competition layout): walls and walk prior "
            "for --filter particle; for kalman, each floor's grid direction (heading drift elimination along corridors)",
        )
        c.add_argument("--start", metavar="X,Y,SIGMA", help="known start position in the site frame (m) and its standard deviation")
        c.add_argument("--floor", help="floor at the start (with --start)")
        c.add_argument(
            "--lockstep",
            action="store_true",
            help="wait for the server's answer to each scan before replaying on (fixes arrive as they would live, whatever K)",
        )
        c.add_argument("--pose-out", metavar="FILE", help="live pose output: .csv (t,x,y,floor,sigma_x,sigma_y), .jsonl or .nmea")
        c.add_argument("--pose-format", choices=("csv", "jsonl", "nmea"))
        c.add_argument("--spool", help="folder for unacknowledged batches (default .hybridloc-spool/<device>)")
        c.add_argument(
            "--spool-max-mb",
            type=float,
            default=None,
            help="cap on the spool; when full the oldest unacknowledged batches lose their data first (default: the disk)",
        )
        c.add_argument("--ack-timeout", type=float, default=10.0, help="seconds to wait for acknowledgements at the end")
        c.add_argument("--user")
        c.add_argument("--password")
        c.add_argument("--tls-ca")
        c.add_argument("--format", choices=("csv", "pyshoe", "openshoe"), help="foot recording format (detected by default)")
        c.add_argument("--rate", type=float, help="IMU rate: foot files without timestamps, and --live streams")
        if kind != "foot":
            c.add_argument("--offset", type=float, default=0.0, help="walking direction minus the phone's heading, rad (as pdr phone --offset)")
            c.add_argument(
                "--estimate-offset",
                action="store_true",
                help="estimate the walking offset from the gait (as pdr phone --estimate-offset): a phone carried in a pocket or bag",
            )
            c.add_argument("--calibration", metavar="FILE", help="the device's step-length calibration (as pdr phone --calibration)")
            c.add_argument(
                "--update-calibration",
                action="store_true",
                help="at the end, teach --calibration (created when absent) what this walk showed: a survey from its marks "
                "(known distances), a phone from the step-length scale its Kalman filter learned from the fixes",
            )
        c.set_defaults(
            func=_cmd_client,
            _parser=c,
            _required=("site",),
            _settings={
                "endpoint": "endpoint",
                "site": "site",
                "speed": "filter.speed",
                "filter": "filter.kind",
                "start": "filter.start",
                "floor": "filter.floor",
                "floorplan": "floorplan",
                "user": "security.user",
                "password": "security.password",
                "tls_ca": "security.tls_ca",
            },
        )

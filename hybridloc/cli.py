"""The ``hybridloc`` command.

Layering (as in evo): this module only parses arguments, calls pure library functions and prints.
Every library error derived from :class:`hybridloc.io.DataFormatError` or :class:`ValueError` is
reported as one line on stderr with exit status 1 (2 for usage errors, from argparse).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from . import __version__
from .progress import Progress

#: step length models of ``pdr phone --model`` and ``eval pdr-phone --model`` (hybridloc.pdr.steplength.MODELS)
LENGTH_MODELS = ("constant", "weinberg", "frequency", "kim", "height")

log = logging.getLogger("hybridloc")


def _cmd_data_inspect(args: argparse.Namespace) -> int:
    from .inspect import inspect_file

    status = 0
    for p in args.files:
        try:
            print(inspect_file(p, args.format, args.rate).render())
        except (ValueError, OSError) as exc:  # DataFormatError is a ValueError
            print(f"{p}: error: {exc}", file=sys.stderr)
            status = 1
        print()
    return status


def _load_imu(path: str, fmt: str | None, rate: float | None, accel_unit: str = "m/s^2"):
    """(imu, read report, device model, waypoints or None) of a recording."""
    from .io import detect_format

    fmt = fmt or detect_format(path)
    if fmt == "msft":
        from .io.msft import read_ilc_trace

        tr = read_ilc_trace(path)
        if tr.imu is None:
            raise ValueError(f"{path}: no usable IMU data ({tr.report.summary()})")
        return tr.imu, tr.report, tr.device_model, tr.waypoints
    from .io.imu_files import read_imu_csv, read_openshoe_mat, read_pyshoe_mat

    if fmt == "csv":
        rec = read_imu_csv(path, accel_unit=accel_unit)
    elif fmt == "pyshoe":
        rec = read_pyshoe_mat(path)
    elif fmt == "openshoe":
        rec = read_openshoe_mat(path, rate or 100.0)
    else:
        raise ValueError(f"{path}: format {fmt} holds no IMU data")
    return rec.imu, rec.report, "", None


def _cmd_pdr_phone(args: argparse.Namespace) -> int:
    from .io.common import stem_of
    from .io.writers import write_trajectory_csv
    from .pdr import PhonePdr, PhonePdrConfig, dead_reckon, make_model
    from .pdr.files import parse_start, write_steps_csv

    x0, y0, h0 = parse_start(args.start)
    out = Path(args.out)
    cal, cal_path = _open_calibration(args.calibration, args.update_calibration, args.model)
    status = 0
    for p in args.traces:
        try:
            imu, report, device, marks = _load_imu(p, args.format, None, args.accel_unit)
        except (ValueError, OSError) as exc:
            print(f"{p}: error: {exc}", file=sys.stderr)
            status = 1
            continue
        model = cal.model if cal is not None else make_model(args.model)
        cfg = PhonePdrConfig(detector=args.detector, walking_offset=args.offset, estimate_offset=args.estimate_offset)
        pdr = PhonePdr(imu.rate_hz, model, cfg, heading0=h0)
        steps = pdr.process(imu)
        coef_used = [float(c) for c in model.coef]
        if args.update_calibration:
            _update_calibration(p, cal, cal_path, steps, pdr.features, marks)
        d = out / stem_of(p)
        d.mkdir(parents=True, exist_ok=True)
        write_steps_csv(d / "steps.csv", steps)
        write_trajectory_csv(d / "trajectory.csv", dead_reckon(steps, x0, y0, float(imu.t[0])))
        st = pdr.stats
        degraded = sum(1 for s in steps if s.degraded)
        rej = ", ".join(f"{k} x{v}" for k, v in st.rejected_samples.items()) or "none"
        print(f"{p}: {len(steps)} steps over {imu.duration:.1f} s ({model.name} {coef_used}), "
              f"{degraded} with degraded heading, gaps {st.gaps}, saturated samples {st.saturated}, rejected samples: {rej}; input: {report.summary()} -> {d}")
    return status


def _open_calibration(path: str | None, update: bool, model_name: str):
    """(calibrator, path) of --calibration FILE, created from ``model_name`` when absent and
    ``update`` (--update-calibration) asks for it; (None, None) without a file."""
    from .pdr import LengthCalibrator, make_model

    if path is None:
        if update:
            raise ValueError("--update-calibration needs --calibration FILE (the device's calibration; created when absent)")
        return None, None
    p = Path(path)
    if p.is_file():
        return LengthCalibrator.load(p), p
    if not update:
        raise ValueError(f"calibration {p} not found (add --update-calibration to create it)")
    return LengthCalibrator(make_model(model_name)), p


def _update_calibration(path: str, cal, cal_path: Path, steps, features, marks) -> None:
    """The device's step-length calibration, updated from this walk's waypoint segments (known
    distances) and saved; a walk without marked points leaves it as it was."""
    import numpy as np

    from .pdr.steplength import calibrate_from_marks

    if marks is None or len(marks) < 2:
        print(f"{path}: no waypoints (known distances): calibration {cal_path} not updated", file=sys.stderr)
        return
    before = [float(c) for c in cal.model.coef]
    n = calibrate_from_marks(cal, np.array([s.t for s in steps]), features, marks.t, marks.pos_enu)
    if n:
        cal.save(cal_path)
    print(f"{path}: calibration {cal_path}: {n} waypoint segments, {cal.model.name} {before} -> {[float(c) for c in cal.model.coef]} "
          f"({cal.n_segments} segments in all)")


def _cmd_eval_pdr_phone(args: argparse.Namespace) -> int:
    import math

    import numpy as np

    from .io.msft import find_ilc_traces
    from .metrics import summarize_errors
    from .pdr import PhonePdrConfig
    from .pdr.evaluate import collect_runs, decompose_segment_errors, decompose_turn_errors, evaluate_phone_pdr, fit_model, marks_on_straight_walks, offset_recovery

    paths = find_ilc_traces(args.dir)[:: args.every]
    if not paths:
        raise ValueError(f"no Indoor Location Competition traces under {args.dir}")
    cfg = PhonePdrConfig(detector=args.detector)
    runs, skipped = collect_runs(paths, cfg)
    print(f"phone PDR on {len(runs)} traces of {args.dir} (detector {args.detector}; {len(skipped)} skipped); "
          "lengths calibrated by 2-fold cross-fitting over traces")
    print(f"{'model':<10} {'coef (fold A | B)':<34} {'len p50':>8} {'len p90':>8} {'turn p50':>9} {'turn p90':>9} {'wp p50':>7} {'wp p90':>7} {'segs':>5}")

    def row(name: str, r) -> None:
        coef = " | ".join(",".join(f"{c:.3f}" for c in cf) for cf in r.coefs)
        wp = summarize_errors(r.wp_err)
        print(f"{name:<10} {coef:<34} {100 * np.median(r.length_rel_err):7.1f}% {100 * np.percentile(r.length_rel_err, 90):7.1f}% "
              f"{np.median(r.turn_err_deg):8.1f}d {np.percentile(r.turn_err_deg, 90):8.1f}d {wp.median:6.2f}m {wp.p90:6.2f}m {r.n_segments:5d}")

    res = {}
    for m in LENGTH_MODELS:
        res[m] = evaluate_phone_pdr(paths, m, cfg, runs=runs)
        row(m, res[m])
    main_m = res[args.model]
    andr = evaluate_phone_pdr(paths, args.model, cfg, runs=runs, heading="android")
    if andr.n_segments:
        row("+android", andr)
    print(f"\n{args.model}: segment length error median {100 * np.median(main_m.length_rel_err):.1f}% (goal <= 5%), "
          f"90th pct {100 * np.percentile(main_m.length_rel_err, 90):.1f}% (goal <= 15%); heading-change error median "
          f"{np.median(main_m.turn_err_deg):.1f} deg (goal <= 8); error at waypoints from the first one: {summarize_errors(main_m.wp_err)}")
    if andr.n_segments:
        print(f"heading against Android's own fused attitude (+android: {args.model} lengths, our steps, heading from TYPE_ROTATION_VECTOR "
              f"on {andr.n_traces} traces): heading-change error median {np.median(andr.turn_err_deg):.1f} deg, ratio ours/Android "
              f"{np.median(main_m.turn_err_deg) / np.median(andr.turn_err_deg):.2f}; mean error at waypoints ratio {np.mean(main_m.wp_err) / np.mean(andr.wp_err):.2f}")
    base = np.median(res["constant"].length_rel_err)
    print(f"ratio of median length error {args.model} / constant-length baseline: {np.median(main_m.length_rel_err) / base:.2f}")
    print(f"{main_m.n_steps} steps over {main_m.walked_m:.0f} m of waypoint-to-waypoint walking")
    s_end, s_rel = decompose_segment_errors(main_m.seg_true_m, main_m.seg_err_m)
    d_med = float(np.median(main_m.seg_true_m))
    print(f"segment errors decompose (robust fit, sigmas) as +-{s_end:.2f} m fixed per segment (waypoint marks, where and "
          f"when; the track cut at the mark times) and +-{100 * s_rel:.1f}% of length (the PDR's scale); the fixed part alone "
          f"gives a median relative error of about {100 * 0.6745 * s_end / d_med:.1f}% on the median segment ({d_med:.1f} m)")
    s_turn, s_mark = decompose_turn_errors(main_m.turn_lengths_m, main_m.turn_err_rad)
    own = (f"+-{math.degrees(s_turn):.1f} deg the PDR's own heading-change error (median {0.6745 * math.degrees(s_turn):.1f} deg)"
           if s_turn > 1e-3 else "a part independent of segment length not resolvable from 0")
    print(f"turn errors decompose (robust fit, sigmas) as {own} and +-{s_mark:.2f} m across the segment at each end "
          f"(the waypoint marks, and the PDR track's sideways position at the mark times): the turn error shrinks as 1/length")
    straight, n_turns = marks_on_straight_walks(runs, fit_model(runs, args.model))
    if straight.size:
        print(f"marks on straight walks: where our heading and Android's both see a turn under 5 deg ({straight.size} of {n_turns} turns), the "
              f"waypoints turn by median {np.median(straight):.1f} deg, p90 {np.percentile(straight, 90):.1f} deg, {100 * np.mean(straight >= 10):.0f}% "
              "by 10 deg or more: the marks' own direction error, which no PDR removes")
    rec = offset_recovery(paths[::5])
    share = {r: {a: 100 * float(np.mean(v < math.radians(20))) if len(v) else float("nan") for a, v in d.items()} for r, d in rec.items()}
    angles = list(rec["gait"])
    print(f"walking-direction offset (phone carried turned by {' / '.join(f'{a:g}' for a in angles)} deg about its screen's normal, "
          f"{len(rec['gait'][angles[0]])} real walks re-oriented; walk heading within 20 deg of the unturned phone's): ours (sign from the gait) "
          + " / ".join(f"{share['gait'][a]:.0f}" for a in angles) + " %, the principal axis signed by continuity (textbook) "
          + " / ".join(f"{share['continuity'][a]:.0f}" for a in angles) + " %")
    return 0


def _cmd_pdr_foot(args: argparse.Namespace) -> int:
    import csv

    from .io.common import stem_of
    from .ins.foot import FootInsConfig, run_foot_ins, strides
    from .pdr.files import write_steps_csv

    out = Path(args.out)
    status = 0
    for p in args.files:
        try:
            imu, report, _, _ = _load_imu(p, args.format, args.rate, args.accel_unit)
            if args.rate and args.format != "openshoe" and abs(imu.rate_hz - args.rate) > 0.05 * args.rate:
                raise ValueError(f"--rate {args.rate} Hz disagrees with the file's timestamps ({imu.rate_hz:.1f} Hz)")
            if not 50.0 <= imu.rate_hz <= 2000.0:
                raise ValueError(f"sample rate {imu.rate_hz:.1f} Hz is implausible for a foot-mounted IMU (50-2000 Hz)")
        except (ValueError, OSError) as exc:
            print(f"{p}: error: {exc}", file=sys.stderr)
            status = 1
            continue
        res = run_foot_ins(imu, FootInsConfig(detector=args.detector, detector_threshold=args.threshold, smooth=not args.forward))
        d = out / stem_of(p)
        d.mkdir(parents=True, exist_ok=True)
        with open(d / "trajectory.csv", "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(("t", "x", "y", "z", "sigma_x", "sigma_y", "sigma_z", "stance"))
            for i in range(len(res.t)):
                w.writerow([f"{res.t[i]:.5f}", *(f"{v:.4f}" for v in res.pos_enu[i]), *(f"{v:.4f}" for v in res.sigma_pos[i]), int(res.stance[i])])
        st = strides(res)
        write_steps_csv(d / "steps.csv", st)
        s = res.stats
        print(f"{p}: {len(res.t)} samples at {imu.rate_hz:.1f} Hz, {len(st)} strides, {s['stance_samples']} stance samples, "
              f"gaps {s['gaps']}, NaN samples {s['nan_samples']}, saturated samples {s['saturated_samples']}, re-initialisations {s['reinit']}; "
              f"input: {report.summary()} -> {d}")
    return status


def _cmd_eval_pdr_foot(args: argparse.Namespace) -> int:
    import numpy as np

    from .ins.evaluate import evaluate_trial

    files = sorted(Path(args.dir).glob("*.mat"))
    if not files:
        raise ValueError(f"no PyShoe .mat trials in {args.dir}")
    print(f"foot INS (15-state ESKF, ZUPT, default adaptive SHOE detector, one setting for all, strides RTS-smoothed) on {len(files)} PyShoe VICON trials")
    print("ARMSE: the smoothed track `hybridloc pdr foot` writes; fwd: the forward filter alone (a live client's track, and what the "
          "authors' figure is); ours@opt: our forward filter on the authors' per-trial-optimal stance labels")
    print(f"{'trial':<22} {'ARMSE 2D':>9} {'fwd 2D':>8} {'ARMSE 3D':>9} {'authors':>8} {'ours@opt':>9} {'DEDRIFT-I':>10} {'dist m':>7} {'loop %':>7}")
    rows = []
    for f in files:
        r = evaluate_trial(f)
        rows.append(r)
        loop = f"{r.loop_pct:6.2f}%" if r.loop_pct is not None else "      -"
        print(f"{r.name:<22} {r.armse_2d:8.3f}m {r.forward_2d:7.3f}m {r.armse_3d:8.3f}m {r.authors_2d:7.3f}m {r.opt_labels_2d:8.3f}m {r.dedrift_2d:9.3f}m "
              f"{r.distance_m:7.1f} {loop}")
    a2 = np.array([r.armse_2d for r in rows])
    a3 = np.array([r.armse_3d for r in rows])
    au = np.array([r.authors_2d for r in rows])
    dd = np.array([r.dedrift_2d for r in rows])
    loops = [r.loop_pct for r in rows if r.loop_pct is not None]
    fw = np.array([r.forward_2d for r in rows])
    print(f"\nmean 2-D ARMSE {a2.mean():.4f} m (median {np.median(a2):.4f}), stride-smoothed; goal <= 0.059 m, the authors' figure on all 56 trials")
    print(f"forward filter alone: mean 2-D ARMSE {fw.mean():.4f} m (median {np.median(fw):.4f}); the authors' figure is a forward filter's")
    print(f"mean 3-D ARMSE {a3.mean():.4f} m (median {np.median(a3):.4f}), stride-smoothed")
    print(f"authors' per-trial-tuned SHOE on these {len(rows)} trials: mean {au.mean():.4f} m; ratio ours/authors {a2.mean() / au.mean():.2f} smoothed, "
          f"{fw.mean() / au.mean():.2f} forward")
    op = np.array([r.opt_labels_2d for r in rows])
    if np.isfinite(op).all() and np.isfinite(fw).all():
        print(f"our forward filter on the authors' per-trial-optimal SHOE stance labels (ours@opt): mean {op.mean():.4f} m; so of the forward gap "
              f"{fw.mean() - au.mean():+.4f} m to the authors, our one-setting detector accounts for {fw.mean() - op.mean():+.4f} and the filter for "
              f"{op.mean() - au.mean():+.4f}")
    print(f"plain DEDRIFT-I (Ojeda) in the same run: mean 2-D ARMSE {dd.mean():.3f} m; ratio ours/DEDRIFT-I {a2.mean() / dd.mean():.3f}")
    if loops:
        print(f"closed loops ({len(loops)}): mean return-to-start error {np.mean(loops):.2f}% of distance travelled (Ojeda eq 9)")
    return 0


def _cmd_map_build(args: argparse.Namespace) -> int:
    from .radio.radiomap import BuildParams, build_radio_map
    from .radio.sources import labelled_from_inputs

    labelled, plan, site = labelled_from_inputs(args.format, args.inputs, args.floorplan)
    if not labelled:
        raise ValueError("no labelled scans in the inputs (surveys need at least two waypoints)")
    params = BuildParams(cell=args.cell, max_age_s=args.max_age)
    rmap = build_radio_map(labelled, site=args.site or site, plan=plan, params=params)
    rmap.save(args.out)
    fl = ", ".join(f"{f.name}: {len(f.cells)} cells, {len(f.tx)} transmitters" for f in rmap.floors.values())
    print(f"radio map of {len(labelled)} labelled scans -> {args.out} ({fl}; device offsets {rmap.device_offsets})")
    return 0


def _cmd_locate(args: argparse.Namespace) -> int:
    import csv
    import math

    from .io.common import stem_of
    from .io.writers import region_feature, write_geojson
    from .radio.locate import KnnLocator, ProbabilisticLocator
    from .radio.radiomap import RadioMap
    from .radio.sources import scans_to_locate

    rmap = RadioMap.load(args.map)
    if args.method == "knn":
        if not rmap.references:
            raise ValueError(f"{args.map} holds no reference scans for kNN; use --method prob")
        knn = KnnLocator(rmap.references, k=args.k, max_age_s=args.max_age, metric=args.metric)
    else:
        prob = ProbabilisticLocator(rmap, max_age_s=args.max_age)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for p in args.inputs:
        scans, site = scans_to_locate(args.format, p)
        if site and rmap.site and site != rmap.site:
            from .radio.locate import LocateResult

            results = [LocateResult(None, None, reason=f"the map is of site {rmap.site!r}, this input of {site!r}") for _ in scans]
        else:
            results = knn.locate_many(scans) if args.method == "knn" else [prob.locate(s) for s in scans]
        stem = stem_of(p)
        feats = []
        with open(out / f"{stem}.csv", "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            extra_cols = ["building"] if args.format == "ujiindoorloc" else []
            w.writerow(["t", "x", "y", "floor", "sigma_x", "sigma_y", "floor_prob", *extra_cols, "reason"])
            n_fix = 0
            for s, res in zip(scans, results):
                if res.fix is None:
                    w.writerow([f"{s.t:.3f}", "", "", "", "", "", "", *([""] * len(extra_cols)), res.reason])
                    continue
                n_fix += 1
                fl = res.fix.floor or ""
                extra = []
                if args.format == "ujiindoorloc" and fl.startswith("b"):
                    b, f_ = fl[1:].split("_f")
                    fl, extra = f_, [b]
                sx, sy = (math.sqrt(v) for v in (res.fix.cov[0, 0], res.fix.cov[1, 1]))
                w.writerow([f"{s.t:.3f}", f"{res.fix.pos_enu[0]:.3f}", f"{res.fix.pos_enu[1]:.3f}", fl, f"{sx:.3f}", f"{sy:.3f}", f"{res.fix.floor_prob:.4f}", *extra, ""])
                if res.region is not None:
                    feats.append(region_feature(res.region))
        write_geojson(out / f"{stem}.geojson", feats)
        print(f"{p}: {len(scans)} scans, {n_fix} fixes -> {out / (stem + '.csv')}")
    return 0


def _cmd_map_show(args: argparse.Namespace) -> int:
    from .radio.plot import plot_map

    plan = None
    if args.floorplan:
        from .io.msft import read_ilc_site

        plan = read_ilc_site(args.floorplan)
    plot_map(args.map, args.out, args.tx, plan)
    print(f"wrote {args.out}")
    return 0


def _cmd_eval_fingerprint(args: argparse.Namespace) -> int:
    from .radio.evaluate import run_fingerprint_eval

    return run_fingerprint_eval(args.uji, args.ilc, args.folds, args.every, args.uji_validation)


def _cmd_sim_world(args: argparse.Namespace) -> int:
    from .sim.run import make_world

    w = make_world(args.seed, args.floors, args.out, args.floorplan)
    print(f"world {args.seed}{' on ' + args.floorplan if args.floorplan else ''}: {w.n_floors} floors of {w.width - w.x_min:.1f} m x {w.depth - w.y_min:.1f} m, {len(w.rooms)} rooms, {len(w.aps)} WiFi APs, "
          f"{len(w.beacons)} BLE beacons, {len(w.rfid)} RFID readers -> {args.out}")
    return 0


def _cmd_sim_walk(args: argparse.Namespace) -> int:
    from .sim.run import load_world, simulate_walks

    world = load_world(args.world)

    bar = Progress("[sim] walker", args.walkers)
    out = simulate_walks(world, args.walkers, args.minutes, args.carrier, args.out, args.seed, lambda i, n: bar.update(i))
    print(f"{len(out)} walks of {args.minutes:g} min ({args.carrier}) -> {args.out}")
    return 0


def _cmd_eval_sim_realism(args: argparse.Namespace) -> int:
    from .sim.evaluate import run_sim_realism

    return run_sim_realism(args.ilc, args.walkers, args.minutes, args.every, args.seed)


def _security(args: argparse.Namespace):
    from .wire.zconfig import Security

    devices = []
    if getattr(args, "acl_devices", None):
        devices = [ln.split(":")[0].strip() for ln in Path(args.acl_devices).read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    return Security(users_file=getattr(args, "users", None), user=getattr(args, "user", None), password=getattr(args, "password", None),
                    tls_cert=getattr(args, "tls_cert", None), tls_key=getattr(args, "tls_key", None), tls_ca=getattr(args, "tls_ca", None),
                    acl_devices=devices)


def _cmd_serve(args: argparse.Namespace) -> int:
    from .server.service import Server, serve_forever

    server = Server(args.endpoint, args.db, _security(args), method=args.method)
    for spec in args.map or []:
        site, _, path = spec.partition("=")
        if not path:
            raise ValueError(f"--map expects SITE=FILE, got {spec!r}")
        server.load_map(site, Path(path).read_bytes())
    for site in args.site or []:
        if server.load_map(site) is None:
            print(f"warning: no stored radio map for site {site!r}", file=sys.stderr)
    serve_forever(server)
    return 0


def _cmd_db_upgrade(args: argparse.Namespace) -> int:
    from .server.db import make_engine
    from .server.migrate import current_revision, upgrade

    eng = make_engine(args.db)
    upgrade(eng)
    print(f"{args.db}: schema at revision {current_revision(eng)}")
    eng.dispose()
    return 0


def _cmd_status(args: argparse.Namespace) -> int:
    from .clients.status import query_status

    st = query_status(args.endpoint, _security(args), args.timeout)
    if st is None:
        print(f"no server answered on {args.endpoint}", file=sys.stderr)
        return 1
    print(f"devices online ({len(st['online'])}): {', '.join(st['online']) or '-'}")
    print("database: " + ", ".join(f"{k} {v}" for k, v in st["db"].items() if k not in ("rejections", "maps")))
    print("messages: " + ", ".join(f"{k} {v}" for k, v in sorted(st["counts"].items())))
    print("rejections stored: " + (", ".join(f"{k} {v}" for k, v in st["db"]["rejections"].items()) or "none"))
    print("radio maps: " + (", ".join(f"{k} v{v}" for k, v in st["db"]["maps"].items()) or "none"))
    return 0


def _cmd_map_import(args: argparse.Namespace) -> int:
    from .radio.radiomap import RadioMap
    from .server.store import Store

    RadioMap.load(args.map_file)  # refuse anything that is not a radio map
    st = Store(args.db)
    v = st.save_map(args.site, Path(args.map_file).read_bytes())
    st.close()
    print(f"{args.map_file} -> site {args.site} radio map version {v} in {args.db}")
    return 0


def _cmd_map_export(args: argparse.Namespace) -> int:
    from .server.store import Store

    st = Store(args.db)
    got = st.load_map(args.site)
    st.close()
    if got is None:
        raise ValueError(f"no radio map stored for site {args.site!r}")
    Path(args.out).write_bytes(got[1])
    print(f"site {args.site} radio map version {got[0]} -> {args.out}")
    return 0


def _cmd_map_rebuild(args: argparse.Namespace) -> int:
    from .server.rebuild import rebuild
    from .server.store import Store

    st = Store(args.db)
    bar = Progress("[rebuild] devices", 0, bar_width=30)  # the device count comes with each update

    def progress(i, n, dev):
        bar.total = n
        bar.update(i, f"({dev})")

    try:
        v, n, relabelled = rebuild(st, args.site, args.cache or (str(args.db) + ".rebuild"), progress)
    finally:
        st.close()
    if v is None:
        print(f"site {args.site}: no survey (devices with at least two marks) in {args.db}; no map built", file=sys.stderr)
        return 1
    print(f"site {args.site}: radio map version {v} from {n} labelled scans ({relabelled} device(s) relabelled, the rest from the cache)")
    return 0


def _cmd_client(args: argparse.Namespace) -> int:
    from .clients.agent import Agent, PoseWriter, open_client, replay_foot, replay_phone

    if bool(args.replay) == bool(args.live):
        raise ValueError("give one input: --replay FILE (a recording) or --live SOURCE (a live line stream, - for stdin)")
    if args.live and args.kind != "phone":
        raise ValueError("--live is for phone clients (IMU samples and WiFi scans as lines); foot and survey clients replay recordings")
    if args.live and not args.rate:
        raise ValueError("--live needs the IMU sample rate: --rate HZ")
    device = args.device or f"{args.kind}-{stem_safe(args.replay) if args.replay else 'live'}"
    spool = args.spool or f".hybridloc-spool/{device}"
    pose = PoseWriter(args.pose_out, args.pose_format)
    init = _parse_floats(args.start, 3, "--start x,y,sigma") if args.start else None
    # a phone's or survey's step-length calibration (foot clients have no such options)
    cal, cal_path = _open_calibration(getattr(args, "calibration", None), getattr(args, "update_calibration", False), "height")
    length_model = cal.model if cal is not None else None
    pdr_config = None
    if args.kind != "foot":
        from .pdr import PhonePdrConfig

        pdr_config = PhonePdrConfig(walking_offset=args.offset, estimate_offset=args.estimate_offset)
    pdr = None
    with open_client(args.endpoint, _security(args), log=lambda m: print(f"{device}: {m}", file=sys.stderr)) as s:
        fusion = None
        if args.filter == "particle":
            from .clients.agent import fetch_walk_prior
            from .fusion import ParticleFusion

            plan = None
            if args.floorplan:
                from .io.msft import read_ilc_site

                plan = read_ilc_site(args.floorplan)
            prior = fetch_walk_prior(s, args.site, plan)
            if prior is None:
                print(f"{device}: the server has no radio map for {args.site!r}: the particle filter runs without a walk prior", file=sys.stderr)
            from .geo import corridor_axes

            fusion = ParticleFusion(prior, init=init, floor=args.floor, corridor_axes=corridor_axes(plan))
        elif args.filter == "kourogi":
            from .fusion import KourogiFusion

            fusion = KourogiFusion(init=init, floor=args.floor)
        elif args.floorplan:  # our Kalman filter, with the floors' grid directions (heuristic drift elimination)
            from .fusion import LocalFusion
            from .geo import corridor_axes
            from .io.msft import read_ilc_site

            fusion = LocalFusion(init=init, floor=args.floor, corridor_axes=corridor_axes(read_ilc_site(args.floorplan)))
        if args.live:
            from .clients.agent import live_phone

            agent = Agent(s, args.site, device, spool, pose, init=init, fusion=fusion, floor=args.floor)
            src = sys.stdin if args.live == "-" else open(args.live, encoding="utf-8")
            try:
                ls = live_phone(agent, src, args.rate, lockstep=args.lockstep, length_model=length_model, pdr_config=pdr_config)
                pdr = ls.pdr
            finally:
                if src is not sys.stdin:
                    src.close()
            print(f"{device}: live input: {ls.samples} IMU samples, {ls.scans} scans, {ls.bad_lines} malformed lines skipped"
                  + (f" (first: {ls.first_bad})" if ls.first_bad else ""))
        elif args.kind == "foot":
            imu, _, _, _ = _load_imu(args.replay, args.format, args.rate)
            agent = Agent(s, args.site, device, spool, pose, init=init, fusion=fusion, floor=args.floor)
            replay_foot(agent, imu, args.speed)
        else:
            from .io.msft import read_ilc_trace

            tr = read_ilc_trace(args.replay)
            agent = Agent(s, args.site, device, spool, pose, tr.device_model, init=init, fusion=fusion, floor=args.floor)
            local = None
            if args.fixes:
                from .io.fixes import read_fixes_csv

                local, rep = read_fixes_csv(args.fixes)
                if not rep.ok:
                    print(f"{args.fixes}: {rep.summary()}", file=sys.stderr)
            pdr = replay_phone(agent, tr, args.speed, survey=args.kind == "survey", lockstep=args.lockstep, local_fixes=local, length_model=length_model,
                               pdr_config=pdr_config)
        r = agent.close(wait=args.ack_timeout)
    if args.kind != "foot" and args.update_calibration and pdr is not None:
        _client_update_calibration(device, args, cal, cal_path, pdr, agent.fusion, tr if args.replay else None)
    print(f"{device}: {r.steps} steps, {r.batches} batches ({r.acked} acknowledged; the rest stay in the spool {spool}), "
          f"{r.fixes_received} fixes received, {r.fixes_accepted} accepted" + (f" -> {args.pose_out}" if args.pose_out else ""))
    return 0


def _client_update_calibration(device: str, args: argparse.Namespace, cal, cal_path: Path, pdr, fusion, trace) -> None:
    """A survey teaches the calibration from its marks, a phone from the scale its Kalman filter learned."""
    import math

    import numpy as np

    from .fusion import LocalFusion
    from .pdr.steplength import calibrate_from_marks, calibrate_from_scale

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
    print(f"{device}: calibration {cal_path}: {how}: {cal.model.name} {before} -> {[float(c) for c in cal.model.coef]}"
          + ("" if learned else " (not updated)"))


def _parse_floats(text: str, n: int, what: str) -> tuple[float, ...]:
    import math

    try:
        vals = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise ValueError(f"{what} expected, got {text!r}") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{what} expected ({n} finite numbers), got {text!r}")
    return vals


def stem_safe(path: str) -> str:
    import re

    from .io.common import stem_of

    return re.sub(r"[^A-Za-z0-9_.-]", "_", stem_of(path))[:40]


def _cmd_eval_fusion(args: argparse.Namespace) -> int:
    from .demo import run_fusion_eval

    return run_fusion_eval(args.dir, Path(args.out), args.replay_every, args.every)


def _cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(Path(args.out), sim=args.sim, speed=args.speed)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hybridloc", description="Crowd-sourced hybrid PDR + WiFi/RF SLAM for indoor positioning.")
    ap.add_argument("--version", action="version", version=f"hybridloc {__version__}")
    ap.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = ap.add_subparsers(dest="command", required=True)

    data = sub.add_parser("data", help="inspect recordings")
    dsub = data.add_subparsers(dest="data_command", required=True)
    ins = dsub.add_parser("inspect", help="print what recordings hold: duration, rates, scans, APs, waypoints, gaps, problems")
    ins.add_argument("files", nargs="+", metavar="FILE")
    ins.add_argument("--format", choices=("msft", "pyshoe", "openshoe", "csv", "ujiindoorloc"), help="skip format detection")
    ins.add_argument("--rate", type=float, default=None, metavar="HZ", help="sample rate for files without timestamps (OpenShoe; default 100)")
    ins.set_defaults(func=_cmd_data_inspect)

    pdr = sub.add_parser("pdr", help="pedestrian dead reckoning")
    psub = pdr.add_subparsers(dest="pdr_command", required=True)
    ph = psub.add_parser("phone", help="smartphone step-and-heading PDR: steps.csv and trajectory.csv per input")
    ph.add_argument("traces", nargs="+", metavar="TRACE")
    ph.add_argument("--out", required=True, help="output folder; writes <out>/<input-stem>/{steps,trajectory}.csv")
    ph.add_argument("--start", default="0,0,0", help="initial pose x,y,heading (m, m, rad or e.g. 90deg); default 0,0,0")
    ph.add_argument("--format", choices=("msft", "csv"), help="input format (detected by default)")
    ph.add_argument("--accel-unit", choices=("m/s^2", "g"), default="m/s^2", help="accelerometer unit of a plain IMU CSV")
    ph.add_argument("--model", choices=LENGTH_MODELS, default="height", help="step length model (default height: Kim's on the bounce height)")
    ph.add_argument("--calibration", help="a per-device calibration JSON (LengthCalibrator.save) to use instead of --model defaults")
    ph.add_argument("--update-calibration", action="store_true",
                    help="after each input, update --calibration from its waypoint segments (known distances; robust to a mis-marked one) and save it; "
                         "created from --model when absent")
    ph.add_argument("--detector", choices=("peak", "autocorr"), default="peak", help="step detector family (default peak)")
    ph.add_argument("--offset", type=float, default=0.0, help="walking direction minus device heading, rad (phone in pocket/bag)")
    ph.add_argument("--estimate-offset", action="store_true", help="estimate the walking offset from the gait (horizontal acceleration's principal axis, "
                    "its forward half the one rising with the vertical): for a phone in a pocket or bag; held in front, leave it off")
    ph.set_defaults(func=_cmd_pdr_phone)

    ft = psub.add_parser("foot", help="foot-mounted INS (ZUPT-aided error-state EKF): trajectory.csv and steps.csv per input")
    ft.add_argument("files", nargs="+", metavar="FILE")
    ft.add_argument("--out", required=True, help="output folder; writes <out>/<input-stem>/{trajectory,steps}.csv")
    ft.add_argument("--format", choices=("csv", "pyshoe", "openshoe"), help="input format (detected by default)")
    ft.add_argument("--rate", type=float, metavar="HZ", help="sample rate for files without timestamps (OpenShoe); checked against timestamps otherwise")
    ft.add_argument("--accel-unit", choices=("m/s^2", "g"), default="m/s^2", help="accelerometer unit of a plain IMU CSV")
    ft.add_argument("--detector", choices=("adaptive", "shoe", "ared", "amvd", "mbgtd"), default="adaptive", help="stance detector (default adaptive SHOE)")
    ft.add_argument("--threshold", type=float, help="the detector's threshold in its units (see hybridloc.ins.stance)")
    ft.add_argument("--forward", action="store_true", help="write the forward filter's track (what a live client has at each sample) instead of the default track smoothed back over each stride from its stance (RTS)")
    ft.set_defaults(func=_cmd_pdr_foot)

    mp = sub.add_parser("map", help="radio maps: build, show")
    msub = mp.add_subparsers(dest="map_command", required=True)
    mb = msub.add_parser("build", help="build a radio map from surveys (waypointed traces) or labelled fingerprints")
    mb.add_argument("inputs", nargs="+", metavar="INPUT")
    mb.add_argument("--format", choices=("msft", "ujiindoorloc", "csv"), required=True)
    mb.add_argument("--floorplan", help="site folder or geojson_map.json of the floor plan (msft; found next to the traces by default)")
    mb.add_argument("--out", required=True, metavar="MAP", help="radio map file (.npz)")
    mb.add_argument("--site", help="site name stored in the map")
    mb.add_argument("--cell", type=float, default=1.5, help="grid cell size, m (default 1.5)")
    mb.add_argument("--max-age", type=float, default=8.0, help="leave out readings older than this at scan time, s (default 8)")
    mb.set_defaults(func=_cmd_map_build)
    ms = msub.add_parser("show", help="coverage and per-transmitter heat maps as a PNG")
    ms.add_argument("map", metavar="MAP")
    ms.add_argument("--out", required=True, metavar="PNG")
    ms.add_argument("--tx", help="transmitter to draw (default: the most widely seen)")
    ms.add_argument("--floorplan", metavar="GEOJSON", help="floor plan to draw under the maps: a site folder (Indoor Location Competition layout) "
                    "or a simulated world's folder, as for map build")
    ms.set_defaults(func=_cmd_map_show)

    mi = msub.add_parser("import", help="store a radio map file as the site's newest version on the server database")
    mi.add_argument("map_file", metavar="MAP")
    mi.add_argument("--site", required=True)
    mi.add_argument("--db", default="hybridloc.db", help="database file or URL (default hybridloc.db)")
    mi.set_defaults(func=_cmd_map_import)
    me = msub.add_parser("export", help="write the site's newest radio map from the server database to a file")
    me.add_argument("--site", required=True)
    me.add_argument("--db", default="hybridloc.db")
    me.add_argument("--out", required=True, metavar="MAP")
    me.set_defaults(func=_cmd_map_export)

    mr = msub.add_parser("rebuild", help="rebuild a site's radio map from the surveys stored in the database (incremental, resumable)")
    mr.add_argument("--site", required=True)
    mr.add_argument("--db", default="hybridloc.db")
    mr.add_argument("--cache", help="folder for per-device labelled scans (default <db>.rebuild)")
    mr.set_defaults(func=_cmd_map_rebuild)

    cl = sub.add_parser("client", help="client agents: phone, foot or survey, replaying a recording against a server")
    csub = cl.add_subparsers(dest="kind", required=True)
    for kind, helptext in (("phone", "a phone: step-and-heading PDR, WiFi scans, fused fixes"), ("foot", "a foot-mounted IMU: ZUPT INS strides, fused fixes"),
                           ("survey", "an operator surveying by walking: steps, scans and survey marks (waypoints)")):
        c = csub.add_parser(kind, help=helptext)
        c.add_argument("--endpoint", default="tcp/127.0.0.1:7447")
        c.add_argument("--site", required=True)
        c.add_argument("--device", help="device id (default: from the recording's name)")
        c.add_argument("--replay", metavar="FILE", help="recording to replay (ILC trace for phone/survey; IMU file for foot)")
        c.add_argument("--live", metavar="SOURCE", help="phone: read live IMU samples and WiFi scans as lines from SOURCE (a pipe or FIFO; - for "
                       "stdin): 't,ax,ay,az,gx,gy,gz[,mx,my,mz]' and 'wifi,t,BSSID=RSSI;...' (needs --rate)")
        c.add_argument("--speed", type=float, default=1.0, help="replay speed factor K (0 = as fast as possible)")
        c.add_argument("--fixes", metavar="CSV", help="the device's own GPS / RFID fixes for the replay (t,x,y,floor,sigma,source[,sigma_random]; "
                       "the simulator writes them beside each walk): fused at their times, GPS pairs also in differential mode")
        c.add_argument("--filter", choices=("kalman", "particle", "kourogi"), default="kalman",
                       help="local fusion: our Kalman filter (position, heading bias, step scale), a particle filter with the site's walls "
                            "and walk prior, or Kourogi et al.'s own (position and velocity; the reference) (default kalman)")
        c.add_argument("--floorplan", metavar="DIR", help="site folder with the floor plans (Indoor Location Competition layout): walls and walk prior "
                       "for --filter particle; for kalman, each floor's grid direction (heading drift elimination along corridors)")
        c.add_argument("--start", metavar="X,Y,SIGMA", help="known start position in the site frame (m) and its standard deviation")
        c.add_argument("--floor", help="floor at the start (with --start)")
        c.add_argument("--lockstep", action="store_true",
                       help="wait for the server's answer to each scan before replaying on (fixes arrive as they would live, whatever K)")
        c.add_argument("--pose-out", metavar="FILE", help="live pose output: .csv (t,x,y,floor,sigma_x,sigma_y), .jsonl or .nmea")
        c.add_argument("--pose-format", choices=("csv", "jsonl", "nmea"))
        c.add_argument("--spool", help="folder for unacknowledged batches (default .hybridloc-spool/<device>)")
        c.add_argument("--ack-timeout", type=float, default=10.0, help="seconds to wait for acknowledgements at the end")
        c.add_argument("--user")
        c.add_argument("--password")
        c.add_argument("--tls-ca")
        c.add_argument("--format", choices=("csv", "pyshoe", "openshoe"), help="foot recording format (detected by default)")
        c.add_argument("--rate", type=float, help="IMU rate: foot files without timestamps, and --live streams")
        if kind != "foot":
            c.add_argument("--offset", type=float, default=0.0, help="walking direction minus the phone's heading, rad (as pdr phone --offset)")
            c.add_argument("--estimate-offset", action="store_true", help="estimate the walking offset from the gait (as pdr phone --estimate-offset): "
                           "a phone carried in a pocket or bag")
            c.add_argument("--calibration", metavar="FILE", help="the device's step-length calibration (as pdr phone --calibration)")
            c.add_argument("--update-calibration", action="store_true",
                           help="at the end, teach --calibration (created when absent) what this walk showed: a survey from its marks "
                                "(known distances), a phone from the step-length scale its Kalman filter learned from the fixes")
        c.set_defaults(func=_cmd_client)

    sv = sub.add_parser("serve", help="run the server: Zenoh router + ingest + locate/map/status services")
    sv.add_argument("--endpoint", default="tcp/127.0.0.1:7447", help="Zenoh endpoint to listen on (default tcp/127.0.0.1:7447)")
    sv.add_argument("--db", default="hybridloc.db", help="SQLite file or database URL (postgresql+psycopg://...)")
    sv.add_argument("--map", action="append", metavar="SITE=FILE", help="load a radio map file for a site (stored as a new version)")
    sv.add_argument("--site", action="append", help="serve the newest stored radio map of this site")
    sv.add_argument("--method", choices=("knn", "prob"), default="knn", help="positioning method of the locate service (default knn)")
    sv.add_argument("--users", help="user:password dictionary file (enables authentication)")
    sv.add_argument("--acl-devices", help="file listing device ids (one per line, or the users file): each may use only its own keys")
    sv.add_argument("--tls-cert", help="server certificate (PEM) for tls/ endpoints")
    sv.add_argument("--tls-key", help="server private key (PEM)")
    sv.set_defaults(func=_cmd_serve)

    dbp = sub.add_parser("db", help="database maintenance")
    dbsub = dbp.add_subparsers(dest="db_command", required=True)
    du = dbsub.add_parser("upgrade", help="apply the Alembic migrations up to the newest schema")
    du.add_argument("--db", default="hybridloc.db")
    du.set_defaults(func=_cmd_db_upgrade)

    stp = sub.add_parser("status", help="ask a running server: devices online, message and rejection counts, map versions")
    stp.add_argument("--endpoint", default="tcp/127.0.0.1:7447")
    stp.add_argument("--user")
    stp.add_argument("--password")
    stp.add_argument("--tls-ca")
    stp.add_argument("--timeout", type=float, default=5.0)
    stp.set_defaults(func=_cmd_status)

    lo = sub.add_parser("locate", help="fingerprint positioning: a CSV of fixes and a GeoJSON of regions per input")
    lo.add_argument("inputs", nargs="+", metavar="INPUT")
    lo.add_argument("--map", required=True, metavar="MAP")
    lo.add_argument("--format", choices=("msft", "ujiindoorloc", "csv"), required=True)
    lo.add_argument("--out", required=True, metavar="DIR")
    lo.add_argument("--method", choices=("knn", "prob"), default="knn", help="weighted kNN (default) or the probabilistic cell likelihood")
    lo.add_argument("--k", type=int, default=5)
    lo.add_argument("--metric", choices=("sorensen", "euclidean"), default="sorensen",
                    help="kNN distance on powed fingerprints: Sorensen / Bray-Curtis (default) or Euclidean")
    lo.add_argument("--max-age", type=float, default=8.0, help="ignore readings older than this at scan time, s (default 8)")
    lo.set_defaults(func=_cmd_locate)

    sm = sub.add_parser("sim", help="simulated buildings and walks with ground truth")
    ssub = sm.add_subparsers(dest="sim_command", required=True)
    sw = ssub.add_parser("world", help="generate a multi-floor building with WiFi, BLE and RFID infrastructure")
    sw.add_argument("--seed", type=int, required=True)
    sw.add_argument("--floors", type=int, default=3, help="floors of a generated building (default 3)")
    sw.add_argument("--floorplan", metavar="DIR", help="build the world on a real floor plan instead: a site folder in the Indoor Location "
                    "Competition layout (<floor>/geojson_map.json); walkers route through its corridors")
    sw.add_argument("--out", required=True)
    sw.set_defaults(func=_cmd_sim_world)
    sk = ssub.add_parser("walk", help="simulate walkers in a world: traces in the ILC format, foot IMU CSV, truth")
    sk.add_argument("--world", required=True)
    sk.add_argument("--walkers", type=int, default=1)
    sk.add_argument("--minutes", type=float, default=5.0)
    sk.add_argument("--carrier", choices=("phone", "foot", "both"), default="phone")
    sk.add_argument("--seed", type=int, default=0, help="seed of the walkers (the world has its own)")
    sk.add_argument("--out", required=True)
    sk.set_defaults(func=_cmd_sim_walk)

    ev = sub.add_parser("eval", help="evaluation commands that print figures")
    esub = ev.add_subparsers(dest="eval_command", required=True)
    ep = esub.add_parser("pdr-phone", help="phone PDR against waypoints of Indoor Location Competition traces")
    ep.add_argument("dir", help="a site or floor folder, e.g. ../shared/data/msft-ilc/site1")
    ep.add_argument("--model", choices=LENGTH_MODELS, default="height")
    ep.add_argument("--detector", choices=("peak", "autocorr"), default="peak")
    ep.add_argument("--every", type=int, default=1, help="use every N-th trace (default all)")
    ep.set_defaults(func=_cmd_eval_pdr_phone)

    ef = esub.add_parser("pdr-foot", help="foot INS against PyShoe VICON ground truth (ARMSE, return-to-start)")
    ef.add_argument("dir", help="folder of PyShoe .mat trials, e.g. ../shared/data/pyshoe-vicon")
    ef.set_defaults(func=_cmd_eval_pdr_foot)

    efp = esub.add_parser("fingerprint", help="fingerprint positioning on UJIIndoorLoc and Indoor Location Competition data")
    efp.add_argument("--uji", default="../shared/data/ujiindoorloc/trainingData.csv.gz", help="UJIIndoorLoc CSV ('' to skip)")
    efp.add_argument("--uji-validation", metavar="CSV", help="UJIIndoorLoc validation file for the standard split (default: validationData.csv "
                     "beside --uji when present; '' to skip)")
    efp.add_argument("--ilc", default="../shared/data/msft-ilc/site1", help="Indoor Location Competition site folder ('' to skip)")
    efp.add_argument("--folds", type=int, default=4, help="trace folds for the ILC leave-traces-out test")
    efp.add_argument("--every", type=int, default=1, help="use every N-th ILC trace")
    efp.set_defaults(func=_cmd_eval_fingerprint)

    esr = esub.add_parser("sim-realism", help="simulated statistics beside real ones; phone PDR step counts on simulated walks")
    esr.add_argument("--ilc", default="../shared/data/msft-ilc/site1", help="real Indoor Location Competition site folder ('' to skip)")
    esr.add_argument("--walkers", type=int, default=60, help="simulated walkers (default 60: ~11 min of phone handling, for a steady false-step rate)")
    esr.add_argument("--minutes", type=float, default=5.0)
    esr.add_argument("--every", type=int, default=3, help="use every N-th real trace")
    esr.add_argument("--seed", type=int, default=1, help="simulated building and walkers (1 is the default; others are fresh samples)")
    esr.set_defaults(func=_cmd_eval_sim_realism)

    efu = esub.add_parser("fusion", help="PDR only, WiFi only and fused at waypoints, through the real client and server path")
    efu.add_argument("dir", help="Indoor Location Competition site folder, e.g. ../shared/data/msft-ilc/site1")
    efu.add_argument("--out", default="out/eval-fusion")
    efu.add_argument("--replay-every", type=int, default=4, help="every N-th trace is a phone client, the rest are surveys (default 4)")
    efu.add_argument("--every", type=int, default=1, help="use every N-th trace of the site")
    efu.set_defaults(func=_cmd_eval_fusion)

    demo = sub.add_parser("demo", help="the platform end to end: server, surveys, radio map, phone clients, scores, PNG")
    demo.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    demo.add_argument("--sim", action="store_true", help="use a simulated building instead of the bundled real sample")
    demo.add_argument("--speed", type=float, default=20.0, help="replay speed of the phone clients (default 20x)")
    demo.set_defaults(func=_cmd_demo)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2), format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError) as exc:
        print(f"hybridloc: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

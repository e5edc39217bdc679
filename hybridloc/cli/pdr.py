"""``hybridloc pdr phone`` and ``hybridloc pdr foot``: dead reckoning of recordings, CSV files per input."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from ..errors import BadInput
from ._common import LENGTH_MODELS, load_imu, open_calibration, report_input_error


def _cmd_pdr_phone(args: argparse.Namespace) -> int:
    from ..io.common import stem_of
    from ..io.writers import write_trajectory_csv
    from ..pdr import PhonePdr, PhonePdrConfig, dead_reckon, make_model
    from ..pdr.files import parse_start, write_steps_csv

    x0, y0, h0 = parse_start(args.start)
    out = Path(args.out)
    cal, cal_path = open_calibration(args.calibration, args.update_calibration, args.model)
    status = 0
    for p in args.traces:
        try:
            imu, report, device, marks, _ = load_imu(p, args.format, None, args.accel_unit)
        except Exception as exc:  # one line per unreadable input, then the next input
            status = max(status, report_input_error(p, exc))
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
        print(
            f"{p}: {len(steps)} steps over {imu.duration:.1f} s ({model.name} {coef_used}), "
            f"{degraded} with degraded heading, gaps {st.gaps}, saturated samples {st.saturated}, rejected samples: {rej}; input: {report.summary()} -> {d}"
        )
    return status


def _update_calibration(path: str, cal, cal_path: Path, steps, features, marks) -> None:
    """The device's step-length calibration, updated from this walk's waypoint segments (known
    distances) and saved; a walk without marked points leaves it as it was."""
    import numpy as np

    from ..pdr.steplength import calibrate_from_marks

    if marks is None or len(marks) < 2:
        print(f"{path}: no waypoints (known distances): calibration {cal_path} not updated", file=sys.stderr)
        return
    before = [float(c) for c in cal.model.coef]
    n = calibrate_from_marks(cal, np.array([s.t for s in steps]), features, marks.t, marks.pos_enu)
    if n:
        cal.save(cal_path)
    print(
        f"{path}: calibration {cal_path}: {n} waypoint segments, {cal.model.name} {before} -> {[float(c) for c in cal.model.coef]} "
        f"({cal.n_segments} segments in all)"
    )


def _cmd_pdr_foot(args: argparse.Namespace) -> int:
    import csv

    from ..ins.foot import FootInsConfig, run_foot_ins, strides
    from ..io.common import stem_of
    from ..pdr.files import write_steps_csv

    hde = None
    if args.hde is not None:
        from dataclasses import replace

        from ..ins.hde import HDE_DEFAULT
        from ..pdr.files import parse_start

        try:
            hde = replace(HDE_DEFAULT, grid=None if args.hde == "learn" else parse_start(f"0,0,{args.hde}")[2])
        except ValueError as exc:
            raise BadInput(f"--hde {args.hde!r}: a grid direction in rad or e.g. 30deg ({exc})") from exc
    from ..ins.foot import FOOT_PRESETS

    # the preset's settings (none: FootInsConfig's defaults), then the options given explicitly over them
    opts = dict(FOOT_PRESETS[args.preset]) if args.preset else {}
    if args.detector is not None:
        opts["detector"] = args.detector
    if args.vet_demoted:
        opts["vet_demoted"] = True
    if args.zaru_up is not None:
        if not (math.isfinite(args.zaru_up) and args.zaru_up > 0):
            raise BadInput(f"--zaru-up {args.zaru_up}: a standard deviation in deg/s, above 0")
        opts["zaru_up_sigma"] = math.radians(args.zaru_up)
    cfg = FootInsConfig(detector_threshold=args.threshold, smooth=not args.forward, hde=hde, **opts)
    out = Path(args.out)
    status = 0
    for p in args.files:
        try:
            imu, report, _, _, fmt = load_imu(p, args.format, args.rate, args.accel_unit)
            if args.rate and args.format != "openshoe" and abs(imu.rate_hz - args.rate) > 0.05 * args.rate:
                raise BadInput(f"--rate {args.rate} Hz disagrees with the file's timestamps ({imu.rate_hz:.1f} Hz)")
            if not 50.0 <= imu.rate_hz <= 2000.0:
                raise BadInput(f"sample rate {imu.rate_hz:.1f} Hz is implausible for a foot-mounted IMU (50-2000 Hz)")
        except Exception as exc:  # one line per unreadable input, then the next input
            status = max(status, report_input_error(p, exc))
            continue
        res = run_foot_ins(imu, cfg)
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
        print(
            f"{p}: {len(res.t)} samples at {imu.rate_hz:.1f} Hz, {len(st)} strides, {s['stance_samples']} stance samples, "
            f"gaps {s['gaps']}, NaN samples {s['nan_samples']}, saturated samples {s['saturated_samples']} ({100 * s['saturated_samples'] / max(len(res.t), 1):.1f} %), re-initialisations {s['reinit']}; "
            f"input: {report.summary()} -> {d}"
            + (f"; drift elimination: {s['hde_accepted']} of {s['hde_strides']} strides measured as a dominant direction" if hde is not None else "")
            + (
                "; a SensorConnect recording with the default settings: --preset gait-driven applies those chosen held out for the 3DM-GX5-25"
                if not args.preset and args.detector is None and fmt == "sensorconnect"
                else ""
            )
        )
    return status


def register(sub) -> None:
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
    ph.add_argument(
        "--update-calibration",
        action="store_true",
        help="after each input, update --calibration from its waypoint segments (known distances; robust to a mis-marked one) and save it; "
        "created from --model when absent",
    )
    ph.add_argument("--detector", choices=("peak", "autocorr"), default="peak", help="step detector family (default peak)")
    ph.add_argument("--offset", type=float, default=0.0, help="walking direction minus device heading, rad (phone in pocket/bag)")
    ph.add_argument(
        "--estimate-offset",
        action="store_true",
        help="estimate the walking offset from the gait (horizontal acceleration's principal axis, "
        "its forward half the one rising with the vertical): for a phone in a pocket or bag; held in front, leave it off",
    )
    ph.set_defaults(func=_cmd_pdr_phone)

    ft = psub.add_parser("foot", help="foot-mounted INS (ZUPT-aided error-state EKF): trajectory.csv and steps.csv per input")
    ft.add_argument("files", nargs="+", metavar="FILE")
    ft.add_argument("--out", required=True, help="output folder; writes <out>/<input-stem>/{trajectory,steps}.csv")
    ft.add_argument(
        "--format",
        choices=("csv", "pyshoe", "openshoe", "sensorconnect"),
        help="input format (detected by default; sensorconnect: a MicroStrain SensorConnect CSV export)",
    )
    ft.add_argument(
        "--rate", type=float, metavar="HZ", help="sample rate for files without timestamps (OpenShoe); checked against timestamps otherwise"
    )
    ft.add_argument("--accel-unit", choices=("m/s^2", "g"), default="m/s^2", help="accelerometer unit of a plain IMU CSV")
    ft.add_argument(
        "--detector",
        choices=("adaptive", "robust", "shoe", "ared", "amvd", "mbgtd"),
        help="stance detector (default adaptive SHOE, or the preset's; robust: its ZUPTs, strides cut at one stance per step, for a sensor "
        "that dips mid-swing)",
    )
    ft.add_argument(
        "--preset",
        choices=("gait-driven",),
        help="settings chosen held out for a sensor family (hybridloc.ins.foot.FOOT_PRESETS); explicit options override them. gait-driven: "
        "a MicroStrain 3DM-GX5-25 on the foot (--detector robust --zaru-up 5 --vet-demoted, what eval pdr-foot chooses on the gait-driven "
        "walks); default: none (PyShoe's sensor's settings)",
    )
    ft.add_argument("--threshold", type=float, help="the detector's threshold in its units (see hybridloc.ins.stance)")
    ft.add_argument(
        "--forward",
        action="store_true",
        help="write the forward filter's track (what a live client has at each sample) instead of the default track smoothed back over each stride from its stance (RTS)",
    )
    ft.add_argument(
        "--hde",
        nargs="?",
        const="learn",
        metavar="GRID",
        help="heuristic drift elimination: straight strides near a dominant direction of the building (GRID + k 90 deg in the INS frame, "
        "rad or e.g. 30deg; without GRID learned from the walk's first straight stretch) are measured as that direction (hybridloc.ins.hde); "
        "off by default",
    )
    ft.add_argument(
        "--zaru-up",
        type=float,
        metavar="DEG_S",
        help="vertical zero angular rate at stance with this sigma in deg/s (hybridloc.ins.measurements.ZeroYawRate): the gyro's bias about "
        "the body's up axis, which a foot that rolls through its stance keeps from the 3-D update; off by default (eval pdr-foot chooses it: 5 with --detector robust --vet-demoted on the gait-driven walks)",
    )
    ft.add_argument(
        "--vet-demoted",
        action="store_true",
        help="with --detector robust: the ZUPTs of the stance runs not kept as a step's (mid-swing dips, fragments of a rolling stance) "
        "pass the chi-square gate instead of being applied as any stance's (FootInsConfig.vet_demoted); off by default",
    )
    ft.set_defaults(func=_cmd_pdr_foot)

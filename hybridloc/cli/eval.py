"""``hybridloc eval ...``: evaluation commands that print figures (a human table, then one JSON line of the headline figures)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import MissingData
from ._common import LENGTH_MODELS, print_headline


def _cmd_eval_pdr_phone(args: argparse.Namespace) -> int:
    import math

    import numpy as np

    from ..io.msft import find_ilc_traces
    from ..metrics import summarize_errors
    from ..pdr import PhonePdrConfig
    from ..pdr.evaluate import (
        collect_runs,
        decompose_segment_errors,
        decompose_turn_errors,
        evaluate_phone_pdr,
        fit_model,
        marks_on_straight_walks,
        offset_recovery,
    )

    paths = find_ilc_traces(args.dir)[:: args.every]
    if not paths:
        raise MissingData(f"no Indoor Location Competition traces under {args.dir}")
    cfg = PhonePdrConfig(detector=args.detector)
    runs, skipped = collect_runs(paths, cfg)
    if not runs:
        raise MissingData(f"{args.dir}: no trace with IMU data and waypoints ({len(skipped)} skipped)")
    print(
        f"phone PDR on {len(runs)} traces of {args.dir} (detector {args.detector}; {len(skipped)} skipped); "
        "lengths calibrated by 2-fold cross-fitting over traces"
    )
    print(
        f"{'model':<10} {'coef (fold A | B)':<34} {'len p50':>8} {'len p90':>8} {'turn p50':>9} {'turn p90':>9} {'wp p50':>7} {'wp p90':>7} {'segs':>5}"
    )

    def row(name: str, r) -> None:
        coef = " | ".join(",".join(f"{c:.3f}" for c in cf) for cf in r.coefs)
        wp = summarize_errors(r.wp_err)
        print(
            f"{name:<10} {coef:<34} {100 * np.median(r.length_rel_err):7.1f}% {100 * np.percentile(r.length_rel_err, 90):7.1f}% "
            f"{np.median(r.turn_err_deg):8.1f}d {np.percentile(r.turn_err_deg, 90):8.1f}d {wp.median:6.2f}m {wp.p90:6.2f}m {r.n_segments:5d}"
        )

    res = {}
    for m in LENGTH_MODELS:
        res[m] = evaluate_phone_pdr(paths, m, cfg, runs=runs)
        row(m, res[m])
    main_m = res[args.model]
    andr = evaluate_phone_pdr(paths, args.model, cfg, runs=runs, heading="android")
    if andr.n_segments:
        row("+android", andr)
    print(
        f"\n{args.model}: segment length error median {100 * np.median(main_m.length_rel_err):.1f}% (goal <= 5%), "
        f"90th pct {100 * np.percentile(main_m.length_rel_err, 90):.1f}% (goal <= 15%); heading-change error median "
        f"{np.median(main_m.turn_err_deg):.1f} deg (goal <= 8); error at waypoints from the first one: {summarize_errors(main_m.wp_err)}"
    )
    if andr.n_segments:
        print(
            f"heading against Android's own fused attitude (+android: {args.model} lengths, our steps, heading from TYPE_ROTATION_VECTOR "
            f"on {andr.n_traces} traces): heading-change error median {np.median(andr.turn_err_deg):.1f} deg, ratio ours/Android "
            f"{np.median(main_m.turn_err_deg) / np.median(andr.turn_err_deg):.2f}; mean error at waypoints ratio {np.mean(main_m.wp_err) / np.mean(andr.wp_err):.2f}"
        )
    base = np.median(res["constant"].length_rel_err)
    print(f"ratio of median length error {args.model} / constant-length baseline: {np.median(main_m.length_rel_err) / base:.2f}")
    print(f"{main_m.n_steps} steps over {main_m.walked_m:.0f} m of waypoint-to-waypoint walking")
    s_end, s_rel = decompose_segment_errors(main_m.seg_true_m, main_m.seg_err_m)
    d_med = float(np.median(main_m.seg_true_m))
    print(
        f"segment errors decompose (robust fit, sigmas) as +-{s_end:.2f} m fixed per segment (waypoint marks, where and "
        f"when; the track cut at the mark times) and +-{100 * s_rel:.1f}% of length (the PDR's scale); the fixed part alone "
        f"gives a median relative error of about {100 * 0.6745 * s_end / d_med:.1f}% on the median segment ({d_med:.1f} m)"
    )
    s_turn, s_mark = decompose_turn_errors(main_m.turn_lengths_m, main_m.turn_err_rad)
    own = (
        f"+-{math.degrees(s_turn):.1f} deg the PDR's own heading-change error (median {0.6745 * math.degrees(s_turn):.1f} deg)"
        if s_turn > 1e-3
        else "a part independent of segment length not resolvable from 0"
    )
    print(
        f"turn errors decompose (robust fit, sigmas) as {own} and +-{s_mark:.2f} m across the segment at each end "
        f"(the waypoint marks, and the PDR track's sideways position at the mark times): the turn error shrinks as 1/length"
    )
    straight, n_turns = marks_on_straight_walks(runs, fit_model(runs, args.model))
    if straight.size:
        print(
            f"marks on straight walks: where our heading and Android's both see a turn under 5 deg ({straight.size} of {n_turns} turns), the "
            f"waypoints turn by median {np.median(straight):.1f} deg, p90 {np.percentile(straight, 90):.1f} deg, {100 * np.mean(straight >= 10):.0f}% "
            "by 10 deg or more: the marks' own direction error, which no PDR removes"
        )
    rec = offset_recovery(paths[::5])
    share = {r: {a: 100 * float(np.mean(v < math.radians(20))) if len(v) else float("nan") for a, v in d.items()} for r, d in rec.items()}
    angles = list(rec["gait"])
    print(
        f"walking-direction offset (phone carried turned by {' / '.join(f'{a:g}' for a in angles)} deg about its screen's normal, "
        f"{len(rec['gait'][angles[0]])} real walks re-oriented; walk heading within 20 deg of the unturned phone's): ours (sign from the gait) "
        + " / ".join(f"{share['gait'][a]:.0f}" for a in angles)
        + " %, the principal axis signed by continuity (textbook) "
        + " / ".join(f"{share['continuity'][a]:.0f}" for a in angles)
        + " %"
    )
    wp = summarize_errors(main_m.wp_err)
    held: dict = {}
    k_mags = tuple(float(k) for k in args.k_mags.split(",") if k.strip())
    floors_seen = {r.floor for r in runs}
    if len(floors_seen) > 1 and k_mags:
        from ..pdr.evaluate import floor_held_out

        fh = floor_held_out(paths, cfg, runs, args.model, k_mags)
        print(
            f"held out by floor ({len(fh.floors)} floors): the magnetometer's yaw pull k_mag chosen on the other floors from "
            + ", ".join(f"{k:g}" for k in k_mags)
            + " ("
            + ", ".join(f"{f} {fh.chosen[f]:g}" for f in fh.floors)
            + f"), lengths ({args.model}) fitted on the other floors; plain baseline (our peak steps, Weinberg lengths, Android's "
            f"rotation vector, {fh.plain_traces} traces) held out alike"
        )
        for f in fh.floors:
            print(
                f"  {f}: heading-change median {fh.turn_med[f]:5.1f} deg (plain {fh.plain_turn_med[f]:5.1f}), segment length median "
                f"{fh.length_med[f]:5.1f}% (plain {fh.plain_length_med[f]:5.1f}%)"
            )
        print(
            f"  all floors, held out: heading-change median {fh.turn_held_out:.1f} deg, segment length median {fh.length_held_out:.1f}%; "
            f"fitted (k_mag {fh.fitted_k_mag:g} on every floor): {fh.turn_fitted:.1f} deg, {fh.length_fitted:.1f}%; plain {fh.plain_turn:.1f} deg, "
            f"{fh.plain_length:.1f}% (ratio ours/plain {fh.turn_held_out / fh.plain_turn:.2f} heading, {fh.length_held_out / fh.plain_length:.2f} length)"
        )
        below = sum(fh.length_med[f] < fh.plain_length_med[f] for f in fh.floors)
        print(
            f"  goal: heading-change <= 10 deg held out by floor; segment length median below the plain baseline's on every floor ({below} of {len(fh.floors)})"
        )
        held = {
            "turn_error_held_out_by_floor_deg": fh.turn_held_out,
            "turn_error_fitted_deg": fh.turn_fitted,
            "turn_error_plain_held_out_deg": fh.plain_turn,
            "segment_length_held_out_by_floor_median_pct": fh.length_held_out,
            "segment_length_plain_held_out_median_pct": fh.plain_length,
            "floors_length_below_plain": below,
            "turn_error_worst_floor_deg": max(fh.turn_med.values()),
        }
    print_headline(
        {
            "segment_length_median_pct": 100 * np.median(main_m.length_rel_err),
            "segment_length_p90_pct": 100 * np.percentile(main_m.length_rel_err, 90),
            "turn_error_median_deg": np.median(main_m.turn_err_deg),
            "waypoint_error_mean_m": wp.mean,
            "waypoint_error_median_m": wp.median,
            "length_error_ratio_to_constant": np.median(main_m.length_rel_err) / base,
            "steps": main_m.n_steps,
            "walked_m": main_m.walked_m,
            **held,
        }
    )
    return 0


def _cmd_eval_pdr_foot(args: argparse.Namespace) -> int:
    import numpy as np

    from ..ins.evaluate import LOOP_CLOSE_M, evaluate_trial

    files = sorted(Path(args.dir).glob("*.mat"))
    if not files:
        raise MissingData(f"no PyShoe .mat trials in {args.dir}")
    print(
        f"foot INS (15-state ESKF, ZUPT, default adaptive SHOE detector, one setting for all, strides RTS-smoothed) on {len(files)} PyShoe VICON trials"
    )
    print(
        "ARMSE: the smoothed track `hybridloc pdr foot` writes; fwd: the forward filter alone (a live client's track, and what the "
        "authors' figure is); ours@opt: our forward filter on the authors' per-trial-optimal stance labels"
    )
    print(f"{'trial':<22} {'ARMSE 2D':>9} {'fwd 2D':>8} {'ARMSE 3D':>9} {'authors':>8} {'ours@opt':>9} {'DEDRIFT-I':>10} {'dist m':>7} {'loop %':>7}")
    rows = []
    for f in files:
        r = evaluate_trial(f)
        rows.append(r)
        loop = f"{r.loop_pct:6.2f}%" if r.loop_pct is not None else "      -"
        print(
            f"{r.name:<22} {r.armse_2d:8.3f}m {r.forward_2d:7.3f}m {r.armse_3d:8.3f}m {r.authors_2d:7.3f}m {r.opt_labels_2d:8.3f}m {r.dedrift_2d:9.3f}m "
            f"{r.distance_m:7.1f} {loop}"
        )
    a2 = np.array([r.armse_2d for r in rows])
    a3 = np.array([r.armse_3d for r in rows])
    au = np.array([r.authors_2d for r in rows])
    dd = np.array([r.dedrift_2d for r in rows])
    loops = [r.loop_pct for r in rows if r.loop_pct is not None]
    fw = np.array([r.forward_2d for r in rows])
    print(f"\nmean 2-D ARMSE {a2.mean():.4f} m (median {np.median(a2):.4f}), stride-smoothed; goal <= 0.059 m, the authors' figure on all 56 trials")
    print(f"forward filter alone: mean 2-D ARMSE {fw.mean():.4f} m (median {np.median(fw):.4f}); the authors' figure is a forward filter's")
    print(f"mean 3-D ARMSE {a3.mean():.4f} m (median {np.median(a3):.4f}), stride-smoothed")
    print(
        f"authors' per-trial-tuned SHOE on these {len(rows)} trials: mean {au.mean():.4f} m; ratio ours/authors {a2.mean() / au.mean():.2f} smoothed, "
        f"{fw.mean() / au.mean():.2f} forward"
    )
    op = np.array([r.opt_labels_2d for r in rows])
    if np.isfinite(op).all() and np.isfinite(fw).all():
        print(
            f"our forward filter on the authors' per-trial-optimal SHOE stance labels (ours@opt): mean {op.mean():.4f} m; so of the forward gap "
            f"{fw.mean() - au.mean():+.4f} m to the authors, our one-setting detector accounts for {fw.mean() - op.mean():+.4f} and the filter for "
            f"{op.mean() - au.mean():+.4f}"
        )
    print(f"plain DEDRIFT-I (Ojeda) in the same run: mean 2-D ARMSE {dd.mean():.3f} m; ratio ours/DEDRIFT-I {a2.mean() / dd.mean():.3f}")
    if loops:
        print(f"closed loops ({len(loops)}): mean return-to-start error {np.mean(loops):.2f}% of distance travelled (Ojeda eq 9)")
    head = {
        "armse_mean_m": a2.mean(),
        "armse_median_m": np.median(a2),
        "armse_forward_mean_m": fw.mean(),
        "armse_3d_mean_m": a3.mean(),
        "authors_armse_mean_m": au.mean(),
        "dedrift_armse_mean_m": dd.mean(),
        "loop_error_mean_pct": np.mean(loops) if loops else float("nan"),
        "trials": len(rows),
    }
    decades = [float(x) for x in args.decades.split(",") if x.strip()]
    grid = _foot_held_out(files, decades, head) if decades else None
    gait = args.gait
    if gait is None and Path(_GAIT_DEFAULT).is_dir():
        gait = _GAIT_DEFAULT
    gait_walks_rs = _foot_gait(gait, decades, grid, head) if gait else None
    if args.sim_loops:
        from ..ins.evaluate import simulated_loop_errors

        sim = simulated_loop_errors(args.sim_loops)
        print(
            f"\nsimulated closed loops ({args.sim_loops}, 1.5 min each, industrial-grade foot IMU at 200 Hz, default detector): return error "
            f"median {np.median(sim):.2f} %, max {sim.max():.2f} % of path ({', '.join(f'{x:.2f}' for x in sim)})"
        )
        head["sim_return_error_median_pct"] = np.median(sim)
        head["sim_return_error_max_pct"] = sim.max()
    if loops:
        # Ojeda's figure counts the truth's own gap (up to LOOP_CLOSE_M) as error; the end against the true end does not
        loop_all = np.array(loops)
        net = np.array([r.end_pct for r in rows if r.loop_pct is not None])
        print(
            f"PyShoe trials whose truth returns within {LOOP_CLOSE_M:g} m of its start ({len(loops)}): return error (Ojeda, end to start) median "
            f"{np.median(loop_all):.2f} %, max {loop_all.max():.2f} %; end against the true end (after PyShoe's alignment) median "
            f"{np.median(net):.2f} %, max {net.max():.2f} % of path"
        )
        head["loop_error_median_pct"] = np.median(loop_all)
        head["loop_error_max_pct"] = loop_all.max()
        head["loop_end_error_median_pct"] = np.median(net)
        head["loop_end_error_max_pct"] = net.max()
    if gait_walks_rs is not None:
        _foot_hde(*gait_walks_rs, files, args.sim_loops, head)
        _foot_zaru_up(*gait_walks_rs, files, args.sim_loops, head)
    print_headline(head)
    return 0


_GAIT_DEFAULT = "../shared/data/gait-driven-own"


def _foot_held_out(files: list, decades: list[float], head: dict):
    """PyShoe, the adaptive detector's one threshold (``decades``) chosen leave one recording day out."""
    import numpy as np

    from ..ins.evaluate import foot_joint_candidates, leave_one_group_out, pyshoe_armse_grid, pyshoe_group

    joint_configs = foot_joint_candidates(decades)
    joint = pyshoe_armse_grid(files, joint_configs, workers=2)
    grid = joint[:, : len(decades)]  # the thresholds alone, the other constants at their defaults
    groups = [pyshoe_group(f) for f in files]
    chosen, held = leave_one_group_out(grid, groups)
    best = int(np.argmin(grid.mean(axis=0)))
    print(
        f"\nheld out: the adaptive detector's threshold (decades above the cycle's minimum, candidates {','.join(f'{d:g}' for d in decades)}) "
        "chosen on the other recording days' mean ARMSE, scored on the day left out (the smoothed track)"
    )
    print(f"{'day':<12} {'trials':>6} {'chosen':>7} {'held out':>9} {'fitted':>8}")
    for g in sorted(set(groups)):
        m = np.array(groups) == g
        print(f"{g:<12} {m.sum():6d} {decades[chosen[m][0]]:7g} {held[m].mean():8.4f}m {grid[m, best].mean():7.4f}m")
    print(
        f"mean 2-D ARMSE held out by day {held.mean():.4f} m (median {np.median(held):.4f}) beside fitted on all {len(files)} "
        f"{grid[:, best].mean():.4f} m (decades {decades[best]:g}); per-candidate means "
        + ", ".join(f"{d:g}: {v:.4f}" for d, v in zip(decades, grid.mean(axis=0)))
    )
    print("  (only this threshold is held out: the detector's and filter's design, and their other constants, were chosen on these same 28 trials)")
    head["armse_held_out_mean_m"] = held.mean()
    head["armse_held_out_median_m"] = np.median(held)
    head["armse_fitted_mean_m"] = grid[:, best].mean()
    _foot_held_out_joint(joint, joint_configs, groups, head)
    return grid


def _foot_held_out_joint(joint, configs: list, groups: list[str], head: dict) -> None:
    """The threshold, the ZUPT's sigma and the turn-on bias priors chosen together, leaving one recording day out."""
    import numpy as np

    from ..ins.evaluate import leave_one_group_out
    from ..units import DEG

    def label(c) -> str:
        return f"threshold {c.detector_threshold:g}, ZUPT {c.zupt_sigma:g} m/s, bias priors {c.noise.accel_bias_sigma0:g} m/s^2 / {c.noise.gyro_bias_sigma0 / DEG:g} deg/s"

    chosen, held = leave_one_group_out(joint, groups)
    best = int(np.argmin(joint.mean(axis=0)))
    print(
        "\nheld out, jointly: the threshold, the ZUPT's velocity sigma and the accelerometer / gyroscope turn-on bias priors "
        f"({len(configs)} candidates) chosen on the other recording days, scored on the day left out"
    )
    for g in sorted(set(groups)):
        m = np.array(groups) == g
        print(f"  {g}: {m.sum()} trials, chose {label(configs[chosen[m][0]])}; held out {held[m].mean():.4f} m, fitted {joint[m, best].mean():.4f} m")
    print(
        f"mean 2-D ARMSE held out by day {held.mean():.4f} m (median {np.median(held):.4f}) beside fitted on all {len(held)} "
        f"{joint[:, best].mean():.4f} m ({label(configs[best])}); goal <= 0.062 m held out"
    )
    print("  (the detector's and filter's design and the IMU's noise densities, PyShoe's own, are not searched)")
    head["armse_held_out_joint_mean_m"] = held.mean()
    head["armse_held_out_joint_median_m"] = np.median(held)
    head["armse_fitted_joint_mean_m"] = joint[:, best].mean()


def _foot_gait(folder: str, decades: list[float], grid, head: dict) -> tuple[list, list]:
    """The gait-driven walks stride by stride, with the settings fitted on PyShoe, and the reverse."""
    from dataclasses import replace

    import numpy as np

    from ..ins import stance as stance_mod
    from ..ins.evaluate import GAIT_ALIGN_M, GAIT_CLOSE_FRACTION, evaluate_gait_walk, gait_walks, summarize_gait
    from ..ins.foot import FootInsConfig

    walks = gait_walks(folder)
    if not walks:
        raise MissingData(f"no gait-driven walks (SensorConnect CSV + footprint .mat) in {folder}")
    base = FootInsConfig(detector="robust")
    rs_ad = [evaluate_gait_walk(w, FootInsConfig()) for w in walks]
    rs = [evaluate_gait_walk(w, base) for w in walks]
    print(
        f"\ngait-driven walks ({folder}, {len(walks)} walks, 3DM-GX5-25, other walkers): settings as above, none fitted on this set but the shortest stance "
        f"(robust: the adaptive detector's ZUPTs, strides cut at one stance per step, shortest swing {base.min_swing:g} s, a physical bound, and shortest stance "
        f"{base.min_stance:g} s, chosen on these walks' stride counts below)"
    )
    print(
        f"footprints: the stance middles; the estimate starts at the true start, its heading turned so that its first footprint "
        f"{GAIT_ALIGN_M:g} m out points as the truth's does; per-stride error only where the strides were counted exactly; "
        f"return: walks whose truth ends within {100 * GAIT_CLOSE_FRACTION:g} % of the path from its start"
    )
    print(f"{'walk':<22} {'walked':>6} {'adaptive':>8} {'robust':>7} {'fp p50':>7} {'fp max':>7} {'final':>7} {'path m':>7} {'closes':>6}")
    for a, r in zip(rs_ad, rs):
        fe = r.footprint_err_m
        f50 = f"{np.median(fe):6.2f}m" if fe is not None else "      -"
        fmx = f"{np.max(fe):6.2f}m" if fe is not None else "      -"
        print(
            f"{r.name:<22} {r.n_walked:6d} {a.n_detected - a.n_walked:+8d} {r.n_detected - r.n_walked:+7d} {f50} {fmx} "
            f"{r.final_pct:6.2f}% {r.distance_m:7.1f} {'yes' if r.closes else '':>6}"
        )
    sa, sr = summarize_gait(rs_ad), summarize_gait(rs)
    for name, sm in (("adaptive", sa), ("robust", sr)):
        print(
            f"{name:<9} strides counted exactly on {sm.count_exact} of {sm.walks} walks (mean |error| {sm.count_abs_err_mean:.1f} strides); "
            f"footprint error median {sm.footprint_median_m:.3f} m, p90 {sm.footprint_p90_m:.3f} m (exactly counted walks); "
            f"final point median {sm.final_median_pct:.2f} %, max {sm.final_max_pct:.2f} % of path; "
            f"return ({sm.closing} closing walks) median {sm.return_median_pct:.2f} %, max {sm.return_max_pct:.2f} %"
        )
    head.update(
        {
            "gait_walks": sr.walks,
            "gait_stride_count_exact": sr.count_exact,
            "gait_stride_count_exact_adaptive": sa.count_exact,
            "gait_stride_count_abs_err_mean": sr.count_abs_err_mean,
            "gait_footprint_error_median_m": sr.footprint_median_m,
            "gait_final_error_median_pct": sr.final_median_pct,
            "gait_final_error_max_pct": sr.final_max_pct,
            "gait_return_error_pct": sr.return_median_pct,
            "gait_return_error_max_pct": sr.return_max_pct,
        }
    )
    # the shortest swing, chosen leave one walk out on the stride counts (the gait set's own truth)
    swings = stance_mod.MIN_SWING_CANDIDATES_S
    cnt, chosen, held, bj = _stride_count_choice(walks, rs, base, "min_swing", swings)
    print(
        f"shortest swing ({','.join(f'{x:g}' for x in swings)} s) chosen leave one walk out on |stride count error|: held out exact on "
        f"{int((held == 0).sum())} of {len(walks)} (mean |error| {held.mean():.2f}), fitted on all ({swings[bj]:g} s) {int((cnt[:, bj] == 0).sum())} "
        f"(mean {cnt[:, bj].mean():.2f}); the default {base.min_swing:g} s (not fitted): {int((cnt[:, swings.index(base.min_swing)] == 0).sum())}"
    )
    head["gait_stride_count_exact_held_out"] = int((held == 0).sum())
    # the shortest stance of a step, chosen alike (a shorter run is a mid-swing dip: stance.MIN_STANCE_S)
    stances = stance_mod.MIN_STANCE_CANDIDATES_S
    cnt, chosen, held, bj = _stride_count_choice(walks, rs, base, "min_stance", stances)
    same = int((np.asarray(stances)[chosen] == base.min_stance).sum())
    print(
        f"shortest stance ({','.join(f'{x:g}' for x in stances)} s) chosen leave one walk out on |stride count error|: held out exact on "
        f"{int((held == 0).sum())} of {len(walks)} (mean |error| {held.mean():.2f}; the default {base.min_stance:g} s chosen in {same} of "
        f"{len(walks)} folds), fitted on all ({stances[bj]:g} s) {int((cnt[:, bj] == 0).sum())} (mean {cnt[:, bj].mean():.2f}); "
        f"with no bound (0 s): {int((cnt[:, stances.index(0.0)] == 0).sum())}; the sections below run the default, so their held-out "
        f"figures are nested in this choice only where every fold made it"
    )
    head["gait_stride_count_exact_held_out_min_stance"] = int((held == 0).sum())
    if grid is not None and decades:
        # the reverse: the adaptive threshold fitted on the gait walks' final-point error, scored on PyShoe
        fin = np.zeros((len(walks), len(decades)))
        for j, d in enumerate(decades):
            for i, w in enumerate(walks):
                fin[i, j] = evaluate_gait_walk(w, replace(base, detector_threshold=d)).final_pct
        gj = int(np.argmin(np.median(fin, axis=0)))
        pj = int(np.argmin(grid.mean(axis=0)))
        print(
            f"cross-set, the threshold (decades): fitted on PyShoe ({decades[pj]:g}) -> gait final point median {np.median(fin[:, pj]):.2f} % "
            f"(fitted on gait, {decades[gj]:g}: {np.median(fin[:, gj]):.2f} %); fitted on gait -> PyShoe mean ARMSE {grid[:, gj].mean():.4f} m "
            f"(fitted on PyShoe: {grid[:, pj].mean():.4f} m); per-candidate gait medians "
            + ", ".join(f"{d:g}: {v:.2f} %" for d, v in zip(decades, np.median(fin, axis=0)))
        )
        head["armse_gait_fitted_mean_m"] = grid[:, gj].mean()
        head["gait_final_error_pyshoe_fitted_median_pct"] = np.median(fin[:, pj])
    return walks, rs


def _stride_count_choice(walks: list, rs: list, base, field: str, candidates) -> tuple:
    """|stride count error| of each gait walk (rows) with the robust detector's ``field`` at each of
    ``candidates`` (columns; ``rs`` where a candidate is ``base``'s own value), and the candidate chosen
    leave one walk out: ``(counts, chosen index per walk, held-out count error per walk, index fitted
    on all)``."""
    from dataclasses import replace

    import numpy as np

    from ..ins.evaluate import evaluate_gait_walk, leave_one_group_out

    cnt = np.zeros((len(walks), len(candidates)))
    for j, v in enumerate(candidates):
        for i, w in enumerate(walks):
            r = rs[i] if v == getattr(base, field) else evaluate_gait_walk(w, replace(base, **{field: v}))
            cnt[i, j] = abs(r.n_detected - r.n_walked)
    chosen, held = leave_one_group_out(cnt, [w.name for w in walks])
    return cnt, chosen, held, int(np.argmin(cnt.mean(axis=0)))


def _foot_hde(walks: list, rs: list, files: list, sim_loops: int, head: dict) -> None:
    """Heuristic drift elimination (ins/hde.py) on the gait-driven walks, its settings chosen leave one
    walk out and leave one session out; the setting chosen on all the gait walks scored on PyShoe (a
    set it never saw) and on simulated loops."""
    from dataclasses import replace

    import numpy as np

    from ..ins.evaluate import evaluate_gait_walk, pyshoe_armse_grid, simulated_loop_errors
    from ..ins.foot import FootInsConfig
    from ..ins.hde import HDE_CANDIDATES, describe

    cands = HDE_CANDIDATES
    base = FootInsConfig(detector="robust")
    res = [[evaluate_gait_walk(w, replace(base, hde=c)) for c in cands] for w in walks]
    fin = np.array([[r.final_pct for r in row] for row in res])  # (walks, candidates)
    intro = (
        "\nheuristic drift elimination (HDE/iHDE: a straight stride near a dominant direction of the building - learned from the walk's "
        "first straight stretch, modulo 90 deg - is measured as that direction through the filter's gated update; window 15 deg, sigma 3 deg), "
        "robust detector; candidates: " + "; ".join(f"{k}: {describe(c)}" for k, c in enumerate(cands))
    )
    bj = _gait_choice(walks, rs, fin, intro, "no HDE", "gait_hde", head)
    cfg = replace(base, detector="adaptive", hde=cands[bj])
    armse = pyshoe_armse_grid(files, [cfg])[:, 0]
    print(
        f"  PyShoe with the setting chosen on the gait walks (held out by set: never fitted on PyShoe; default detector): mean 2-D ARMSE "
        f"{armse.mean():.4f} m (median {np.median(armse):.4f}); without HDE see above"
    )
    head["armse_hde_mean_m"] = armse.mean()
    if sim_loops:
        sim = simulated_loop_errors(sim_loops, config=replace(cfg))
        print(
            f"  simulated closed loops ({sim_loops}) with it: return error median {np.median(sim):.2f} %, max {sim.max():.2f} % ({', '.join(f'{x:.2f}' for x in sim)})"
        )
        head["sim_hde_return_error_median_pct"] = np.median(sim)
        head["sim_hde_return_error_max_pct"] = sim.max()


def _gait_choice(walks: list, rs: list, fin, intro: str, none_label: str, key: str, head: dict) -> int:
    """A setting chosen on the gait-driven walks by their mean final-point error, leaving one walk out
    and one session out: ``intro``, then per walk its final-point error without it (``rs``), held out by
    walk and by session (with the candidate chosen) and fitted on all; then the return and final-point
    summaries of each, and the held-out figures as ``key``_... in ``head``. ``fin`` (walks, candidates)
    of final-point errors, %. Returns the candidate fitted on all the walks."""
    import numpy as np

    from ..ins.evaluate import leave_one_group_out

    sessions = [r.session for r in rs]
    ch_w, held_w = leave_one_group_out(fin, [w.name for w in walks])
    ch_s, held_s = leave_one_group_out(fin, sessions)
    bj = int(np.argmin(fin.mean(axis=0)))
    print(intro)
    closes = np.array([r.closes for r in rs])
    print("chosen on the other walks' mean final-point error (leave one walk out), and on the other sessions' (leave one session out)")
    print(f"{'walk':<22} {'session':>9} {none_label:>7} {'LOWO':>7} {'cand':>4} {'LOSO':>7} {'cand':>4} {'fitted':>7} {'closes':>6}")
    for i, r in enumerate(rs):
        print(
            f"{r.name:<22} {sessions[i]:>9} {r.final_pct:6.2f}% {held_w[i]:6.2f}% {ch_w[i]:4d} {held_s[i]:6.2f}% {ch_s[i]:4d} {fin[i, bj]:6.2f}% "
            f"{'yes' if r.closes else '':>6}"
        )
    before = np.array([r.final_pct for r in rs])
    for label, v in (
        (none_label, before),
        ("held out by walk", held_w),
        ("held out by session", held_s),
        (f"fitted on all (candidate {bj})", fin[:, bj]),
    ):
        print(
            f"  {label:<28} return ({int(closes.sum())} closing walks) median {np.median(v[closes]):.2f} %, max {v[closes].max():.2f} %; "
            f"final point (all {len(v)}) median {np.median(v):.2f} %, max {v.max():.2f} %"
        )
    head[f"{key}_return_error_held_out_median_pct"] = np.median(held_w[closes])
    head[f"{key}_return_error_held_out_max_pct"] = held_w[closes].max()
    head[f"{key}_return_error_session_held_out_median_pct"] = np.median(held_s[closes])
    head[f"{key}_return_error_fitted_median_pct"] = np.median(fin[closes, bj])
    head[f"{key}_final_error_held_out_median_pct"] = np.median(held_w)
    return bj


def _foot_zaru_up(walks: list, rs: list, files: list, sim_loops: int, head: dict) -> None:
    """The vertical ZARU (measurements.ZeroYawRate) on the gait-driven walks, its sigma (or none) chosen
    leave one walk out and leave one session out; the sigma chosen on all the gait walks scored on PyShoe
    (a set it never saw) and on simulated loops."""
    from dataclasses import replace

    import numpy as np

    from ..ins.evaluate import FOOT_ZARU_UP_SIGMAS, evaluate_gait_walk, pyshoe_armse_grid, simulated_loop_errors
    from ..ins.foot import FOOT_PRESETS, FootInsConfig
    from ..units import DEG

    # (sigma, vet the demoted runs' ZUPTs): the second is the robust detector's, so PyShoe (adaptive) sees the first only
    cands = [(c, vd) for vd in (False, True) for c in FOOT_ZARU_UP_SIGMAS]
    base = FootInsConfig(detector="robust")

    def final_pct(w, r, c, vd) -> float:
        return r.final_pct if (c, vd) == (None, False) else evaluate_gait_walk(w, replace(base, zaru_up_sigma=c, vet_demoted=vd)).final_pct

    fin = np.array([[final_pct(w, r, c, vd) for c, vd in cands] for w, r in zip(walks, rs)])

    def label(c, vd) -> str:
        return ("off" if c is None else f"sigma {c / DEG:g} deg/s") + (", demoted runs' ZUPTs gated" if vd else "")

    intro = (
        "\nvertical zero angular rate (at every stance sample with an accepted ZUPT, the gyro's reading about the body's up axis measured "
        "as its bias along it, gated: the rolling stance that trips the 3-D ZARU's gate has no vertical component), robust detector, with "
        "or without the chi-square gate on the ZUPTs of the stance runs not kept as a step's (mid-swing dips, fragments of a rolling "
        "stance); candidates: " + "; ".join(f"{k}: {label(*c)}" for k, c in enumerate(cands))
    )
    bj = _gait_choice(walks, rs, fin, intro, "off", "gait_zaru_up", head)
    preset = FOOT_PRESETS["gait-driven"]
    want = (preset["zaru_up_sigma"], preset["vet_demoted"])  # written as FOOT_ZARU_UP_SIGMAS writes its sigmas: equal floats
    print(
        f"  pdr foot --preset gait-driven ({label(*want)}): "
        + ("the candidate fitted on all" if want == cands[bj] else f"NOT the candidate fitted on all ({label(*cands[bj])}): the preset is stale")
    )
    closes = np.array([r.closes for r in rs])
    sigmas = [c for c, _ in cands]
    cfg = FootInsConfig(zaru_up_sigma=sigmas[bj])
    grid_s = pyshoe_armse_grid(files, [FootInsConfig(zaru_up_sigma=c) for c in FOOT_ZARU_UP_SIGMAS], workers=2)
    grid = grid_s[:, [FOOT_ZARU_UP_SIGMAS.index(c) for c in sigmas]]  # the adaptive detector has no demoted runs
    armse = grid[:, bj]
    print(
        f"  PyShoe with the setting chosen on the gait walks (held out by set: never fitted on PyShoe; default detector): mean 2-D ARMSE "
        f"{armse.mean():.4f} m (median {np.median(armse):.4f}); off see above"
    )
    pj = int(np.argmin(grid.mean(axis=0)))
    print(
        f"  cross-set, the other way: fitted on PyShoe (candidate {pj}; per-candidate mean ARMSE "
        + ", ".join(f"{k}: {v:.5f} m" for k, v in enumerate(grid.mean(axis=0)))
        + f") -> gait return ({int(closes.sum())} closing walks) median {np.median(fin[closes, pj]):.2f} %, max {fin[closes, pj].max():.2f} %; "
        f"final point median {np.median(fin[:, pj]):.2f} %"
    )
    head["armse_zaru_up_mean_m"] = armse.mean()
    head["gait_zaru_up_pyshoe_fitted_return_median_pct"] = np.median(fin[closes, pj])
    if sim_loops:
        sim = simulated_loop_errors(sim_loops, config=cfg)
        print(
            f"  simulated closed loops ({sim_loops}) with it: return error median {np.median(sim):.2f} %, max {sim.max():.2f} % ({', '.join(f'{x:.2f}' for x in sim)})"
        )
        head["sim_zaru_up_return_error_median_pct"] = np.median(sim)
        head["sim_zaru_up_return_error_max_pct"] = sim.max()


def _cmd_eval_fingerprint(args: argparse.Namespace) -> int:
    from ..radio.evaluate import run_fingerprint_eval

    res = run_fingerprint_eval(args.uji, args.ilc, args.folds, args.every, args.uji_validation)
    print_fingerprint(res)
    print_headline(fingerprint_headline(res))
    return 0


def _print_uji(results: dict, indent: str) -> None:
    """One row per method of :data:`~hybridloc.radio.evaluate.UJI_METHODS` and the ratio of their mean errors."""
    import numpy as np

    from ..radio.evaluate import UJI_METHODS, _fmt

    for name, label in UJI_METHODS:
        v = results[name]
        print(
            f"{indent}{label:<36} building hit {100 * v['building']:.2f}%  floor hit {100 * v['floor']:.2f}%  2-D error on the right floor: {_fmt(v['errors'])}"
        )
    print(f"{indent}ratio of mean error ours/plain: {np.nanmean(results['ours']['errors']) / np.nanmean(results['plain']['errors']):.2f}")


def print_fingerprint(res) -> None:
    """The report of ``eval fingerprint`` (:class:`hybridloc.radio.evaluate.FingerprintEval`)."""
    import numpy as np

    from ..radio.evaluate import PATHLOSS_FAR_REACH_M, UJI_COVERED_M, UJI_METHODS, _fmt

    if res.uji:
        val = res.uji_validation
        if res.uji_split is not None:
            v = res.uji_split
            print(f"UJIIndoorLoc standard split: references {res.uji}, queries {val} ({v['ours']['n']} scans)")
            _print_uji(v, "  ")
            print("  (goal: building 100 %, floor >= 95 %, mean <= 6 m; plain 3-NN about 9.1 m)")
        r = res.uji_cv
        print(
            f"UJIIndoorLoc {res.uji}: cross-validation grouped by user"
            + ("" if val is not None else " (no validationData.csv beside it: the standard split is not scored)")
        )
        for subset, title in (
            ("all", "all scans"),
            (
                "covered",
                f"scans inside the map ({100 * r['covered_share']:.0f} %: another user's reference within {UJI_COVERED_M:.0f} m on the floor; nearer the standard split)",
            ),
        ):
            print(f"  {title}:")
            _print_uji({name: r[name][subset] for name, _ in UJI_METHODS}, "    ")
        print("  (goal on the standard split: building 100 %, floor >= 95 %, mean <= 6 m; plain 3-NN about 9.1 m there)")
        ph = res.uji_phone
        if ph is not None:
            print(
                f"UJIIndoorLoc {res.uji}: cross-validation grouped by phone ({ph['n_phones']} phones in {ph['folds']} folds; settings chosen by leave-one-phone-out inside each fold)"
            )
            for i, (rep, v, fitted, held) in enumerate(ph["chosen"]):
                print(f"  fold {i}: chose {rep}, {v}: penalised {fitted:.2f} m fitted (inner CV), {held:.2f} m held out")
            for subset, mask in (("all scans", None), (f"scans inside the map ({100 * ph['covered'].mean():.0f} %)", ph["covered"])):
                print(f"  {subset}:")
                sm = {name: ph[name].summary(mask) for name in ("ours", "plain")}
                for name, label in (("ours", "building/floor/position kNN (CV-chosen)"), ("plain", "plain 3-NN, Euclidean, raw dBm")):
                    x = sm[name]
                    print(
                        f"    {label:<40} building hit {x['building_hit_pct']:.2f}%  floor hit {x['floor_hit_pct']:.2f}%  "
                        f"mean {x['mean_m']:.2f} m on the right floor  penalised {x['penalised_m']:.2f} m (n={x['n']})"
                    )
                print(
                    f"    ratio ours/plain: mean {sm['ours']['mean_m'] / sm['plain']['mean_m']:.2f}, penalised {sm['ours']['penalised_m'] / sm['plain']['penalised_m']:.2f}"
                )
    if res.uji_phone_split is not None:
        _print_uji_split_votes(res)
    if res.ilc:
        print(f"Indoor Location Competition {res.ilc}: {res.n_ilc_traces} traces as surveys, {res.folds}-fold leave-traces-out, WiFi only, per scan")
        for m in res.ilc_methods:
            s = m.score
            e = np.array(s.errors)
            print(
                f"  {m.label:<22} floor hit {100 * np.mean(s.floor_hits):.2f}%  error on the right floor: {_fmt(e)}; "
                f"95% region holds the truth {100 * np.mean(s.region_hits):.1f}% (mean area {np.mean(s.region_areas):.0f} m^2); no fix {s.no_fix}"
            )
        ro = res.routes
        s = ro.score
        e = np.array(s.errors)
        rep, rest = ro.repeated_errors, ro.other_errors
        print(
            f"  routes held out whole ({ro.n_repeated} of {res.n_ilc_traces} walks follow a route walked more than once, with the same marks; "
            f"in the folds above {ro.n_seen} of them have a repeat in the map), weighted 5-NN: floor hit {100 * np.mean(s.floor_hits):.2f}%  "
            f"error on the right floor: {_fmt(e)}; on the repeated routes' walks {np.nanmean(rep) if rep.size else float('nan'):.2f} m, "
            f"on the others {np.nanmean(rest) if rest.size else float('nan'):.2f} m; 95% region holds the truth {100 * np.mean(s.region_hits):.1f}% "
            f"(mean area {np.mean(s.region_areas):.0f} m^2)"
        )
        cov = np.array(s.cover_m)
        parts = []
        for lo, hi in _COVER_BINS:
            m = (cov >= lo) & (cov < hi)
            parts.append(f"{lo:g}-{hi:g} m: {100 * m.mean():.0f} % of scans, mean {_finite_mean(e[m]):.2f} m")
        print("  routes held out whole, error by the distance from the truth to the nearest reference label on its floor: " + "; ".join(parts))
        for sc, label in ((ro.pathloss, "at the kernel's reach"), (ro.pathloss_far, f"carried {PATHLOSS_FAR_REACH_M:g} m past the labels")):
            if sc is None:
                continue
            ep, cp = np.array(sc.errors), np.array(sc.cover_m)
            by = [f"{lo:g}-{hi:g} m: {_finite_mean(ep[(cp >= lo) & (cp < hi)]):.2f} m" for lo, hi in _COVER_BINS]
            print(
                f"  routes held out whole, cell likelihood on maps with the path-loss prior {label}: floor hit {100 * np.mean(sc.floor_hits):.2f}%  "
                f"error on the right floor: {_fmt(ep)}; by distance to the nearest label: " + "; ".join(by)
            )
        lo = res.routes_left_out
        if lo is not None:
            _print_routes_left_out(lo)
        print("  (goal: mean <= 5 m, floor >= 97 %, region hit >= 90 %; routes held out: mean <= 6 m)")


def _print_routes_left_out(lo) -> None:
    """The leave-one-route-out lines of ``eval fingerprint`` (:class:`~hybridloc.radio.evaluate.RoutesLeftOut`)."""
    import numpy as np

    from ..radio.evaluate import _fmt

    def setting(s) -> str:
        return f"k {s[0]}, readings <= {s[1]:g} s old"

    h, p = lo.held_out, lo.plain
    eh, ep = np.array(h.errors), np.array(p.errors)
    best = min(lo.fitted_mean_m, key=lambda s: lo.fitted_mean_m[s])
    print(
        f"  leave one route out ({lo.n_routes} routes, each located with every other walk in the map: no repeat of the route, all the rest of the site), "
        f"weighted kNN with its setting chosen per floor on the other floors ("
        + "; ".join(f"{fl}: {setting(s)}" for fl, s in lo.chosen.items())
        + "): "
        f"floor hit {100 * np.mean(h.floor_hits):.2f}%  error on the right floor: {_fmt(eh)}; no fix {h.no_fix}"
    )
    print(
        "    per floor, held out (plain): "
        + "; ".join(f"{fl} {a:.2f} m ({b:.2f})" for fl, (a, b) in lo.floor_mean_m.items())
        + f"; fitted on all floors ({setting(best)}): {lo.fitted_mean_m[best]:.2f} m, the held-out choice costs {_finite_mean(eh) - lo.fitted_mean_m[best]:+.2f} m"
    )
    print(
        f"    plain 3-NN, Euclidean, raw dBm, the same scans: floor hit {100 * np.mean(p.floor_hits):.2f}%  error on the right floor: {_fmt(ep)}; "
        f"ratio ours/plain {_finite_mean(eh) / _finite_mean(ep):.2f}"
    )
    cov = np.array(h.cover_m)
    parts = [
        f"{a:g}-{b:g} m: {100 * ((cov >= a) & (cov < b)).mean():.0f} % of scans, mean {_finite_mean(eh[(cov >= a) & (cov < b)]):.2f} m"
        for a, b in _COVER_BINS
    ]
    print("    by the distance from the truth to the nearest reference label on its floor: " + "; ".join(parts))


def _finite_mean(x) -> float:
    """Mean of the finite values of ``x`` (errors are NaN on a wrong floor); NaN when there are none."""
    import numpy as np

    x = np.asarray(x, float)
    return float(np.nanmean(x)) if np.isfinite(x).any() else float("nan")


#: The distance bins, m, from a routes-held-out scan's truth to the nearest label on its floor
_COVER_BINS = ((0, 2), (2, 5), (5, 10), (10, float("inf")))


def _split_label(c) -> str:
    """A :class:`~hybridloc.radio.hierarchy.SplitChoice` in one phrase."""
    f, p = c.floor, c.position
    return (
        f"floor by {f.rep.label()} (k_building {f.k_building}, k_floor {f.k_floor}, weight d^-{f.weight_power:g}), "
        f"position by {p.rep.label()} (k {p.k} on the floor, weight d^-{p.weight_power:g})"
    )


def _print_uji_split_votes(res) -> None:
    """The building/floor vote and the position vote chosen apart (evaluate_uji_phone_split), beside
    the joint vote and the plain 3-NN on the same folds."""
    sp, ph = res.uji_phone_split, res.uji_phone
    print(
        f"UJIIndoorLoc {res.uji}: floor vote and position vote chosen apart (each its own representation; position from the "
        "neighbours on the chosen floor), settings chosen by leave-one-phone-out inside each split, held out by phone"
    )
    for name, title in (
        ("kfold", f"the same {sp['folds']} phone folds as above"),
        ("lopo", f"leave one phone out ({sp['n_phones']} splits: every other phone's references in the map)"),
    ):
        r = sp[name]
        print(f"  {title}:")
        for out_ph, c, held in r["chosen"]:
            print(
                f"    phones {','.join(str(p) for p in out_ph)} out: {_split_label(c)}: penalised {c.fitted:.2f} m fitted (inner CV), {held:.2f} m held out"
            )
        plain = ph["plain"] if name == "kfold" and ph is not None else r.get("plain")
        joint = ph["ours"] if name == "kfold" and ph is not None else None
        for subset, mask in (("all scans", None), (f"scans inside the map ({100 * r['covered'].mean():.0f} %)", r["covered"])):
            print(f"    {subset}:")
            rows = [("split", "floor vote + position vote (CV-chosen)", r["ours"])]
            if joint is not None:
                rows.append(("joint", "building/floor/position kNN (CV-chosen)", joint))
            if plain is not None:
                rows.append(("plain", "plain 3-NN, Euclidean, raw dBm", plain))
            sm = {key: sc.summary(mask) for key, _, sc in rows}
            for key, label, _ in rows:
                x = sm[key]
                print(
                    f"      {label:<40} building hit {x['building_hit_pct']:.2f}%  floor hit {x['floor_hit_pct']:.2f}%  "
                    f"mean {x['mean_m']:.2f} m on the right floor  penalised {x['penalised_m']:.2f} m (n={x['n']})"
                )
            if "plain" in sm:
                print(
                    f"      ratio split/plain: mean {sm['split']['mean_m'] / sm['plain']['mean_m']:.2f}, penalised {sm['split']['penalised_m'] / sm['plain']['penalised_m']:.2f}"
                )
    print(f"  chosen over the whole file (leave one phone out, {sp['full'].fitted:.2f} m penalised): {_split_label(sp['full'])}")
    if res.uji_split_votes is not None:
        x = res.uji_split_votes["scores"].summary()
        print(
            f"  standard split ({res.uji_validation}, {res.uji_split_votes['n']} scans) with that choice: building hit {x['building_hit_pct']:.2f}%  "
            f"floor hit {x['floor_hit_pct']:.2f}%  mean {x['mean_m']:.2f} m on the right floor  penalised {x['penalised_m']:.2f} m"
        )
    print("  (goal on the validation file: building 100 %, floor >= 96 %, mean <= 6 m)")


def fingerprint_headline(res) -> dict:
    import numpy as np

    from ..radio.evaluate import PATHLOSS_FAR_REACH_M

    out: dict = {}
    if res.uji_split is not None:
        v = res.uji_split["ours"]
        out.update(uji_split_mean_m=np.nanmean(v["errors"]), uji_split_floor_hit_pct=100 * v["floor"], uji_split_building_hit_pct=100 * v["building"])
    if res.uji_cv is not None:
        v = res.uji_cv["ours"]["all"]
        out.update(uji_cv_mean_m=np.nanmean(v["errors"]), uji_cv_floor_hit_pct=100 * v["floor"])
    if res.uji_phone is not None:
        out.update(_score_keys("uji_phone_cv", res.uji_phone["ours"].summary()))
        out["uji_phone_cv_plain_mean_m"] = res.uji_phone["plain"].summary()["mean_m"]
    for m, key in zip(res.ilc_methods, ("ilc_knn", "ilc_prob", "ilc_prob_pathloss")):
        s = m.score
        out[f"{key}_mean_m"] = np.nanmean(s.errors) if s.errors else float("nan")
        out[f"{key}_floor_hit_pct"] = 100 * np.mean(s.floor_hits)
        out[f"{key}_region_hit_pct"] = 100 * np.mean(s.region_hits)
    if res.routes is not None:
        s = res.routes.score
        out["ilc_routes_held_out_mean_m"] = np.nanmean(s.errors) if s.errors else float("nan")
        cov, e = np.array(s.cover_m), np.array(s.errors)
        near = cov < 2.0
        out["ilc_routes_held_out_near_share_pct"] = 100 * float(near.mean()) if near.size else float("nan")
        out["ilc_routes_held_out_near_mean_m"] = _finite_mean(e[near])
        out["ilc_routes_held_out_far_mean_m"] = _finite_mean(e[cov >= 5.0])
        for sc, key in (
            (res.routes.pathloss, "ilc_routes_held_out_pathloss"),
            (res.routes.pathloss_far, f"ilc_routes_held_out_pathloss_reach{PATHLOSS_FAR_REACH_M:g}"),
        ):
            if sc is None:
                continue
            ep, cp = np.array(sc.errors), np.array(sc.cover_m)
            out[f"{key}_mean_m"] = np.nanmean(ep) if ep.size else float("nan")
            out[f"{key}_floor_hit_pct"] = 100 * float(np.mean(sc.floor_hits))
            out[f"{key}_far_mean_m"] = _finite_mean(ep[cp >= 5.0])
    lo = res.routes_left_out
    if lo is not None:
        eh, ep = np.array(lo.held_out.errors), np.array(lo.plain.errors)
        out["ilc_loro_mean_m"] = _finite_mean(eh)
        out["ilc_loro_floor_hit_pct"] = 100 * float(np.mean(lo.held_out.floor_hits))
        out["ilc_loro_fitted_mean_m"] = min(lo.fitted_mean_m.values())
        out["ilc_loro_plain_mean_m"] = _finite_mean(ep)
        out["ilc_loro_plain_floor_hit_pct"] = 100 * float(np.mean(lo.plain.floor_hits))
        out["ilc_loro_ratio_plain"] = out["ilc_loro_mean_m"] / out["ilc_loro_plain_mean_m"]
    sp = res.uji_phone_split
    if sp is not None:
        for name, key in (("kfold", "uji_phone_cv_split"), ("lopo", "uji_lopo_split")):
            xc = sp[name]["ours"].summary(sp[name]["covered"])
            out.update(_score_keys(key, sp[name]["ours"].summary()))
            out.update(
                {
                    f"{key}_covered_mean_m": xc["mean_m"],
                    f"{key}_covered_floor_hit_pct": xc["floor_hit_pct"],
                    f"{key}_covered_penalised_m": xc["penalised_m"],
                }
            )
        out["uji_lopo_plain_mean_m"] = sp["lopo"]["plain"].summary()["mean_m"]
        out["uji_lopo_plain_penalised_m"] = sp["lopo"]["plain"].summary()["penalised_m"]
    if res.uji_split_votes is not None:
        out.update(_score_keys("uji_split_votes", res.uji_split_votes["scores"].summary()))
    return out


def _score_keys(prefix: str, x: dict) -> dict:
    """The headline keys of a building/floor/position score (:meth:`hybridloc.radio.hierarchy.Scores.summary`),
    in this order: ``<prefix>_mean_m``, ``_building_hit_pct``, ``_floor_hit_pct``, ``_penalised_m``."""
    return {f"{prefix}_{k}": x[k] for k in ("mean_m", "building_hit_pct", "floor_hit_pct", "penalised_m")}


def _cmd_eval_sim_realism(args: argparse.Namespace) -> int:
    from ..sim.evaluate import run_sim_realism

    res = run_sim_realism(args.ilc, args.walkers, args.minutes, args.every, args.seed)
    print_sim_realism(res)
    print_headline(sim_realism_headline(res))
    return 0


def print_sim_realism(res) -> None:
    """The table of ``eval sim-realism`` (:class:`hybridloc.sim.evaluate.SimRealism`)."""
    import numpy as np

    from ..sim.evaluate import poisson_rate
    from ..sim.realism import DIST_BINS, in_range

    print(f"simulated: {res.walkers} walkers x {res.minutes:g} min in a generated 3-floor building (seed {res.seed})")
    if res.have_real:
        print(f"real: {res.n_real_traces} Indoor Location Competition traces of {res.ilc}")

    def row(name, sim_v, real_v=None, unit=""):
        if real_v is None or len(real_v) == 0:
            print(f"  {name:<44} sim {sim_v:8.2f}{unit}")
            return
        lo, hi = np.percentile(real_v, [10, 90])
        ok = "inside" if in_range(sim_v, real_v) else "OUTSIDE"
        print(f"  {name:<44} sim {sim_v:8.2f}{unit}   real p10-p90 {lo:7.2f}..{hi:7.2f}{unit}   {ok}")

    print("statistic (simulated median vs the real distribution)")
    for st in res.stats:
        row(st.name, st.sim, st.real, st.unit)
    print("  fingerprint cosine similarity by distance bin (m): " + "  ".join(f"{a:g}-{b:g}" for a, b in zip(DIST_BINS[:-1], DIST_BINS[1:])))
    print("    sim  " + "  ".join(f"{v:6.3f}" for v in res.sim_similarity))
    if res.have_real:
        print("    real " + "  ".join(f"{v:6.3f}" for v in res.real_similarity))
        print(
            f"    rms difference sim - real {_similarity_rms(res):.3f} (the radio model's n, shadowing and noise are set on it; "
            "the real scans carry survey-label error, the simulated ones their true positions)"
        )
    r, plain = res.pdr, res.plain

    def rate(k: int, minutes: float) -> str:
        per_min, lo, hi = poisson_rate(k, minutes)
        return f"{per_min:.2f}/min (95 % interval {lo:.2f}-{hi:.2f}; {minutes:.1f} min)"

    print(
        f"phone PDR on the simulated walks (consumer IMU, phone in hand): {r['n_detected']} steps detected for {r['n_true']} true "
        f"(count error {100 * r['count_error']:+.2f}%; goal within 1 %); false steps standing {rate(r['false_standing'], r['standing_min'])}, "
        f"handling {rate(r['false_handling'], r['handling_min'])}; goal <= 1/min"
    )
    h, hp = np.degrees(r["heading_errors"]), np.degrees(plain["heading_errors"])
    print(
        f"heading on the simulated walks (relative to the first step, straight walking, {res.minutes:g} min walks with raw consumer gyros "
        f"and indoor magnetic disturbances): median {np.median(h):.1f} deg, p90 {np.percentile(h, 90):.1f}; plain gyro integration "
        f"{np.median(hp):.1f} / {np.percentile(hp, 90):.1f} deg (ratio of medians ours/plain {np.median(h) / np.median(hp):.2f})"
    )
    _print_lengths(res)


def _print_lengths(res) -> None:
    """The step-length models on simulated and real waypoint segments (``SimRealism.lengths_*``)."""
    sim, marked, real = res.lengths_sim, res.lengths_sim_marked, res.lengths_real
    if sim is None:
        return
    print(
        "step-length models on waypoint segments >= 3 m (median relative length error; 'one K': the library's uncalibrated constant, "
        "'fit': one constant fitted on all the scored walks; sim level segments only)"
    )
    print(
        f"  {'model':<10} {'sim one K':>10} {'sim fit':>8} {'sim, vague marks':>17} {'fit':>6}" + (f" {'real one K':>11} {'fit':>6}" if real else "")
    )
    for name, row in sim.items():
        line = f"  {name:<10} {row['default_pct']:9.1f}% {row['fit_pct']:7.1f}% {marked[name]['default_pct']:16.1f}% {marked[name]['fit_pct']:5.1f}%"
        if real:
            line += f" {real[name]['default_pct']:10.1f}% {real[name]['fit_pct']:5.1f}%"
        print(line)
    from ..pdr.steplength import WeinbergLength

    w = sim["weinberg"]
    print(
        f"  Weinberg, one uncalibrated K = {WeinbergLength().coef[0]:.2f}: simulated {marked['weinberg']['default_pct']:.1f}% with marks as vague as the real "
        f"ones (+-{res.mark_sigma:.2f} m per axis; {w['default_pct']:.1f}% with the exact marks)"
        + (f", real {real['weinberg']['default_pct']:.1f}% ({real['weinberg']['segments']} segments)" if real else "")
        + f"; the proportional part (the step model's scale) {w['scale_pct']:.1f}%"
        + (f" vs real {real['weinberg']['scale_pct']:.1f}%" if real else "")
    )


def _similarity_rms(res) -> float:
    import numpy as np

    diff = np.array(res.sim_similarity) - np.array(res.real_similarity)
    return float(np.sqrt(np.nanmean(diff**2)))


def sim_realism_headline(res) -> dict:
    import numpy as np

    r = res.pdr
    h = np.degrees(r["heading_errors"])
    out = {
        "step_count_error_pct": 100 * r["count_error"],
        "false_steps_standing_per_min": r["false_per_min_standing"],
        "false_steps_handling_per_min": r["false_per_min_handling"],
        "heading_error_median_deg": float(np.median(h)),
    }
    if res.have_real:
        out["similarity_rms_diff"] = _similarity_rms(res)
    if res.lengths_sim is not None:
        out["weinberg_segment_error_sim_pct"] = res.lengths_sim_marked["weinberg"]["default_pct"]
        out["weinberg_segment_error_sim_exact_marks_pct"] = res.lengths_sim["weinberg"]["default_pct"]
        out["weinberg_segment_error_sim_fit_pct"] = res.lengths_sim_marked["weinberg"]["fit_pct"]
        out["weinberg_scale_sim_pct"] = res.lengths_sim["weinberg"]["scale_pct"]
        out["mark_sigma_m"] = res.mark_sigma
    if res.lengths_real is not None:
        out["weinberg_segment_error_real_pct"] = res.lengths_real["weinberg"]["default_pct"]
        out["weinberg_segment_error_real_fit_pct"] = res.lengths_real["weinberg"]["fit_pct"]
        out["weinberg_scale_real_pct"] = res.lengths_real["weinberg"]["scale_pct"]
    return out


def _cmd_eval_fusion(args: argparse.Namespace) -> int:
    from ..demo import run_fusion_eval

    eps = tuple(float(e) for e in args.kld_epsilons.split(",") if e.strip())
    if not eps or not all(0.0 < e < 1.0 for e in eps):
        raise SystemExit("hybridloc eval fusion: --kld-epsilons takes numbers between 0 and 1, e.g. 0.05,0.15,0.4")
    print_headline(run_fusion_eval(args.dir, Path(args.out), args.replay_every, args.every, kld_epsilons=eps))
    return 0


def _cmd_eval_slam(args: argparse.Namespace) -> int:
    from ..slam.evaluate import run_slam_eval

    print_headline(run_slam_eval(args.dir, args.survey_fraction, args.seed, args.data_fraction, workers=args.workers))
    return 0


def _cmd_eval_crowd(args: argparse.Namespace) -> int:
    from ..crowd_eval import run_crowd_eval
    from ..errors import BadInput

    floors = None
    if args.floors is not None:
        floors = [f.strip() for f in args.floors.split(",") if f.strip()]
        if not floors:
            raise BadInput(f"--floors expects floor names separated by commas (e.g. F1,F2), got {args.floors!r}")
    print_headline(
        run_crowd_eval(
            args.dir,
            args.survey_fraction,
            args.seed,
            floors,
            out=Path(args.out),
            concurrency=args.concurrency,
            speed=args.speed,
            wait_timeout=args.wait_timeout,
            slam=not args.no_slam,
            grow_map=args.grow_map,
        )
    )
    return 0


def register(sub) -> None:
    ev = sub.add_parser("eval", help="evaluation commands that print figures")
    esub = ev.add_subparsers(dest="eval_command", required=True)
    ep = esub.add_parser("pdr-phone", help="phone PDR against waypoints of Indoor Location Competition traces")
    ep.add_argument("dir", help="a site or floor folder, e.g. ../shared/data/msft-ilc/site1")
    ep.add_argument("--model", choices=LENGTH_MODELS, default="height")
    ep.add_argument("--detector", choices=("peak", "autocorr"), default="peak")
    ep.add_argument("--every", type=int, default=1, help="use every N-th trace (default all)")
    ep.add_argument(
        "--k-mags",
        default="0,0.01,0.03,0.1",  # hybridloc.pdr.evaluate.K_MAG_CANDIDATES
        help="candidates for the magnetometer's yaw pull, chosen leave one floor out ('' skips the held-out-by-floor part; default %(default)s)",
    )
    ep.set_defaults(func=_cmd_eval_pdr_phone)

    ef = esub.add_parser("pdr-foot", help="foot INS against PyShoe VICON ground truth (ARMSE, return-to-start)")
    ef.add_argument("dir", help="folder of PyShoe .mat trials, e.g. ../shared/data/pyshoe-vicon")
    ef.add_argument(
        "--gait",
        metavar="DIR",
        help=f"gait-driven walks (SensorConnect CSV + footprint .mat) scored stride by stride (default {_GAIT_DEFAULT} when present; '' skips)",
    )
    ef.add_argument("--sim-loops", type=int, default=6, metavar="N", help="simulated closed-loop walks to score (0 skips; default %(default)s)")
    ef.add_argument(
        "--decades",
        default="0.3,0.4,0.5,0.6,0.7",
        help="candidates for the adaptive detector's threshold, chosen leave one recording day out and across the sets ('' skips; default %(default)s)",
    )
    ef.set_defaults(func=_cmd_eval_pdr_foot)

    efp = esub.add_parser("fingerprint", help="fingerprint positioning on UJIIndoorLoc and Indoor Location Competition data")
    efp.add_argument("--uji", default="../shared/data/ujiindoorloc/trainingData.csv.gz", help="UJIIndoorLoc CSV ('' to skip)")
    efp.add_argument(
        "--uji-validation",
        metavar="CSV",
        help="UJIIndoorLoc validation file for the standard split (default: validationData.csv beside --uji when present; '' to skip)",
    )
    efp.add_argument("--ilc", default="../shared/data/msft-ilc/site1", help="Indoor Location Competition site folder ('' to skip)")
    efp.add_argument("--folds", type=int, default=4, help="trace folds for the ILC leave-traces-out test")
    efp.add_argument("--every", type=int, default=1, help="use every N-th ILC trace")
    efp.set_defaults(func=_cmd_eval_fingerprint)

    esr = esub.add_parser("sim-realism", help="simulated statistics beside real ones; phone PDR step counts on simulated walks")
    esr.add_argument("--ilc", default="../shared/data/msft-ilc/site1", help="real Indoor Location Competition site folder ('' to skip)")
    esr.add_argument(
        "--walkers", type=int, default=60, help="simulated walkers (default 60: ~11 min of phone handling, for a steady false-step rate)"
    )
    esr.add_argument("--minutes", type=float, default=5.0)
    esr.add_argument("--every", type=int, default=3, help="use every N-th real trace")
    esr.add_argument("--seed", type=int, default=1, help="simulated building and walkers (1 is the default; others are fresh samples)")
    esr.set_defaults(func=_cmd_eval_sim_realism)

    efu = esub.add_parser("fusion", help="PDR only, WiFi only and fused at waypoints, through the real client and server path")
    efu.add_argument("dir", help="Indoor Location Competition site folder, e.g. ../shared/data/msft-ilc/site1")
    efu.add_argument("--out", default="out/eval-fusion")
    efu.add_argument("--replay-every", type=int, default=4, help="every N-th trace is a phone client, the rest are surveys (default 4)")
    efu.add_argument("--every", type=int, default=1, help="use every N-th trace of the site")
    efu.add_argument(
        "--kld-epsilons",
        default="0.05,0.15,0.4",  # hybridloc.demo.KLD_EPSILONS (the CLI imports no numerics up front)
        help="candidates for Fox's epsilon of the cold-start particle filter, chosen leave one floor out (default %(default)s)",
    )
    efu.set_defaults(func=_cmd_eval_fusion)

    esl = esub.add_parser("slam", help="crowd SLAM: corrected crowd walks, loops, and test clients with survey-only, crowd and all-marks maps")
    esl.add_argument("dir", help="Indoor Location Competition site folder, e.g. ../shared/data/msft-ilc/site1")
    esl.add_argument("--survey-fraction", type=float, default=0.1, help="share F of the crowd walks that keep their survey marks (default 0.1)")
    esl.add_argument("--seed", type=int, default=0, help="seed of the survey and data-fraction draws")
    esl.add_argument("--data-fraction", type=float, default=1.0, help="share P of the unmarked crowd walks used (the data-amount curve)")
    esl.add_argument("--workers", type=int, default=2, help="processes reading the walks")
    esl.set_defaults(func=_cmd_eval_slam)

    ecr = esub.add_parser(
        "crowd",
        help="the site replayed as a crowd through a real server: surveys first, then every other walk as a phone client in time order; "
        "live (causal) and corrected errors, the learning curve",
    )
    ecr.add_argument("dir", help="Indoor Location Competition site folder, e.g. ../shared/data/msft-ilc/site1")
    ecr.add_argument(
        "--survey-fraction", type=float, default=0.1, help="share F of the walks replayed first as surveys with their marks (default 0.1)"
    )
    ecr.add_argument("--seed", type=int, default=0, help="seed of the survey draw (default 0)")
    ecr.add_argument("--floors", metavar="F1,F2", help="floors to evaluate (default all of the site)")
    ecr.add_argument(
        "--out",
        default="out/eval-crowd",
        help="folder of the server database, the clients' spools and clients.jsonl (per client and waypoint: live and corrected errors)",
    )
    ecr.add_argument("--concurrency", type=int, default=3, help="clients replayed at a time, in time order (default 3)")
    ecr.add_argument("--speed", type=float, default=0.0, help="replay speed K x real time; 0 (default) as fast as the lock-step allows")
    ecr.add_argument(
        "--wait-timeout", type=float, default=600.0, help="longest wait, s, for the server's SLAM to catch up (each time; reported when reached)"
    )
    ecr.add_argument(
        "--no-slam",
        action="store_true",
        help="the control: the server without its crowd SLAM, the survey map alone (what the learning curve is without any learning)",
    )
    ecr.add_argument(
        "--grow-map",
        action="store_true",
        help="the server's map grows at every added walk (serve --slam-grow-map): each walk's labels served on top of the map version until the next batch",
    )
    ecr.set_defaults(func=_cmd_eval_crowd)

"""``hybridloc eval sim-realism``: simulated statistics beside real ones, and the phone PDR on simulated
walks with true steps (step-count error, false steps while standing or handling the phone)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..pdr.attitude import AttitudeConfig
from ..pdr.phone import PhonePdrConfig, run_phone_pdr
from ..radio.survey import LabelledScan
from ..units import wrap_angle
from .building import generate_world
from .imu import disturbance_field, phone_imu
from .radio import make_radio_model, simulate_radio
from .realism import DIST_BINS, in_range, rssi_slopes, similarity_by_distance, spectrum_peaks
from .walker import simulate_walk


def simulated_sample(walkers: int, minutes: float, seed: int = 1):
    world = generate_world(np.random.default_rng(seed), 3, seed)
    model = make_radio_model(world, np.random.default_rng([seed, 7]))
    field = disturbance_field(np.random.default_rng([seed, 11]))
    root = np.random.default_rng([seed, 13])
    labelled, walks, imus = [], [], []
    for i in range(walkers):
        rng = np.random.default_rng(root.integers(2**63))
        walk = simulate_walk(world, rng, minutes, walker=i)
        imu = phone_imu(walk, rng, mag_field=field)
        radio = simulate_radio(model, walk, rng)
        for s in radio.wifi:
            pos, fl = walk.position_at(np.array([s.t]))
            labelled.append(LabelledScan(s, pos[0], 0.0, world.floor_name(int(fl[0]))))
        walks.append(walk)
        imus.append(imu)
    ap_pos = {k: p[:2] for k, p in zip(world.ap_ids, world.aps)}
    return world, labelled, walks, imus, ap_pos


def walking_mask(walk, t: np.ndarray) -> np.ndarray:
    ts = np.array([s.t for s in walk.steps])
    if ts.size < 2:
        return np.zeros(len(t), bool)
    k = np.searchsorted(ts, t)
    prev = ts[np.clip(k - 1, 0, len(ts) - 1)]
    nxt = ts[np.clip(k, 0, len(ts) - 1)]
    return (nxt - prev < 1.2) & (nxt >= t) & (prev <= t)


def heading_errors(walk, steps) -> np.ndarray:
    """|heading error| (rad) of detected steps against the true step nearest in time, both taken
    relative to their first step; only where the walker goes straight (the true step and its two
    neighbours share a heading within 1 deg), so a turn's timing does not count as heading error."""
    if len(steps) < 2 or len(walk.steps) < 3:
        return np.zeros(0)
    tt = np.array([s.t for s in walk.steps])
    th = np.array([s.heading for s in walk.steps])
    td = np.array([s.t for s in steps])
    hd = np.array([s.heading for s in steps])
    k = np.clip(np.searchsorted(tt, td), 1, len(tt) - 2)
    k = np.where(np.abs(tt[k - 1] - td) < np.abs(tt[k] - td), k - 1, k).clip(1, len(tt) - 2)
    steady = (np.abs(wrap_angle(th[k] - th[k - 1])) < math.radians(1.0)) & (np.abs(wrap_angle(th[k + 1] - th[k])) < math.radians(1.0))
    err = np.abs(wrap_angle((hd - hd[0]) - (th[k] - th[k[0]])))
    return err[steady]


def pdr_on_sim(walks, imus, attitude: AttitudeConfig | None = None) -> dict:
    """Step-count error while walking, false steps per minute standing or handling, and the heading's
    error along the walk (``attitude``: the heading filter's settings, default ours)."""
    n_true = n_det = 0
    false_steps, still_min, handling_steps, handling_min = 0, 0.0, 0, 0.0
    herr = []
    cfg = PhonePdrConfig(attitude=attitude) if attitude is not None else None
    for walk, imu in zip(walks, imus):
        steps, _ = run_phone_pdr(imu, config=cfg)
        herr.append(heading_errors(walk, steps))
        td = np.array([s.t for s in steps])
        n_true += len(walk.steps)
        n_det += len(steps)
        for a, b, handling in walk.pauses:
            a2, b2 = a + 1.5, b - 0.5  # margins: the last step of a walk lands at a, the next leaves at b
            if b2 <= a2:
                continue
            k = int(((td > a2) & (td < b2)).sum())
            if handling:
                handling_steps += k
                handling_min += (b2 - a2) / 60
            else:
                false_steps += k
                still_min += (b2 - a2) / 60
    return {"n_true": n_true, "n_detected": n_det, "count_error": (n_det - n_true) / max(n_true, 1),
            "false_per_min_standing": false_steps / max(still_min, 1e-9), "false_per_min_handling": handling_steps / max(handling_min, 1e-9),
            "standing_min": still_min, "handling_min": handling_min, "false_standing": false_steps, "false_handling": handling_steps,
            "heading_errors": np.concatenate(herr) if herr else np.zeros(0)}


def run_sim_realism(ilc: str, walkers: int, minutes: float, every: int, seed: int = 1) -> int:
    rng = np.random.default_rng(0)
    world, sim_lab, walks, imus, ap_pos = simulated_sample(walkers, minutes, seed)
    sim_slopes_crowd = rssi_slopes(sim_lab)
    sim_slopes_true = rssi_slopes(sim_lab, ap_pos)
    sim_sim = similarity_by_distance(sim_lab, rng)
    sim_freq = np.array([1.0 / np.median(np.diff([s.t for s in w.steps])) for w in walks if len(w.steps) > 5])
    sim_peaks = np.concatenate([spectrum_peaks(imu, walking_mask(w, imu.t)) for w, imu in zip(walks, imus)])
    print(f"simulated: {walkers} walkers x {minutes:g} min in a generated 3-floor building (seed {seed})")
    have_real = bool(ilc) and Path(ilc).is_dir()
    if have_real:
        from ..radio.evaluate import load_site_surveys
        from ..io.msft import find_ilc_traces, read_ilc_trace

        traces = load_site_surveys(ilc, every)
        real_lab = [ls for t in traces for ls in t.labelled]
        real_slopes = rssi_slopes(real_lab)
        real_sim = similarity_by_distance(real_lab, rng)
        freqs, peaks = [], []
        for p in find_ilc_traces(ilc)[::every]:
            tr = read_ilc_trace(p)
            if tr.imu is None:
                continue
            steps, _ = run_phone_pdr(tr.imu)
            dt = np.diff([s.t for s in steps])
            dt = dt[dt < 1.2]
            if dt.size > 5:
                freqs.append(1.0 / np.median(dt))
            peaks += spectrum_peaks(tr.imu)
        real_freq, real_peaks = np.array(freqs), np.array(peaks)
        print(f"real: {len(traces)} Indoor Location Competition traces of {ilc}")

    def row(name, sim_v, real_v=None, unit=""):
        if real_v is None or len(real_v) == 0:
            print(f"  {name:<44} sim {sim_v:8.2f}{unit}")
            return
        lo, hi = np.percentile(real_v, [10, 90])
        ok = "inside" if in_range(sim_v, real_v) else "OUTSIDE"
        print(f"  {name:<44} sim {sim_v:8.2f}{unit}   real p10-p90 {lo:7.2f}..{hi:7.2f}{unit}   {ok}")

    print("statistic (simulated median vs the real distribution)")
    row("RSSI slope vs log10 distance (crowd AP est.)", float(np.median(sim_slopes_crowd)), real_slopes if have_real else None, " dB/dec")
    row("RSSI slope vs log10 distance (true AP pos.)", float(np.median(sim_slopes_true)), None, " dB/dec")
    row("step frequency while walking", float(np.median(sim_freq)), real_freq if have_real else None, " Hz")
    row("|a| spectrum peak while walking", float(np.median(sim_peaks)), real_peaks if have_real else None, " Hz")
    print("  fingerprint cosine similarity by distance bin (m): " + "  ".join(f"{a:g}-{b:g}" for a, b in zip(DIST_BINS[:-1], DIST_BINS[1:])))
    print("    sim  " + "  ".join(f"{v:6.3f}" for v in sim_sim))
    if have_real:
        print("    real " + "  ".join(f"{v:6.3f}" for v in real_sim))
        diff = np.array(sim_sim) - np.array(real_sim)
        print(f"    rms difference sim - real {float(np.sqrt(np.nanmean(diff**2))):.3f} (the radio model's n, shadowing and noise are set on it; "
              "the real scans carry survey-label error, the simulated ones their true positions)")
    r = pdr_on_sim(walks, imus)

    def rate(k: int, minutes: float) -> str:
        # a count of rare events is Poisson: its exact (Garwood) 95 % interval, per minute
        from scipy.stats import chi2

        lo = chi2.ppf(0.025, 2 * k) / 2 if k else 0.0
        hi = chi2.ppf(0.975, 2 * k + 2) / 2
        m = max(minutes, 1e-9)
        return f"{k / m:.2f}/min (95 % interval {lo / m:.2f}-{hi / m:.2f}; {minutes:.1f} min)"

    print(f"phone PDR on the simulated walks (consumer IMU, phone in hand): {r['n_detected']} steps detected for {r['n_true']} true "
          f"(count error {100 * r['count_error']:+.2f}%; goal within 1 %); false steps standing {rate(r['false_standing'], r['standing_min'])}, "
          f"handling {rate(r['false_handling'], r['handling_min'])}; goal <= 1/min")
    # The same walks through a plain heading: gyro integration with no bias estimate and no compass.
    plain = pdr_on_sim(walks, imus, AttitudeConfig(k_mag=0.0, ki_acc=0.0, zaru=False))
    h, hp = np.degrees(r["heading_errors"]), np.degrees(plain["heading_errors"])
    print(f"heading on the simulated walks (relative to the first step, straight walking, {minutes:g} min walks with raw consumer gyros "
          f"and indoor magnetic disturbances): median {np.median(h):.1f} deg, p90 {np.percentile(h, 90):.1f}; plain gyro integration "
          f"{np.median(hp):.1f} / {np.percentile(hp, 90):.1f} deg (ratio of medians ours/plain {np.median(h) / np.median(hp):.2f})")
    return 0

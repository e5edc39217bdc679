"""``hybridloc eval sim-realism``: simulated statistics beside real ones, the phone PDR on simulated
walks with true steps (step-count error, false steps while standing or handling the phone), and the
step-length models on simulated and real waypoint segments (:func:`length_model_errors`): with one
uncalibrated constant the simulator should be as hard on a Weinberg-type model as real walks are."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..pdr.attitude import AttitudeConfig
from ..pdr.phone import PhonePdrConfig, run_phone_pdr
from ..radio.survey import LabelledScan
from ..units import wrap_angle
from .building import generate_world
from .imu import PhoneSensors, disturbance_field, phone_sensors
from .output import waypoints
from .radio import make_radio_model, simulate_radio
from .realism import rssi_slopes, similarity_by_distance, spectrum_peaks
from .walker import Walk, simulate_walk


@dataclass
class SimSample:
    world: object  # building.World
    labelled: list[LabelledScan]
    walks: list[Walk]
    sensors: list[PhoneSensors]
    ap_pos: dict[str, np.ndarray]


def simulate_sample(walkers: int, minutes: float, seed: int = 1) -> SimSample:
    """``walkers`` walks of ``minutes`` in a generated 3-floor building: their phones (IMU and rotation
    vector) and their WiFi scans labelled with the true positions."""
    world = generate_world(np.random.default_rng(seed), 3, seed)
    model = make_radio_model(world, np.random.default_rng([seed, 7]))
    field = disturbance_field(np.random.default_rng([seed, 11]))
    root = np.random.default_rng([seed, 13])
    labelled, walks, sensors = [], [], []
    for i in range(walkers):
        rng = np.random.default_rng(root.integers(2**63))
        walk = simulate_walk(world, rng, minutes, walker=i)
        phone = phone_sensors(walk, rng, mag_field=field)
        radio = simulate_radio(model, walk, rng)
        for s in radio.wifi:
            pos, fl = walk.position_at(np.array([s.t]))
            labelled.append(LabelledScan(s, pos[0], 0.0, world.floor_name(int(fl[0]))))
        walks.append(walk)
        sensors.append(phone)
    ap_pos = {k: p[:2] for k, p in zip(world.ap_ids, world.aps)}
    return SimSample(world, labelled, walks, sensors, ap_pos)


def simulated_sample(walkers: int, minutes: float, seed: int = 1):
    """:func:`simulate_sample` as (world, labelled scans, walks, IMU blocks, AP positions)."""
    sm = simulate_sample(walkers, minutes, seed)
    return sm.world, sm.labelled, sm.walks, [p.imu for p in sm.sensors], sm.ap_pos


def sim_trace_runs(
    walks: list[Walk],
    sensors: list[PhoneSensors],
    config: PhonePdrConfig | None = None,
    mark_sigma: float = 0.0,
    rng: np.random.Generator | None = None,
) -> list:
    """The simulated walks as :class:`~hybridloc.pdr.evaluate.TraceRun` s for the waypoint-segment
    scores of ``eval pdr-phone``: each walk through the phone PDR once, with the marks its trace file
    carries (:func:`.output.waypoints`). Only level segments are kept, as on the real walks (one floor
    each, no stairs): a walk is cut into stretches of consecutive marks on one floor with no stair step
    or lift ride between them. ``mark_sigma`` (m, per axis) moves every mark by Gaussian noise, as a
    walker's marks are off where and when they are made (the simulated marks are exact)."""
    import dataclasses

    from ..pdr.evaluate import trace_run

    config = config or PhonePdrConfig()
    out = []
    for walk, phone in zip(walks, sensors):
        marks = waypoints(walk)
        if len(marks) < 2:
            continue
        xy = np.array([m[1:3] for m in marks])
        if mark_sigma > 0:
            xy = xy + mark_sigma * (rng or np.random.default_rng(0)).standard_normal(xy.shape)
        run = trace_run(f"w{walk.walker:04d}", phone.imu, np.array([m[0] for m in marks]), xy, config, phone.rotation_vector)
        climb_t = np.array([s.t for s in walk.steps if s.dz != 0.0] + [a for a, _ in walk.lift_rides])
        level = []
        for (ta, _, _, fa), (tb, _, _, fb) in zip(marks[:-1], marks[1:]):
            level.append(fa == fb and not ((climb_t > ta - 1e-6) & (climb_t <= tb + 1e-6)).any())
        k = 0
        while k < len(level):  # maximal runs of level segments
            if not level[k]:
                k += 1
                continue
            j = k
            while j < len(level) and level[j]:
                j += 1
            out.append(dataclasses.replace(run, name=f"{run.name}:{k}", wp_t=run.wp_t[k : j + 1], wp_xy=run.wp_xy[k : j + 1]))
            k = j
    return out


#: m per axis: a waypoint mark's error where no real site gives it (ILC site1: 0.65 m / sqrt 2)
MARK_SIGMA_M = 0.45

#: the step-length models compared on simulated and real segments
LENGTH_MODELS_COMPARED = ("weinberg", "height", "kim", "constant")


def length_model_errors(runs: list) -> dict[str, dict[str, float]]:
    """Per step-length model, on waypoint segments of at least 3 m (``eval pdr-phone``'s scoring):
    ``default_pct``, the median relative segment-length error with the model's one uncalibrated
    constant (the library default a new device starts with: Weinberg K = 0.37); ``fit_pct``, the same
    with one constant fitted on all the scored walks themselves (no constant per walker: what is left
    is how loosely the model follows each walker and step); ``scale_pct``, the part of the segment
    error proportional to length (sigma, robust fit of :func:`~hybridloc.pdr.evaluate.decompose_segment_errors`),
    the step model's own share, and ``end_m`` its fixed part (m: the marks); ``segments``."""
    from ..pdr.evaluate import decompose_segment_errors, fit_model, score
    from ..pdr.steplength import make_model

    out = {}
    for name in LENGTH_MODELS_COMPARED:
        row = {}
        for key, model in (("default", make_model(name)), ("fit", fit_model(runs, name))):
            seg: list = []
            err, _, _ = score(runs, model, seg)
            row[f"{key}_pct"] = 100 * float(np.median(err)) if err else float("nan")
            if key == "default":
                sg = np.array(seg).reshape(-1, 2)
                end, rel = decompose_segment_errors(sg[:, 0], sg[:, 1])
                row["scale_pct"], row["end_m"] = 100 * rel, end
                row["segments"] = len(err)
            else:
                row["constant"] = float(model.coef[0])
        out[name] = row
    return out


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
    return {
        "n_true": n_true,
        "n_detected": n_det,
        "count_error": (n_det - n_true) / max(n_true, 1),
        "false_per_min_standing": false_steps / max(still_min, 1e-9),
        "false_per_min_handling": handling_steps / max(handling_min, 1e-9),
        "standing_min": still_min,
        "handling_min": handling_min,
        "false_standing": false_steps,
        "false_handling": handling_steps,
        "heading_errors": np.concatenate(herr) if herr else np.zeros(0),
    }


@dataclass
class RealismStat:
    """One statistic of ``eval sim-realism``: the simulated median beside the real values (None: no real counterpart)."""

    name: str
    sim: float
    real: np.ndarray | None
    unit: str


@dataclass
class SimRealism:
    """What ``hybridloc eval sim-realism`` reports (rendered by :mod:`hybridloc.cli.eval`)."""

    walkers: int
    minutes: float
    seed: int
    ilc: str
    n_real_traces: int | None  # None: no real site compared
    stats: list[RealismStat]
    sim_similarity: list[float]
    real_similarity: list[float] | None
    pdr: dict  # pdr_on_sim of our PDR
    plain: dict  # pdr_on_sim through plain gyro integration
    lengths_sim: dict | None = None  # length_model_errors on the simulated walks, their marks exact
    lengths_sim_marked: dict | None = None  # ... with marks as vague as the real ones (mark_sigma)
    lengths_real: dict | None = None  # ... on the real walks
    mark_sigma: float = 0.0  # m per axis, the real marks' error (from the real segments' fixed part)

    @property
    def have_real(self) -> bool:
        return self.n_real_traces is not None


def poisson_rate(k: int, minutes: float) -> tuple[float, float, float]:
    """(rate, low, high) per minute of ``k`` rare events in ``minutes``: a count of rare events is
    Poisson, and its exact (Garwood) 95 % interval is chi2(0.025; 2k)/2 .. chi2(0.975; 2k+2)/2."""
    from scipy.stats import chi2

    lo = chi2.ppf(0.025, 2 * k) / 2 if k else 0.0
    hi = chi2.ppf(0.975, 2 * k + 2) / 2
    m = max(minutes, 1e-9)
    return k / m, lo / m, hi / m


def run_sim_realism(ilc: str, walkers: int, minutes: float, every: int, seed: int = 1) -> SimRealism:
    """The simulated statistics, beside those of the real site folder ``ilc`` ('' for none)."""
    if ilc:  # checked before the minutes of simulation
        from ..errors import MissingData, check_input_dir
        from ..io.msft import find_ilc_traces

        check_input_dir(ilc, "Indoor Location Competition site folder (pass --ilc '' to skip)")
        if not find_ilc_traces(ilc):
            raise MissingData(f"{ilc}: no Indoor Location Competition traces (pass --ilc '' to skip)")
    rng = np.random.default_rng(0)
    sample = simulate_sample(walkers, minutes, seed)
    sim_lab, walks, ap_pos = sample.labelled, sample.walks, sample.ap_pos
    imus = [p.imu for p in sample.sensors]
    sim_slopes_crowd = rssi_slopes(sim_lab)
    sim_slopes_true = rssi_slopes(sim_lab, ap_pos)
    sim_sim = similarity_by_distance(sim_lab, rng)
    sim_freq = np.array([1.0 / np.median(np.diff([s.t for s in w.steps])) for w in walks if len(w.steps) > 5])
    sim_peaks = np.concatenate([spectrum_peaks(imu, walking_mask(w, imu.t)) for w, imu in zip(walks, imus)])
    have_real = bool(ilc) and Path(ilc).is_dir()
    n_real = real_sim = None
    real_slopes = real_freq = real_peaks = None
    lengths_real = None
    if have_real:
        from ..io.msft import find_ilc_traces, read_ilc_trace
        from ..pdr.evaluate import trace_run
        from ..radio.evaluate import load_site_surveys

        traces = load_site_surveys(ilc, every)
        real_lab = [ls for t in traces for ls in t.labelled]
        real_slopes = rssi_slopes(real_lab)
        real_sim = similarity_by_distance(real_lab, rng)
        freqs, peaks, real_runs = [], [], []
        config = PhonePdrConfig()
        for p in find_ilc_traces(ilc)[::every]:
            tr = read_ilc_trace(p)
            if tr.imu is None:
                continue
            run = trace_run(Path(p).name, tr.imu, tr.waypoints.t, tr.waypoints.pos_enu, config, tr.rotation_vector)
            if len(tr.waypoints) >= 2:
                real_runs.append(run)
            dt = np.diff([s.t for s in run.steps])
            dt = dt[dt < 1.2]
            if dt.size > 5:
                freqs.append(1.0 / np.median(dt))
            peaks += spectrum_peaks(tr.imu)
        real_freq, real_peaks = np.array(freqs), np.array(peaks)
        n_real = len(traces)
        lengths_real = length_model_errors(real_runs) if real_runs else None
    # The step-length models on the simulated walks' level segments: with their exact marks, and with
    # every mark moved as far as the real walkers' marks are off (the fixed part sigma_end of the real
    # segments' error is two marks' along-segment error: sqrt(2) x mark_sigma; 0.45 m without a real site)
    sim_runs = sim_trace_runs(walks, sample.sensors)
    lengths_sim = length_model_errors(sim_runs)
    mark_sigma = MARK_SIGMA_M
    if lengths_real is not None and math.isfinite(lengths_real["weinberg"]["end_m"]):
        mark_sigma = lengths_real["weinberg"]["end_m"] / math.sqrt(2.0)
    lengths_sim_marked = length_model_errors(sim_trace_runs(walks, sample.sensors, mark_sigma=mark_sigma, rng=np.random.default_rng([seed, 17])))
    stats = [
        RealismStat("RSSI slope vs log10 distance (crowd AP est.)", float(np.median(sim_slopes_crowd)), real_slopes, " dB/dec"),
        RealismStat("RSSI slope vs log10 distance (true AP pos.)", float(np.median(sim_slopes_true)), None, " dB/dec"),
        RealismStat("step frequency while walking", float(np.median(sim_freq)), real_freq, " Hz"),
        RealismStat("|a| spectrum peak while walking", float(np.median(sim_peaks)), real_peaks, " Hz"),
    ]
    r = pdr_on_sim(walks, imus)
    # The same walks through a plain heading: gyro integration with no bias estimate and no compass.
    plain = pdr_on_sim(walks, imus, AttitudeConfig(k_mag=0.0, ki_acc=0.0, zaru=False))
    return SimRealism(
        walkers,
        minutes,
        seed,
        ilc,
        n_real,
        stats,
        list(sim_sim),
        None if real_sim is None else list(real_sim),
        r,
        plain,
        lengths_sim,
        lengths_sim_marked,
        lengths_real,
        mark_sigma,
    )

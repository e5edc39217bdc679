"""Phone PDR evaluation on waypoint-annotated traces (``hybridloc eval pdr-phone``).

For each pair of consecutive waypoints (a *segment*):

* **length error**: |PDR displacement between the two waypoint times| vs the true distance, relative;
* **heading-change error**: the turn between consecutive segments, PDR vs truth (independent of the
  unknown absolute heading offset between the magnetometer and the floor plan);
* **error at waypoints** of a PDR-only track started at the first waypoint. The start heading is
  the one thing PDR cannot know: it is set so that the PDR's first segment points along the true
  first segment (the usual "known start pose" of PDR evaluation); every later waypoint is free.

Step length is calibrated per device from known distances (:class:`~.steplength.LengthCalibrator`)
with two-fold cross-fitting over traces: coefficients learned on one half of the traces score the
other half, so no trace is scored with a model fitted to itself.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.msft import read_ilc_trace
from ..metrics import oracle_start_errors
from ..types import ImuBlock, StepEvent
from ..units import wrap_angle
from .attitude import forward_headings
from .deadreckoning import DeadReckoning
from .phone import PhonePdr, PhonePdrConfig
from .steplength import MIN_CALIBRATION_SEGMENT_M, LengthCalibrator, StepFeatures, calibrate_from_marks, make_model

#: Segments shorter than this are not scored for length or turn (a waypoint mark is ~0.5 m vague).
MIN_SEGMENT_M = MIN_CALIBRATION_SEGMENT_M


@dataclass
class TraceRun:
    name: str
    steps: list[StepEvent]
    features: list[StepFeatures]
    wp_t: np.ndarray
    wp_xy: np.ndarray
    #: per step, the phone's forward heading from Android's own fused attitude (TYPE_ROTATION_VECTOR),
    #: circular mean over the step; None when the recording has no rotation vector
    android_heading: np.ndarray | None = None
    #: the walk's floor (Indoor Location Competition traces: one per trace; "" when unknown), the group
    #: of :func:`floor_held_out`
    floor: str = ""


def android_step_headings(steps: list[StepEvent], rv_t: np.ndarray, rv_quat_wxyz: np.ndarray) -> np.ndarray:
    """Android's forward heading per step: the circular mean over the step's interval (previous step
    to this one) of :func:`~.attitude.forward_headings` of the rotation vector, the nearest sample
    when none falls inside. The same "forward" as our own estimator's, so the two differ only in the
    attitude filter."""
    h = forward_headings(rv_quat_wxyz)
    c, s = np.cumsum(np.concatenate([[0.0], np.cos(h)])), np.cumsum(np.concatenate([[0.0], np.sin(h)]))
    ts = np.array([st.t for st in steps])
    lo = np.searchsorted(rv_t, np.concatenate([[ts[0] - 0.5], ts[:-1]]) if len(ts) else ts, side="right")
    hi = np.searchsorted(rv_t, ts, side="right")
    out = np.empty(len(ts))
    for i in range(len(ts)):
        if hi[i] > lo[i]:
            out[i] = math.atan2(s[hi[i]] - s[lo[i]], c[hi[i]] - c[lo[i]])
        else:
            out[i] = h[min(int(np.searchsorted(rv_t, ts[i])), len(h) - 1)]
    return out


@dataclass
class PhoneEvalResult:
    model: str
    detector: str
    coefs: list[list[float]]
    length_rel_err: np.ndarray
    turn_err_deg: np.ndarray
    wp_err: np.ndarray
    n_traces: int
    n_segments: int
    n_steps: int
    walked_m: float
    skipped: list[str] = field(default_factory=list)
    seg_true_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # true length of each scored segment, m
    seg_err_m: np.ndarray = field(default_factory=lambda: np.zeros(0))  # PDR length minus true length, m
    turn_lengths_m: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # (before, after) segment lengths of each turn
    turn_err_rad: np.ndarray = field(default_factory=lambda: np.zeros(0))  # signed turn error, rad


def _binned_variance_fit(u: np.ndarray, e: np.ndarray, bins: int) -> tuple[float, float]:
    """Robust fit of E[e^2] = a + b u (a, b >= 0): the samples in ``bins`` groups of equal count by u;
    in each, the median of e^2 / 0.455 (the median of a chi-square with one degree of freedom)
    estimates E[e^2] despite gross outliers; a non-negative least-squares line through (mean u, that).
    Returns (sqrt a, sqrt b); NaNs with fewer than 3 samples a bin."""
    from scipy.optimize import nnls

    if len(e) < 3 * bins:
        return float("nan"), float("nan")
    groups = np.array_split(np.argsort(u), bins)
    A = np.array([[1.0, float(np.mean(u[g]))] for g in groups])
    y = np.array([float(np.median(e[g] ** 2)) / 0.455 for g in groups])
    coef, _ = nnls(A, y)
    return float(np.sqrt(coef[0])), float(np.sqrt(coef[1]))


def decompose_segment_errors(true_m: np.ndarray, err_m: np.ndarray, bins: int = 5) -> tuple[float, float]:
    """Split segment length errors into a part fixed per segment and a part proportional to length.

    Model: e = n_end + s D, with n_end ~ (0, sigma_end^2) (where and when the walker marked each
    waypoint, and where the step track is cut at the mark times: neither grows with the segment)
    and s ~ (0, sigma_rel^2) (the PDR's step-length scale), so E[e^2] = sigma_end^2 + sigma_rel^2 D^2,
    fitted robustly (a few segments are off by tens of metres) by :func:`_binned_variance_fit` with
    u = D^2. Returns (sigma_end in m, sigma_rel as a fraction).
    """
    D = np.asarray(true_m, float)
    return _binned_variance_fit(D**2, np.asarray(err_m, float), bins)


def decompose_turn_errors(lengths_m: np.ndarray, err_rad: np.ndarray, bins: int = 5) -> tuple[float, float]:
    """Split turn errors into the PDR's own and what the waypoint marks put into the truth.

    A segment's true direction comes from two marks each off by ~sigma_mark across the segment, so it
    errs by ~sqrt(2) sigma_mark / D; a turn takes two segments: E[e^2] = sigma_turn^2 + sigma_mark^2 u
    with u = 2 (1/D1^2 + 1/D2^2), fitted by :func:`_binned_variance_fit`. Returns (sigma_turn in rad,
    sigma_mark in m).
    """
    Ls = np.asarray(lengths_m, float).reshape(-1, 2)
    return _binned_variance_fit(2.0 * (1.0 / Ls[:, 0] ** 2 + 1.0 / Ls[:, 1] ** 2), np.asarray(err_rad, float), bins)


def collect_runs(paths: list[Path], config: PhonePdrConfig) -> tuple[list[TraceRun], list[str]]:
    """Run the PDR once per trace; the steps' features let any length model be applied afterwards."""
    runs, skipped = [], []
    for p in paths:
        tr = read_ilc_trace(p)
        if tr.imu is None or len(tr.waypoints) < 2:
            skipped.append(f"{Path(p).name}: no IMU or fewer than 2 waypoints")
            continue
        run = trace_run(Path(p).name, tr.imu, tr.waypoints.t, tr.waypoints.pos_enu, config, tr.rotation_vector)
        runs.append(dataclasses.replace(run, floor=tr.waypoints.floor or ""))
    return runs, skipped


def trace_run(
    name: str,
    imu: ImuBlock,
    wp_t: np.ndarray,
    wp_xy: np.ndarray,
    config: PhonePdrConfig,
    rotation_vector: tuple[np.ndarray, np.ndarray] | None = None,
) -> TraceRun:
    """One walk through the PDR (steps and their features), with its marks and, when it has one,
    Android's heading per step from the rotation vector."""
    pdr = PhonePdr(imu.rate_hz, make_model("height"), config, heading0=0.0)
    pdr.process(imu)
    steps = list(pdr.steps)
    rv = rotation_vector
    android = android_step_headings(steps, rv[0], rv[1]) if rv is not None and len(rv[0]) and steps else None
    return TraceRun(name, steps, list(pdr.features), np.asarray(wp_t, float), np.asarray(wp_xy, float).reshape(-1, 2), android)


def _segments(run: TraceRun):
    """(k, t0, t1, true length) of each waypoint segment long enough to score, with steps inside."""
    ts = np.array([s.t for s in run.steps])
    out = []
    for k in range(len(run.wp_t) - 1):
        t0, t1 = run.wp_t[k], run.wp_t[k + 1]
        D = float(np.linalg.norm(run.wp_xy[k + 1] - run.wp_xy[k]))
        idx = np.flatnonzero((ts > t0) & (ts <= t1))
        out.append((k, t0, t1, D, idx))
    return out


def _track(run: TraceRun, lengths: np.ndarray, heading: str = "ours") -> DeadReckoning:
    """The PDR track from the steps' times with ``lengths`` and headings (``heading``: "ours", the
    steps' own, or "android", the rotation vector's), from (0, 0) 1 s before the first step (or at
    the first waypoint if earlier)."""
    if not run.steps:
        return DeadReckoning(run.wp_t[0])
    h = np.array([s.heading for s in run.steps]) if heading == "ours" else run.android_heading
    return DeadReckoning.from_lengths_headings([s.t for s in run.steps], lengths, h, t0=min(run.steps[0].t - 1.0, run.wp_t[0]))


def fit_model(runs: list[TraceRun], model_name: str):
    """One calibration over all the walks' waypoint segments (the same update a device's own
    calibration gets from ``hybridloc pdr phone --update-calibration``)."""
    cal = LengthCalibrator(make_model(model_name), forgetting=1.0)
    for r in runs:
        calibrate_from_marks(cal, np.array([s.t for s in r.steps]), r.features, r.wp_t, r.wp_xy, min_segment_m=MIN_SEGMENT_M)
    return cal.model


def _turns(run: TraceRun, tracks: list[np.ndarray]):
    """(k, true turn, turn of each track) at each waypoint k whose segments on both sides are scored:
    at least MIN_SEGMENT_M long, and at least 0.5 m long in every track (positions at the waypoint
    times). A turn is the change of a segment's direction from one segment to the next, rad."""
    dirs = []
    for k, _t0, _t1, D, _idx in _segments(run):
        moves = [w[k + 1] - w[k] for w in [run.wp_xy] + tracks]
        ok = D >= MIN_SEGMENT_M and all(np.linalg.norm(m) > 0.5 for m in moves[1:])
        dirs.append([math.atan2(m[1], m[0]) for m in moves] if ok else None)
    for k in range(1, len(dirs)):
        if dirs[k] is not None and dirs[k - 1] is not None:
            yield (k, *(wrap_angle(a - b) for a, b in zip(dirs[k], dirs[k - 1])))


def marks_on_straight_walks(runs: list[TraceRun], model, straight_deg: float = 5.0) -> tuple[np.ndarray, int]:
    """The waypoint marks' own turn (deg, absolute) where two heading estimators from the same phone,
    ours and Android's rotation vector, both see the walker go straight (turn under ``straight_deg``),
    and how many turns were compared. A walker cannot turn 10 deg unseen by a gyro (nor could both
    filters miss it alike), so what the marks show there is their own direction error: a part of the
    heading-change error no PDR can remove. Traces without a rotation vector are left out."""
    seen, n = [], 0
    for r in runs:
        if r.android_heading is None or not r.features:
            continue
        L = np.array([model.length(f) for f in r.features])
        tracks = [_track(r, L, h).position_at(r.wp_t) for h in ("ours", "android")]
        for _k, turn_t, turn_ours, turn_android in _turns(r, tracks):
            n += 1
            if max(abs(turn_ours), abs(turn_android)) < math.radians(straight_deg):
                seen.append(abs(math.degrees(turn_t)))
    return np.array(seen), n


def score(
    runs: list[TraceRun], model, seg: list | None = None, turns: list | None = None, heading: str = "ours"
) -> tuple[list[float], list[float], list[float]]:
    """Relative length errors, turn errors (deg) and waypoint errors (m); ``seg`` collects (D, error in m),
    ``turns`` (D before, D after, error in rad) of each scored turn; ``heading`` as in :func:`_track`."""
    len_err, turn_err, wp_err = [], [], []
    for r in runs:
        L = np.array([model.length(f) for f in r.features]) if r.features else np.zeros(0)
        wp_est = _track(r, L, heading).position_at(r.wp_t)
        lens = []
        for k, _t0, _t1, D, _idx in _segments(r):
            if D >= MIN_SEGMENT_M:
                est_len = float(np.linalg.norm(wp_est[k + 1] - wp_est[k]))
                len_err.append(abs(est_len - D) / D)
                if seg is not None:
                    seg.append((D, est_len - D))
            lens.append(D)
        for k, turn_t, turn_e in _turns(r, [wp_est]):
            turn_err.append(abs(wrap_angle(turn_e - turn_t)) * 180 / math.pi)
            if turns is not None:
                turns.append((lens[k - 1], lens[k], wrap_angle(turn_e - turn_t)))
        # PDR-only track from the first waypoint, rotated so its first segment points the true way.
        wp_err.extend(oracle_start_errors(wp_est, r.wp_xy).tolist())
    return len_err, turn_err, wp_err


def evaluate_phone_pdr(
    paths: list[Path], model_name: str = "height", config: PhonePdrConfig | None = None, runs=None, heading: str = "ours"
) -> PhoneEvalResult:
    """Scores of one length model, cross-fitted over two halves of the traces. ``heading="android"``
    replaces our heading by Android's rotation vector (same steps and lengths) on the traces that
    have one: the public estimator doing the same job, for the ratio."""
    config = config or PhonePdrConfig()
    skipped: list[str] = []
    if runs is None:
        runs, skipped = collect_runs(paths, config)
    if heading == "android":
        runs = [r for r in runs if r.android_heading is not None]
    folds = [runs[0::2], runs[1::2]]
    L, T, W, coefs, seg, turns = [], [], [], [], [], []
    for i in (0, 1):
        model = fit_model(folds[1 - i], model_name)  # learned on the other half
        coefs.append([float(c) for c in model.coef])
        le, te, we = score(folds[i], model, seg, turns, heading)
        L += le
        T += te
        W += we
    walked = sum(float(np.linalg.norm(np.diff(r.wp_xy, axis=0), axis=1).sum()) for r in runs)
    sg = np.array(seg).reshape(-1, 2)
    tn = np.array(turns).reshape(-1, 3)
    return PhoneEvalResult(
        model_name,
        config.detector,
        coefs,
        np.array(L),
        np.array(T),
        np.array(W),
        len(runs),
        len(L),
        sum(len(r.steps) for r in runs),
        walked,
        skipped,
        sg[:, 0],
        sg[:, 1],
        tn[:, :2],
        tn[:, 2],
    )


def turn_in_hand(imu: ImuBlock, angle: float) -> ImuBlock:
    """The same walk with the phone turned by ``angle`` (rad) about its own z axis (the screen's
    normal) for the whole recording: a constant re-orientation, so all three sensors rotate together
    and the recording stays physically consistent (new body axes = Rz(angle)^T old)."""
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    turn = lambda x: None if x is None else np.asarray(x) @ R  # noqa: E731  rows: R^T v
    # the same block otherwise (source, full scale): only the axes turn
    return dataclasses.replace(imu, accel_body=turn(imu.accel_body), gyro_body=turn(imu.gyro_body), mag_body=turn(imu.mag_body))


def offset_recovery(
    paths: list[Path], angles_deg: tuple[float, ...] = (90.0, 180.0), sign_rules: tuple[str, ...] = ("gait", "continuity"), min_steps: int = 10
) -> dict[str, dict[float, np.ndarray]]:
    """How well the walking-direction offset is recovered when the phone is carried turned.

    Each real walk is re-oriented (:func:`turn_in_hand`) by each angle and run with the offset
    estimated; its walking heading (circular mean over the second half of the steps) is compared with
    the same walk's unturned one. Returns rule -> angle -> |difference| per walk, rad."""
    out: dict[str, dict[float, list]] = {r: {a: [] for a in angles_deg} for r in sign_rules}

    def walk_heading(imu: ImuBlock, rule: str) -> float | None:
        pdr = PhonePdr(imu.rate_hz, config=PhonePdrConfig(estimate_offset=True, offset_sign=rule))
        steps = pdr.process(imu)
        if len(steps) < min_steps:
            return None
        h = np.array([s.heading for s in steps[len(steps) // 2 :]])
        return float(np.angle(np.exp(1j * h).mean()))

    for p in paths:
        tr = read_ilc_trace(p)
        if tr.imu is None:
            continue
        for rule in sign_rules:
            h0 = walk_heading(tr.imu, rule)
            if h0 is None:
                break
            for a in angles_deg:
                h = walk_heading(turn_in_hand(tr.imu, math.radians(a)), rule)
                if h is not None:
                    out[rule][a].append(abs(wrap_angle(h - h0)))
    return {r: {a: np.array(v) for a, v in d.items()} for r, d in out.items()}


#: the magnetometer's yaw pull (AttitudeConfig.k_mag) candidates :func:`floor_held_out` chooses from
K_MAG_CANDIDATES = (0.0, 0.01, 0.03, 0.1)


@dataclass
class FloorHeldOut:
    """:func:`floor_held_out`'s result: per floor, the setting chosen on the other floors and the
    scores there; pooled over floors, held out and fitted (the one setting best on every floor)."""

    floors: list[str]
    chosen: dict[str, float]  # floor -> k_mag chosen without it
    turn_med: dict[str, float]  # floor -> heading-change error median, deg (held out)
    length_med: dict[str, float]  # floor -> segment length error median, % (held out)
    plain_turn_med: dict[str, float]  # the plain baseline (peak steps, Weinberg, Android's yaw), same floors
    plain_length_med: dict[str, float]
    turn_held_out: float  # pooled over every floor's held-out errors, deg
    length_held_out: float  # %
    plain_turn: float
    plain_length: float
    fitted_k_mag: float
    turn_fitted: float  # the fitted setting, lengths still fitted on the other floors
    length_fitted: float
    plain_traces: int  # traces with Android's rotation vector (the baseline's heading)


def _floor_scores(runs: list[TraceRun], model_name: str, heading: str = "ours") -> dict[str, tuple[list[float], list[float]]]:
    """Per floor: (segment length errors, turn errors in deg) of its walks, the length model fitted on
    the walks of the other floors only."""
    out = {}
    for f in sorted({r.floor for r in runs}):
        train = [r for r in runs if r.floor != f]
        model = fit_model(train if train else runs, model_name)
        le, te, _ = score([r for r in runs if r.floor == f], model, heading=heading)
        out[f] = (le, te)
    return out


def floor_held_out(
    paths: list[Path],
    config: PhonePdrConfig,
    runs: list[TraceRun],
    model_name: str = "height",
    k_mags: tuple[float, ...] = K_MAG_CANDIDATES,
) -> FloorHeldOut:
    """Phone PDR held out by floor (issue 24 points 1 and 3): for each floor, the magnetometer's yaw
    pull k_mag is chosen from ``k_mags`` by the pooled heading-change median of the OTHER floors (each
    of them scored with lengths fitted without it), and that floor is scored with it, its lengths
    fitted on the other floors. The plain baseline (peak steps, Weinberg lengths, Android's rotation
    vector for the heading) is held out the same way. ``runs``: the walks under ``config`` (reused for
    its k_mag); every other candidate runs the PDR again."""
    by_k: dict[float, list[TraceRun]] = {}
    for k in k_mags:
        if math.isclose(k, config.attitude.k_mag):
            by_k[k] = runs
        else:
            cfg = dataclasses.replace(config, attitude=dataclasses.replace(config.attitude, k_mag=k))
            by_k[k] = collect_runs(paths, cfg)[0]
    floors = sorted({r.floor for r in runs})
    scores = {k: _floor_scores(rk, model_name) for k, rk in by_k.items()}

    def pooled_turn(k: float, fl) -> float:
        vals = [e for f in fl for e in scores[k][f][1]]
        return float(np.median(vals)) if vals else math.inf

    chosen: dict[str, float] = {}
    for f in floors:
        others = [g for g in floors if g != f] or floors
        chosen[f] = min(k_mags, key=lambda k: pooled_turn(k, others))
    fitted = min(k_mags, key=lambda k: pooled_turn(k, floors))
    andr = [r for r in runs if r.android_heading is not None]
    plain = _floor_scores(andr, "weinberg", heading="android") if andr else {}

    def med(v, scale=1.0) -> float:
        return scale * float(np.median(v)) if len(v) else float("nan")

    held_len = [e for f in floors for e in scores[chosen[f]][f][0]]
    held_turn = [e for f in floors for e in scores[chosen[f]][f][1]]
    return FloorHeldOut(
        floors=floors,
        chosen=chosen,
        turn_med={f: med(scores[chosen[f]][f][1]) for f in floors},
        length_med={f: med(scores[chosen[f]][f][0], 100.0) for f in floors},
        plain_turn_med={f: med(plain[f][1]) if f in plain else float("nan") for f in floors},
        plain_length_med={f: med(plain[f][0], 100.0) if f in plain else float("nan") for f in floors},
        turn_held_out=med(held_turn),
        length_held_out=med(held_len, 100.0),
        plain_turn=med([e for v in plain.values() for e in v[1]]),
        plain_length=med([e for v in plain.values() for e in v[0]], 100.0),
        fitted_k_mag=fitted,
        turn_fitted=pooled_turn(fitted, floors),
        length_fitted=med([e for f in floors for e in scores[fitted][f][0]], 100.0),
        plain_traces=len(andr),
    )

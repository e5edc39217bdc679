"""Foot INS evaluation on PyShoe VICON trials (``hybridloc eval pdr-foot``).

Per trial: PyShoe's 2-D and 3-D ARMSE (:func:`hybridloc.metrics.pyshoe_armse` after
:func:`~hybridloc.metrics.pyshoe_align`) of our default filter and detector, one setting for all
trials, beside the authors' own ``trial_error`` (their ZUPT-EKF with the SHOE detector at the
threshold tuned per trial on the ground truth); for trials whose truth returns to its start (a loop:
end within ``LOOP_CLOSE_M`` of the start), the return-to-start error in % of distance travelled
(Ojeda & Borenstein eqs 7-9). A plain method runs beside ours in the same pass: DEDRIFT-I
(Ojeda's velocity reset + acceleration de-drifting at gyro minima).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..io.imu_files import read_pyshoe_mat
from ..metrics import pyshoe_align, pyshoe_armse, return_to_start_error
from ..units import DEG
from .eskf import ImuNoise
from .foot import FootInsConfig, dedrift_i, run_foot_ins, still_prefix
from .stance import gyro_minimum

#: A trial is a loop when its true end is within this distance of its true start, m.
LOOP_CLOSE_M = 0.3


@dataclass
class TrialResult:
    name: str
    armse_2d: float
    armse_3d: float
    authors_2d: float
    dedrift_2d: float
    distance_m: float
    loop_pct: float | None  # return-to-start error, % of distance (loops only)
    duration_s: float
    stance_fraction: float
    opt_labels_2d: float = float("nan")  # our forward filter on the authors' per-trial-optimal SHOE stance labels
    forward_2d: float = float("nan")  # the forward filter alone (no stride smoothing), like the authors' figure
    end_pct: float = float("nan")  # the aligned track's end against the true end, % of distance (loops: the return error net of the truth's own gap)


def evaluate_trial(path: str | Path, config: FootInsConfig | None = None) -> TrialResult:
    rec = read_pyshoe_mat(path)
    if rec.truth is None:
        raise ValueError(f"{path}: no ground truth")
    res = run_foot_ins(rec.imu, config)
    est, gt = pyshoe_align(res.pos_enu, rec.truth.pos_enu)
    fwd = float("nan")
    if res.pos_enu_forward is not None:
        fwd = pyshoe_armse(*pyshoe_align(res.pos_enu_forward, rec.truth.pos_enu), 2)
    dd = dedrift_i(rec.imu, gyro_minimum(rec.imu.gyro_body, n=max(1, int(0.5 * rec.imu.rate_hz)))[1])
    dd_a, gt_a = pyshoe_align(dd, rec.truth.pos_enu)
    loop = None
    if np.linalg.norm(gt[-1, :2] - gt[0, :2]) <= LOOP_CLOSE_M:
        loop = return_to_start_error(res.pos_enu).e_p
    dist = float(np.linalg.norm(np.diff(gt[:, :2], axis=0), axis=1).sum())
    end_pct = 100.0 * float(np.linalg.norm(est[-1, :2] - gt[-1, :2])) / dist
    te = rec.extras.get("trial_error")
    opt = float("nan")
    labels = rec.extras.get("zv_shoe_opt")
    if labels is not None and len(labels) == len(rec.imu.t):
        # the same filter on the stance the authors' SHOE gives at its per-trial best threshold: splits
        # the gap to their figure into what the detector costs and what the filter does. Their labels
        # are taken as they are (no vetting: deciding which stances to doubt is part of our detection)
        # and, like the authors' figure, the forward filter's track
        cfg_opt = replace(config or FootInsConfig(), vet=False, smooth=False)
        e_opt, g_opt = pyshoe_align(run_foot_ins(rec.imu, cfg_opt, stance=labels).pos_enu, rec.truth.pos_enu)
        opt = pyshoe_armse(e_opt, g_opt, 2)
    return TrialResult(
        Path(path).stem,
        pyshoe_armse(est, gt, 2),
        pyshoe_armse(est, gt, 3),
        float(te[0]) if te is not None else float("nan"),
        pyshoe_armse(dd_a, gt_a, 2),
        dist,
        loop,
        rec.imu.duration,
        float(res.stance.mean()),
        opt,
        fwd,
        end_pct,
    )


# ---------------------------------------------------------------- gait-driven set: stride by stride
#: The estimate's heading is aligned on the first footprint at least this far (m) from the start.
GAIT_ALIGN_M = 2.0
#: A gait-driven walk "closes" when its true end is within this share of its path from its start:
#: there the return error hardly depends on the heading alignment (a heading error d moves the end
#: by at most d * 2 % of the path: 0.2 % at 0.1 rad).
GAIT_CLOSE_FRACTION = 0.02


@dataclass
class GaitResult:
    name: str
    n_walked: int  # numberOfStrides
    n_detected: int  # strides called (footprints - 1)
    footprint_err_m: np.ndarray | None  # (K,) per truth footprint after the start, when the count is exact
    final_err_m: float  # last footprint against the true end, m
    distance_m: float  # true path (footprint to footprint), m
    closes: bool  # true end within GAIT_CLOSE_FRACTION of the path from the start
    session: str = ""  # gait_session: logging rate and mounting

    @property
    def final_pct(self) -> float:
        return 100.0 * self.final_err_m / self.distance_m


def align_footprints(est_xy: np.ndarray, true_xy: np.ndarray, dist: float = GAIT_ALIGN_M) -> np.ndarray:
    """Shift the estimated footprints (K, 2) to start at the true start, and rotate them about it so
    that the first footprint at least ``dist`` m from the start points the same way as the truth's
    first footprint that far out (no stride correspondence needed: counts may differ)."""
    e = np.asarray(est_xy, float) - est_xy[0]
    g = np.asarray(true_xy, float) - true_xy[0]

    def bearing(p: np.ndarray) -> float:
        d = np.hypot(p[:, 0], p[:, 1])
        far = np.flatnonzero(d >= dist)
        k = int(far[0]) if far.size else len(p) - 1
        return float(np.arctan2(p[k, 1], p[k, 0]))

    ang = bearing(g) - bearing(e)
    c, s = np.cos(ang), np.sin(ang)
    return e @ np.array([[c, s], [-s, c]]) + true_xy[0]


def evaluate_gait_walk(path: str | Path, config: FootInsConfig | None = None) -> GaitResult:
    """One gait-driven walk (SensorConnect CSV with its footprint .mat beside it), stride by stride."""
    from ..io.imu_files import footprints_beside, read_sensorconnect_csv
    from .foot import stance_points

    fp = footprints_beside(path)
    if fp is None:
        raise ValueError(f"{path}: no footprint .mat beside it")
    rec = read_sensorconnect_csv(path)
    res = run_foot_ins(rec.imu, config)
    pts = stance_points(res)
    if len(pts) < 2:
        raise ValueError(f"{path}: fewer than two stances detected")
    est = align_footprints(res.pos_enu[pts, :2], fp.pos_xy)
    n_det = len(pts) - 1
    err = None
    if n_det == fp.n_strides:
        err = np.linalg.norm(est[fp.stride] - fp.pos_xy, axis=1)[1:]
    if fp.stride[-1] != fp.n_strides:
        raise ValueError(f"{path}: the last footprint is not after the last stride")
    final = float(np.linalg.norm(est[-1] - fp.pos_xy[-1]))
    closes = bool(np.linalg.norm(fp.pos_xy[-1] - fp.pos_xy[0]) <= GAIT_CLOSE_FRACTION * fp.distance_m)
    name = Path(path).name.split(".")[0]
    up = np.mean(rec.imu.accel_body[: still_prefix(rec.imu, 0.5)], axis=0)
    return GaitResult(name, fp.n_strides, n_det, err, final, fp.distance_m, closes, gait_session(rec.imu.rate_hz, up))


def gait_session(rate_hz: float, up_body: np.ndarray) -> str:
    """A gait-driven walk's recording session, told apart by what the logs show: the logging rate and
    the sensor's mounting (the body axis gravity leans on at the start; the set's walks 31-36 have it
    along +x, 38-40 along -x, 42-45 log at 250 Hz). The file names carry no dates."""
    u = np.asarray(up_body, float)
    return f"{rate_hz:.0f}Hz/{'+' if u[0] >= 0 else '-'}x"


def gait_walks(folder: str | Path) -> list[Path]:
    """The gait-driven walks of ``folder`` that have both an IMU CSV and a footprint .mat."""
    out = []
    for p in sorted(Path(folder).glob("*.csv*")):
        stem = p.name.split(".")[0]
        if (p.parent / f"{stem}.mat").is_file():
            out.append(p)
    return out


@dataclass
class GaitSummary:
    walks: int
    count_exact: int  # walks whose strides were counted exactly as walked
    count_abs_err_mean: float  # mean |called - walked| strides
    footprint_median_m: float  # per-stride footprint error, median over the exactly counted walks' strides
    footprint_p90_m: float
    final_median_pct: float  # last footprint against the true end, % of the true path
    final_max_pct: float
    return_median_pct: float  # the same on the walks whose truth closes (GAIT_CLOSE_FRACTION)
    return_max_pct: float
    closing: int


def summarize_gait(rs: list[GaitResult]) -> GaitSummary:
    fe = [r.footprint_err_m for r in rs if r.footprint_err_m is not None]
    fe = np.concatenate(fe) if fe else np.array([np.nan])
    fin = np.array([r.final_pct for r in rs])
    ret = np.array([r.final_pct for r in rs if r.closes] or [np.nan])
    return GaitSummary(
        len(rs),
        sum(r.n_detected == r.n_walked for r in rs),
        float(np.mean([abs(r.n_detected - r.n_walked) for r in rs])),
        float(np.median(fe)),
        float(np.percentile(fe, 90)),
        float(np.median(fin)),
        float(fin.max()),
        float(np.median(ret)),
        float(np.max(ret)),
        sum(r.closes for r in rs),
    )


# ---------------------------------------------------------------- cross-validation
def pyshoe_group(path: str | Path) -> str:
    """A PyShoe trial's group: its recording day (``2017-11-22-11-22-03`` -> ``2017-11-22``). The
    trials of one day share a session (walker, shoe, motion types), so a day held out is a session
    the setting has not seen."""
    return Path(path).stem[:10]


def leave_one_group_out(scores: np.ndarray, groups: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Per item, the candidate chosen on the other groups' mean score (lower is better), and the
    item's score at it. ``scores`` (n_items, n_candidates). Returns (chosen index (n,), held-out (n,))."""
    scores = np.asarray(scores, float)
    g = np.asarray(groups)
    chosen = np.zeros(len(g), int)
    for grp in np.unique(g):
        out = g == grp
        chosen[out] = int(np.argmin(scores[~out].mean(axis=0)))
    return chosen, scores[np.arange(len(g)), chosen]


def _trial_armse(job: tuple[Path, list[FootInsConfig]]) -> np.ndarray:
    """One trial's 2-D ARMSE under each config (a process pool's task)."""
    path, configs = job
    rec = read_pyshoe_mat(path)
    return np.array([pyshoe_armse(*pyshoe_align(run_foot_ins(rec.imu, c).pos_enu, rec.truth.pos_enu), 2) for c in configs])


def pyshoe_armse_grid(paths: list[Path], configs: list[FootInsConfig], workers: int = 1) -> np.ndarray:
    """2-D ARMSE (the smoothed track, as `pdr foot` writes it) of each trial under each config, (n, c);
    the trials in ``workers`` processes (each trial's figures are the same either way)."""
    jobs = [(Path(p), list(configs)) for p in paths]
    if workers <= 1 or len(jobs) < 2:
        rows = [_trial_armse(j) for j in jobs]
    else:
        from ..pools import process_pool

        with process_pool(workers) as ex:
            rows = list(ex.map(_trial_armse, jobs))
    return np.array(rows).reshape(len(paths), len(configs))


#: The foot filter's constants besides the stance threshold that were set on the PyShoe trials, with the
#: candidates ``eval pdr-foot`` chooses among jointly with the threshold, leaving one recording day out:
#: the ZUPT's velocity sigma (m/s; the default, half and twice) and the turn-on bias priors
#: (accelerometer m/s^2, gyroscope rad/s; the default, half, and the wider pair eskf.ImuNoise's comment
#: measured against). The defaults come first, so the threshold-only search is the joint one's subset.
FOOT_ZUPT_SIGMAS = (FootInsConfig().zupt_sigma, 0.005, 0.02)
FOOT_BIAS_PRIORS = (
    (ImuNoise().accel_bias_sigma0, ImuNoise().gyro_bias_sigma0),
    (0.005, 0.01 * DEG),
    (0.05, 0.2 * DEG),
)


#: The vertical ZARU's sigma (rad/s; None: off, the filter as it is) that ``eval pdr-foot`` chooses on the
#: gait-driven walks, leaving one walk out and one session out: decades around the 3-D ZARU's 0.5 deg/s
#: and the foot's residual turning at stance (a few deg/s)
FOOT_ZARU_UP_SIGMAS: tuple[float | None, ...] = (None, 0.5 * DEG, 2 * DEG, 5 * DEG, 10 * DEG)


def foot_joint_candidates(decades: list[float]) -> list[FootInsConfig]:
    """Every (threshold, ZUPT sigma, bias priors) of ``decades`` x :data:`FOOT_ZUPT_SIGMAS` x
    :data:`FOOT_BIAS_PRIORS`, the threshold varying fastest: the first ``len(decades)`` are the
    thresholds alone with the other constants at their defaults."""
    return [
        FootInsConfig(detector_threshold=d, zupt_sigma=z, noise=replace(ImuNoise(), accel_bias_sigma0=a, gyro_bias_sigma0=g))
        for (a, g) in FOOT_BIAS_PRIORS
        for z in FOOT_ZUPT_SIGMAS
        for d in decades
    ]


# ---------------------------------------------------------------- simulated closed loops
def simulated_loop_errors(n: int, minutes: float = 1.5, seed: int = 100, config: FootInsConfig | None = None) -> np.ndarray:
    """Return error (% of path) of ``n`` simulated closed-loop foot walks (:mod:`hybridloc.sim`:
    a walker through a generated 3-floor building who returns to the start, the right foot's IMU at
    200 Hz, industrial grade, the 3DM-GX3-25 class). The INS starts at the true heading; the error is
    its end against the true end (the start, to the simulator's last stride), over the true path."""
    from ..sim.building import generate_world
    from ..sim.imu import foot_imu
    from ..sim.walker import simulate_walk

    world = generate_world(np.random.default_rng(5), 3, 5)
    out = np.zeros(n)
    for k in range(n):
        rng = np.random.default_rng(seed + k)
        walk = simulate_walk(world, rng, minutes, close_loop=True)
        imu, truth = foot_imu(walk, rng)
        res = run_foot_ins(imu, config, heading0=walk.steps[0].heading)
        d_est = res.pos_enu[-1, :2] - res.pos_enu[0, :2]
        d_true = truth.pos[-1, :2] - truth.pos[0, :2]
        path = float(np.linalg.norm(np.diff(truth.pos[:, :2], axis=0), axis=1).sum())
        out[k] = 100.0 * float(np.linalg.norm(d_est - d_true)) / path
    return out

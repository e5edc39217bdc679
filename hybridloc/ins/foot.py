"""Foot-mounted inertial navigation: the batch runner, DEDRIFT-I, and strides as StepEvents.

:func:`run_foot_ins` wraps the step API of :class:`~.eskf.ErrorStateEkf`: initial alignment from
the first still samples (roll, pitch from gravity; heading 0 unless given), then per sample a
strapdown prediction and, during stance, a zero-velocity update (and optionally a zero-angular-rate
update) through the one gated correction path. Each stride is then smoothed back from its stance
(:mod:`.smoother`, a Rauch-Tung-Striebel pass over the filter's own transitions): the ZUPT's
correction is carried over the swing it ends, instead of leaving the swing where the forward filter
drew it. Stance positions (and so strides) barely move; the per-sample track does (PyShoe VICON, 28
trials: mean 2-D ARMSE 0.0594 m forward, 0.0529 m smoothed). ``pos_enu_forward`` keeps the forward
track, which is what a live client has at each sample.

Which ZUPTs are vetted. A ZUPT normally goes in unconditionally: after a hard swing (walking,
running) the INS's velocity error exceeds what its covariance says, so a gate would veto true ZUPTs
and the filter would diverge (gating every ZUPT: 8 of 28 PyShoe trials diverge). Two kinds of stance
are doubtful, and for them the filter's own velocity is the better judge, so their ZUPTs pass the
chi-square gate (``vet``):

* the whole of a gentle gait (crawling, shuffling, slow short steps: :func:`.stance.swing_level`
  below :data:`.stance.GENTLE_SWING_LOG10`), where the detector calls stance while the foot still
  creeps, and the INS barely accelerates, so its covariance is right (crawl and slow-step trials
  2018-02-09-11-19-39 0.119 -> 0.043 m, 2018-02-22-10-10-29 0.160 -> 0.063 m);
* weak stances (:func:`.stance.weak_stance`, adaptive detector only): shallow dips of the SHOE
  statistic the adaptive test leaves out, true brief stances of a running foot mixed with a foot
  lifted slowly onto a stair. Inside a gentle gait they are left out: every stance there is vetted
  already, and adding the shallow ones let a crawl trial diverge when their test was widened.

PyShoe VICON, 28 trials, one setting: mean 2-D ARMSE 0.0702 m without vetting, 0.0626 with the
gentle gait vetted, 0.0594 with the weak stances too (weak-test window 0.8 or 1.2 s: 0.0598, 0.0600).

Bad input: NaN samples are skipped and counted; a time gap longer than ``max_gap`` s or a filter
that keeps rejecting ZUPTs (for ``reinit_after_s`` of stance in a row: it has diverged) re-initialises
velocity and tilt at the next stance, and the event is counted. The covariance is kept symmetric
positive definite by the Joseph form (tested).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..types import ImuBlock, StepEvent
from ..units import DEG, G0, wrap_angle
from . import stance as stance_mod
from .eskf import ErrorStateEkf, ImuNoise
from .hde import DriftEliminator, HdeConfig
from .measurements import Heading, StrideHeading, ZeroAngularRate, ZeroVelocity, ZeroYawRate
from .smoother import IntervalRts
from .strapdown import NominalState, level_from_accel, quat_to_dcm

#: Full scale unknown: identical readings on 3 samples beyond these are a clipped plateau (a foot
#: reaches 10 g at heel strike and 10 rad/s in the swing; a live signal does not repeat exactly there).
PLATEAU_ACCEL = 5.0 * G0
PLATEAU_GYRO = 5.0


#: Settings chosen held out for a sensor family, by name (``pdr foot --preset NAME``; explicit options
#: override them). "gait-driven": the MicroStrain 3DM-GX5-25 of the gait-driven walks, whose stance is
#: never still and whose statistic dips mid-swing: the robust detector, the vertical ZARU at 5 deg/s and
#: the demoted runs' ZUPTs gated, what ``eval pdr-foot`` chooses leaving one walk out and one session
#: out (in every fold: return error 0.65 % held out against 2.45 % with the defaults). The defaults are
#: PyShoe's sensor's (the 3DM-GX3-25): there the gate on demoted runs costs 0.0529 -> 0.0743 m ARMSE.
FOOT_PRESETS: dict[str, dict] = {
    "gait-driven": {"detector": "robust", "zaru_up_sigma": 5 * DEG, "vet_demoted": True},
}


@dataclass
class FootInsConfig:
    detector: str = "adaptive"  # one of stance.DETECTORS ("robust": adaptive's ZUPTs, strides cut at one stance per step)
    detector_threshold: float | None = None  # the chosen detector's threshold (units per stance.py)
    zupt_sigma: float = 0.01  # m/s
    gate_zupt: bool = False  # chi-square gate on every ZUPT (see the module docstring)
    vet: bool = True  # chi-square gate on the doubtful ZUPTs only: gentle gait, weak stances (module docstring)
    zaru: bool = True  # zero angular rate at stance: observes the gyro biases (heading drift over minutes)
    # vertical ZARU (measurements.ZeroYawRate) at every stance sample with an accepted ZUPT, its sigma in
    # rad/s, gated; None: off. ``eval pdr-foot`` chooses it on the gait-driven walks (FOOT_ZARU_UP_SIGMAS)
    zaru_up_sigma: float | None = None
    # "robust" detector: the ZUPTs of the runs not kept as a step's stance (mid-swing dips, fragments of a
    # rolling stance) go through the chi-square gate like weak stances; False: applied as any stance
    vet_demoted: bool = False
    gravity: float | None = None  # m/s^2; None: measured from the initial still period
    init_seconds: float = 0.5  # still period used for alignment (at most)
    max_gap: float = 0.1  # s
    reinit_after_s: float = 1.0  # s of stance with every ZUPT rejected before re-initialising
    smooth: bool = True  # RTS-smooth each stride back from its stance (smoother.py); the forward track is kept too
    min_swing: float = stance_mod.MIN_SWING_S  # s, the "robust" detector's shortest swing (stance.one_stance_per_step)
    min_stance: float = stance_mod.MIN_STANCE_S  # s, the "robust" detector's shortest stance of a step (the same)
    smooth_max_s: float = 2.0  # longest smoothing interval, s (a long standing still is cut into pieces)
    noise: ImuNoise = field(default_factory=ImuNoise)
    hde: HdeConfig | None = None  # heuristic drift elimination (hde.py): straight strides measured as a dominant direction; None: off


@dataclass
class FootInsResult:
    t: np.ndarray
    pos_enu: np.ndarray  # (N, 3), starting at the origin
    vel_enu: np.ndarray
    quat_wxyz: np.ndarray
    sigma_pos: np.ndarray  # (N, 3)
    stance: np.ndarray  # (N,) bool
    P_pos: np.ndarray  # (N, 3, 3) position covariance (the forward filter's: an upper bound when smoothed)
    stats: dict
    pos_enu_forward: np.ndarray | None = None  # (N, 3) the forward filter's positions when ``pos_enu`` is smoothed
    step_stance: np.ndarray | None = None  # (N,) bool, one stance per step ("robust" detector): what :func:`strides` cuts at


def detect_stance(
    imu: ImuBlock,
    detector: str,
    threshold: float | None,
    g: float,
    min_swing: float = stance_mod.MIN_SWING_S,
    min_stance: float = stance_mod.MIN_STANCE_S,
) -> np.ndarray:
    """The stance mask of ``detector`` (one of stance.DETECTORS). For "robust" it is the one stance
    per step that strides are cut at (``min_swing`` / ``min_stance`` as in FootInsConfig); the filter
    itself applies the adaptive mask's ZUPTs (:func:`run_foot_ins`)."""
    a, w = imu.accel_body, imu.gyro_body
    if detector in ("adaptive", "robust"):
        T, m = stance_mod.adaptive_shoe(a, w, imu.rate_hz, g=g, **({"decades": threshold} if threshold else {}))
        return stance_mod.one_stance_per_step(m, T, imu.rate_hz, min_swing, min_stance)[0] if detector == "robust" else m
    if detector == "shoe":
        return stance_mod.shoe(a, w, threshold or 2e7, g=g)[1]
    if detector == "ared":
        return stance_mod.ared(w, threshold or 0.1)[1]
    if detector == "amvd":
        return stance_mod.amvd(a, threshold or 0.05, g=g)[1]
    if detector == "mbgtd":
        return stance_mod.gyro_minimum(w, threshold or math.radians(60), n=max(1, int(0.5 * imu.rate_hz)))[1]
    raise ValueError(f"unknown stance detector {detector!r}; choose one of {stance_mod.DETECTORS}")


def still_prefix(imu: ImuBlock, max_seconds: float) -> int:
    """Number of leading samples (at least 2, at most ``max_seconds``) before the unit first moves:
    |omega| < 0.2 rad/s and |a| within 0.3 m/s^2 of its median over the first 10 samples."""
    n_max = max(2, min(int(max_seconds * imu.rate_hz), len(imu)))
    a = np.linalg.norm(imu.accel_body[:n_max], axis=1)
    w = np.linalg.norm(imu.gyro_body[:n_max], axis=1)
    a0 = float(np.median(a[:10]))
    moving = np.flatnonzero((w >= 0.2) | (np.abs(a - a0) >= 0.3) | ~np.isfinite(a))
    return max(2, int(moving[0]) if moving.size else n_max)


def _initial_state(imu: ImuBlock, n_init: int, heading: float) -> tuple[NominalState, float]:
    f0 = np.nanmean(imu.accel_body[:n_init], axis=0)
    q0 = level_from_accel(f0, heading)
    return NominalState(np.zeros(3), np.zeros(3), q0, np.zeros(3), np.zeros(3)), float(np.linalg.norm(f0))


def run_foot_ins(
    imu: ImuBlock, config: FootInsConfig | None = None, stance: np.ndarray | None = None, heading0: float = 0.0, doubtful: np.ndarray | None = None
) -> FootInsResult:
    """Run the ZUPT-aided error-state EKF over a whole recording (``stance`` overrides the detector).

    ``doubtful`` (N,) bool: samples whose stance is in doubt whatever the detector says: they are taken
    as stance, and their ZUPTs go through the chi-square gate (the filter's own velocity decides), like
    the vetted ones (module docstring)."""
    cfg = config or FootInsConfig()
    n = len(imu)
    if n < 10:
        raise ValueError("too few IMU samples for a foot INS")
    acc, gyr, t = imu.accel_body, imu.gyro_body, imu.t
    finite = np.all(np.isfinite(acc), axis=1) & np.all(np.isfinite(gyr), axis=1)
    # Clipped readings: the specific force or rate was larger than read, by an unknown amount. They are
    # counted and reported, and used as read: giving their velocity / attitude step the variance of a
    # miss of half the reading made the simulated walks worse (a foot IMU clipped at 2.5 g: 3.2 -> 4.2 %
    # of the path; at 4 rad/s: 21 -> 56 %), the ZUPT then spreading the miss into heading.
    sat_a, sat_g = imu.saturated(PLATEAU_ACCEL, PLATEAU_GYRO)
    rate = imu.rate_hz
    x0, g_meas = _initial_state(imu, still_prefix(imu, cfg.init_seconds), heading0)
    g = cfg.gravity or g_meas
    T = None  # the SHOE statistic, needed by the adaptive detector and by the vetting only
    adaptive = cfg.detector in ("adaptive", "robust")
    if cfg.vet or (stance is None and adaptive):
        with np.errstate(invalid="ignore", divide="ignore"):
            # a NaN sample counts as a hard swing: nothing is vetted or called stance on its account
            T = np.nan_to_num(stance_mod.shoe(acc, gyr, np.inf, g=g)[0], nan=np.inf)
    weak = np.zeros(n, bool)
    step_stance = None
    if stance is None:
        if adaptive:
            stance = stance_mod.adaptive_mask(T, rate, **({"decades": cfg.detector_threshold} if cfg.detector_threshold else {}))
            if cfg.detector == "robust":
                # the ZUPTs stay the adaptive detector's; only the strides are cut at one stance per
                # step. Vetting the demoted runs' ZUPTs instead (``vet_demoted``: through the gate, like
                # weak stances) cost PyShoe VICON 0.0529 -> 0.0635 m mean ARMSE (one running trial 0.055 ->
                # 0.258 m; 0.0743 m since the shortest stance demotes its brief running stances too), so it
                # is off; eval pdr-foot chooses it with the vertical ZARU on the gait-driven walks (5 deg/s
                # with it in every fold since the shortest stance: return error held out 0.65 %)
                step_stance, demoted = stance_mod.one_stance_per_step(stance, T, rate, cfg.min_swing, cfg.min_stance)
                step_stance &= finite
            if cfg.vet:
                weak = stance_mod.weak_stance(T, rate, stance)
                if cfg.detector == "robust" and cfg.vet_demoted:
                    weak |= demoted
        else:
            stance = detect_stance(imu, cfg.detector, cfg.detector_threshold, g)
    gentle = stance_mod.swing_level(T, rate) < stance_mod.GENTLE_SWING_LOG10 if cfg.vet else np.zeros(n, bool)
    weak &= ~gentle
    if doubtful is not None:
        weak = weak | np.asarray(doubtful, bool)
    stance = (np.asarray(stance, bool) | weak) & finite
    gate = gentle | weak | cfg.gate_zupt
    reinit_after = max(1, int(round(cfg.reinit_after_s * rate)))
    nz = cfg.noise
    P0 = np.diag(
        [1e-8] * 3
        + [1e-6] * 3
        + [(0.5 * math.pi / 180) ** 2] * 2
        + [(0.1 * math.pi / 180) ** 2]
        + [nz.accel_bias_sigma0**2] * 3
        + [nz.gyro_bias_sigma0**2] * 3
    )
    P0[8, 8] = 1e-10  # heading is defined as heading0: no uncertainty at the start
    if cfg.hde is not None and cfg.hde.bias_sigma0_up is not None:
        # the gyro bias's vertical component (body frame: along gravity at the start) gets its own prior:
        # sigma0^2 I + (sigma_up^2 - sigma0^2) u u^T
        u = x0.R.T @ np.array([0.0, 0.0, 1.0])
        P0[12:15, 12:15] += (cfg.hde.bias_sigma0_up**2 - nz.gyro_bias_sigma0**2) * np.outer(u, u)
    kf = ErrorStateEkf(x0, P0, nz, g)
    zupt = ZeroVelocity(cfg.zupt_sigma)
    zaru = ZeroAngularRate(np.zeros(3))
    zaru_up = ZeroYawRate(np.zeros(3), np.array([0.0, 0.0, 1.0]), cfg.zaru_up_sigma) if cfg.zaru_up_sigma is not None else None
    zero1 = np.zeros(1)
    hde = DriftEliminator(cfg.hde) if cfg.hde is not None else None
    if hde is not None:
        # the foot's heading is that of the body axis most level at the start (x or y), made level there
        up = acc[: still_prefix(imu, cfg.init_seconds)].mean(axis=0)
        up = up / np.linalg.norm(up)
        ax = np.eye(3)[int(np.argmin(np.abs(up[:2])))]
        ax = ax - (ax @ up) * up
        foot_heading = Heading(ax / np.linalg.norm(ax))
        stride_heading = StrideHeading(foot_heading.axis, cfg.hde.sigma)
    pos = np.zeros((n, 3))
    vel = np.zeros((n, 3))
    quat = np.zeros((n, 4))
    Ppos = np.zeros((n, 3, 3))
    quat[0] = x0.q
    Ppos[0] = kf.P[:3, :3]
    stats = {
        "nan_samples": int((~finite).sum()),
        "saturated_samples": int((sat_a | sat_g).sum()),
        "gaps": 0,
        "zupt_rejected": 0,
        "reinit": 0,
        "stance_samples": int(stance.sum()),
        "vetted_samples": int((gate & stance).sum()),
        "weak_samples": int(weak.sum()),
    }
    rejected_run = 0
    reinit_pending = False
    last_i = 0
    zero3 = np.zeros(3)
    zero15 = np.zeros(15)
    rts = IntervalRts(0) if cfg.smooth else None
    smooth_max = max(2, int(cfg.smooth_max_s * rate))
    e_smooth = np.zeros((n, 6)) if cfg.smooth else None  # smoothed (dp, dv) per sample

    def smooth_back() -> None:
        idx, e = rts.flush()
        e_smooth[idx] = e[:, :6]

    # per-sample flags and times as Python lists: indexing them costs a tenth of indexing arrays
    finite_l, stance_l, gate_l, t_l = finite.tolist(), stance.tolist(), gate.tolist(), t.tolist()
    for i in range(1, n):
        if not finite_l[i]:
            pos[i], vel[i], quat[i], Ppos[i] = pos[i - 1], vel[i - 1], quat[i - 1], Ppos[i - 1]
            continue
        dt = t_l[i] - t_l[last_i]
        broken = i - last_i > 1  # no smoothing across this transition (skipped NaN, gap, re-initialisation)
        last_i = i
        if dt > cfg.max_gap:
            stats["gaps"] += 1
            reinit_pending = True
            broken = True
            dt = 1.0 / rate  # propagate one nominal step; the state is re-levelled at the next stance
        P_prev = kf.P
        kf.predict(acc[i], gyr[i], dt)
        P_pred = kf.P
        dx = zero15
        if stance_l[i]:
            if reinit_pending:
                broken = True
                # Re-initialise: zero velocity, tilt from gravity, keep position and heading.
                R = quat_to_dcm(kf.x.q)
                fwd = R[:, 0]
                q = level_from_accel(acc[i], math.atan2(fwd[1], fwd[0]))
                kf.x = NominalState(kf.x.p.copy(), zero3.copy(), q, kf.x.b_a.copy(), kf.x.b_g.copy())
                kf.P[3:9, :] = 0.0
                kf.P[:, 3:9] = 0.0
                kf.P[3:6, 3:6] = np.eye(3) * 1e-4
                kf.P[6:9, 6:9] = np.diag([1e-4, 1e-4, 1e-2])
                stats["reinit"] += 1
                reinit_pending = False
                rejected_run = 0
            c = kf.correct(zupt, zero3, gate=gate_l[i])
            if c.accepted:
                dx = c.dx
                rejected_run = 0
            else:
                stats["zupt_rejected"] += 1
                rejected_run += 1
                if rejected_run >= reinit_after:
                    reinit_pending = True
            if zaru_up is not None and c.accepted:  # before the 3-D ZARU, whose gate the rolling foot trips
                zaru_up.omega, zaru_up.up_body = gyr[i], kf.x.R[2]
                cu = kf.correct(zaru_up, zero1)
                if cu.accepted:
                    dx = dx + cu.dx
            if cfg.zaru and c.accepted:  # a vetoed stance is no stance: no zero angular rate either
                zaru.omega = gyr[i]  # one model, its reading updated (no per-sample construction)
                cz = kf.correct(zaru, zero3)
                if cz.accepted:
                    dx = dx + cz.dx  # the two corrections add to first order
            if hde is not None and c.accepted and (i + 1 == n or not stance_l[i + 1]):  # the stance's last sample: a stride may end here
                got = hde.stride_end(kf.x.p)
                if got is not None:
                    z_dom, psi = got
                    # h = foot heading + (stride heading - foot heading) now: the innovation is z_dom - psi
                    stride_heading.offset = psi - float(foot_heading.evaluate(kf.x)[0])
                    ch = kf.correct(stride_heading, np.array([z_dom]))
                    if ch.accepted:
                        dx = dx + ch.dx
        if rts is not None:
            if broken:
                smooth_back()
                rts.restart(i)
            else:
                if stance_l[i - 1] and not stance_l[i]:  # a stance just ended: smooth the stride back from it
                    smooth_back()
                rts.add(i, kf.transition, P_prev, P_pred, dx)
                if len(rts) >= smooth_max:
                    smooth_back()
        pos[i], vel[i], quat[i] = kf.x.p, kf.x.v, kf.x.q
        Ppos[i] = kf.P[:3, :3]
    pos_forward = None
    if rts is not None:
        smooth_back()
        pos_forward = pos.copy()
        pos += e_smooth[:, :3]
        vel += e_smooth[:, 3:6]
    sig = np.sqrt(np.clip(np.einsum("nii->ni", Ppos), 0.0, None))
    stats["P_min_eig"] = float(np.linalg.eigvalsh(kf.P).min())
    stats["P_asym"] = float(np.abs(kf.P - kf.P.T).max())
    if hde is not None:
        stats["hde_strides"], stats["hde_straight"], stats["hde_measured"] = hde.n_strides, hde.n_straight, hde.n_measured
        stats["hde_accepted"] = kf.stats.accepted.get("hde", 0)
        stats["hde_grid"] = hde.grid
    return FootInsResult(t.copy(), pos, vel, quat, sig, stance, Ppos, stats, pos_forward, step_stance)


def dedrift_i(imu: ImuBlock, stance_instants: np.ndarray, g: float | None = None, heading0: float = 0.0) -> np.ndarray:
    """Ojeda & Borenstein's DEDRIFT-I: plain strapdown with velocity reset and acceleration de-drifting.

    At each stance instant T_s (one per step, e.g. from :func:`~.stance.gyro_minimum`) the foot is
    at rest: the velocity is reset to zero, and the nav-frame acceleration read there (which should
    be zero) is taken as drift and subtracted from the following samples. No filter, no covariance.
    Returns positions (N, 3).
    """
    from .strapdown import mechanise

    n = len(imu)
    x, g_meas = _initial_state(imu, still_prefix(imu, 0.5), heading0)
    g = g or g_meas
    drift = np.zeros(3)
    pos = np.zeros((n, 3))
    acc, gyr, t = imu.accel_body, imu.gyro_body, imu.t
    for i in range(1, n):
        dt = t[i] - t[i - 1]
        R = quat_to_dcm(x.q)
        f = acc[i] - R.T @ drift  # remove the nav-frame drift measured at the last stance
        x = mechanise(x, f, gyr[i], dt, g)
        if stance_instants[i]:
            a_nav = quat_to_dcm(x.q) @ acc[i]
            a_nav[2] -= g
            drift = a_nav
            x.v = np.zeros(3)
        pos[i] = x.p
    return pos


#: A stride shorter than this (horizontal, m) is shuffling in place, not a stride.
MIN_STRIDE_M = 0.05


def stance_points(res: FootInsResult) -> list[int]:
    """Sample index of the foot's footprint at each step: the middle of each stance run (of
    ``res.step_stance`` when the detector gives one stance per step, else of ``res.stance``), runs of
    one sample left out; a footprint less than :data:`MIN_STRIDE_M` from the one before is shuffling
    in place, not a step. Footprint 0 is the start; footprint k is where stride k of :func:`strides`
    ends (one more footprint than strides)."""
    mids = _stance_mids(res)
    return mids[:1] + [b for a, b in zip(mids[:-1], mids[1:]) if _horizontal(res, a, b) >= MIN_STRIDE_M]


def _stance_mids(res: FootInsResult) -> list[int]:
    mask = res.stance if res.step_stance is None else res.step_stance
    starts, ends = stance_mod.stance_runs(mask)
    return [(s + e - 1) // 2 for s, e in zip(starts, ends) if e - s >= 2]


def _horizontal(res: FootInsResult, a: int, b: int) -> float:
    d = res.pos_enu[b] - res.pos_enu[a]
    return float(math.hypot(d[0], d[1]))


def strides(res: FootInsResult) -> list[StepEvent]:
    """Slice the trajectory into strides: one StepEvent per stance phase after the first.

    A stride runs from the middle of one stance phase to the middle of the next; its length and
    heading are those of the horizontal displacement, its height change the vertical one. The
    uncertainties come from the filter's position covariance at the two ends (their difference is
    the uncertainty the stride added, Kourogi eq 13 read backwards), projected along and across the
    stride direction.
    """
    mids = _stance_mids(res)
    out: list[StepEvent] = []
    prev_heading = None
    for a, b in zip(mids[:-1], mids[1:]):
        d = res.pos_enu[b] - res.pos_enu[a]
        L = float(math.hypot(d[0], d[1]))
        if L < MIN_STRIDE_M:  # shuffling in place: not a stride
            continue
        psi = math.atan2(d[1], d[0])
        u = np.array([math.cos(psi), math.sin(psi)])
        v = np.array([-u[1], u[0]])
        dC = res.P_pos[b][:2, :2] - res.P_pos[a][:2, :2]
        var_l = max(float(u @ dC @ u), 1e-6)
        var_c = max(float(v @ dC @ v), 1e-6)
        sig_h = math.atan2(math.sqrt(var_c), L)
        dz_var = max(float(res.P_pos[b][2, 2] - res.P_pos[a][2, 2]), 1e-6)
        out.append(
            StepEvent(
                t=float(res.t[b]),
                length=L,
                heading=psi,
                sigma_length=math.sqrt(var_l),
                sigma_heading=sig_h,
                heading_change=None if prev_heading is None else wrap_angle(psi - prev_heading),
                sigma_heading_change=None if prev_heading is None else math.sqrt(2) * sig_h,
                height_change=float(d[2]),
                sigma_height_change=math.sqrt(dz_var),
            )
        )
        prev_heading = psi
    return out

"""Smartphone step-and-heading PDR: samples in, :class:`~hybridloc.types.StepEvent` out.

Pipeline per sample (streaming: :meth:`PhonePdr.update` gives the same steps whether the data come
in one block or one sample at a time):

1. Attitude and heading (:mod:`.attitude`): gravity-aligned heading change whatever the phone's
   orientation, magnetometer yaw correction only while the field is clean.
2. |a| low-passed by a causal 2nd-order Butterworth (3 Hz: walking's step band is 1.4-2.5 Hz).
3. Step candidates, one of two detector families (Harle's survey sec. III):
   * ``"peak"``: local maxima of the filtered magnitude above an adaptive threshold (running mean
     + ``k_sigma`` running std, and at least ``min_swing`` above the last valley), at least
     ``min_step_interval`` apart;
   * ``"autocorr"``: step-cycle detection from the normalised auto-correlation (Zee's NASC): the
     step period tau* maximising NASC gates local maxima at least 0.6 tau* apart, without amplitude
     thresholds.
4. Walking classifier (both families): a candidate counts only while the signal is periodic (max
   NASC over one-step lags >= ``nasc_walking``, for ``confirm_candidates`` consecutive candidates
   whose periods agree within ``period_tolerance``) and not idle (std >= ``idle_std``). Standing,
   fidgeting and handling give no steps. Candidates seen while the classifier was still warming
   up are released retroactively once it confirms walking, so the first steps of a walk are kept.
5. Step length (:mod:`.steplength`) and heading = forward heading (circular mean over the step)
   + walking offset (device heading vs walking direction; 0 for a phone held in front).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from ..types import SATURATION_REPEATS, SATURATION_SHARE, ImuBlock, StepEvent, Trajectory
from ..units import DEG, G0, wrap_angle
from .attitude import AttitudeConfig, AttitudeFilter
from .deadreckoning import DeadReckoning
from .steplength import BounceHeightLength, LengthModel, StepFeatures

#: a one-step NASC peak at least this share of the best (stride) peak is taken as the period
STEP_PEAK_SHARE = 0.85


@dataclass
class PhonePdrConfig:
    detector: str = "peak"  # "peak" | "autocorr"
    lowpass_hz: float = 3.0
    min_step_interval: float = 0.28  # s (fastest walking ~3.5 steps/s)
    max_step_interval: float = 1.6  # s; a longer pause starts a new walk
    k_sigma: float = 0.4  # adaptive threshold: running mean + k_sigma * running std
    min_swing: float = 0.8  # m/s^2 from the previous valley to the peak
    idle_std: float = 0.35  # m/s^2; below this the phone is still
    nasc_walking: float = 0.55  # Zee et al. use ~0.7 on raw data; ours is low-passed and per-step
    nasc_window: float = 2.4  # s of signal for the auto-correlation
    nasc_min_window: float = 1.2  # s of signal needed before the first auto-correlation (after a start or gap)
    period_tolerance: float = 0.15  # relative change of the step period between candidates still "walking"
    min_vertical_share: float = 0.6  # vertical share of dynamic acceleration variance while walking
    confirm_candidates: int = 3  # consecutive periodic candidates with a consistent period to start walking
    release_tolerance: float = 0.5  # held-back candidate released if its gap to the next is the period within this share...
    release_vertical_share: float = 0.7  # ... or if the vertical share of its acceleration is at least this
    step_lag_range: tuple[float, float] = (0.3, 1.0)  # s, one step
    walking_offset: float = 0.0  # rad, walking direction minus device forward heading
    estimate_offset: bool = False  # estimate the offset from the gait's horizontal acceleration (see _update_offset)
    offset_gain: float = 0.1  # per step, of the running circular mean of the walking direction
    offset_prior_steps: float = 3.0  # weight of ``walking_offset`` at the start, in (clear) steps
    #: how the walking axis's 180 deg ambiguity is resolved: "gait" (the forward acceleration rises with
    #: the vertical) or "continuity" (the half nearer the current offset: the common textbook way,
    #: kept to measure against; a wrong start stays wrong)
    offset_sign: str = "gait"
    sigma_mag_heading: float = 12.0 * DEG  # absolute heading from a clean indoor magnetometer
    gyro_drift: float = 0.2 * DEG  # rad/s growth of heading uncertainty without the magnetometer
    sigma_offset: float = 5.0 * DEG
    sigma_turn_floor: float = 1.0 * DEG  # per-step heading-change noise
    turn_scale_sigma: float = 0.03  # relative (gyro scale factor) heading-change error
    attitude: AttitudeConfig = field(default_factory=AttitudeConfig)


#: Full scale unknown: identical readings of an axis on SATURATION_REPEATS consecutive samples beyond a
#: walking phone's plausible range (3 g; 6 rad/s, a brisk turn of the wrist) are a clipped plateau,
#: as :meth:`ImuBlock.saturated <hybridloc.types.ImuBlock.saturated>` decides for a whole block.
PLATEAU_ACCEL = 3.0 * G0
PLATEAU_GYRO = 6.0


@dataclass
class PdrStats:
    samples: int = 0
    rejected_samples: dict = field(default_factory=dict)
    candidates: int = 0
    steps: int = 0
    gaps: int = 0
    saturated: int = 0  # samples with a reading at the sensor's full scale (kept, flagged)

    def reject(self, reason: str) -> None:
        self.rejected_samples[reason] = self.rejected_samples.get(reason, 0) + 1


class PhonePdr:
    """Streaming step-and-heading PDR for one phone."""

    def __init__(
        self,
        rate_hz: float,
        length_model: LengthModel | None = None,
        config: PhonePdrConfig | None = None,
        heading0: float | None = None,
        accel_range: float | None = None,
        gyro_range: float | None = None,
    ):
        """``accel_range``, ``gyro_range``: the sensors' full scale (m/s^2, rad/s) when known
        (:meth:`process` takes them from the IMU block); see :meth:`_saturation`."""
        if not (5.0 <= rate_hz <= 1000.0):
            raise ValueError(f"phone IMU rate {rate_hz} Hz is implausible (expected 5-1000 Hz)")
        if config is not None and config.detector not in ("peak", "autocorr"):
            raise ValueError(f"unknown step detector {config.detector!r}")
        if config is not None and config.offset_sign not in ("gait", "continuity"):
            raise ValueError(f"unknown walking-offset sign rule {config.offset_sign!r}; choose gait or continuity")
        self.cfg = config or PhonePdrConfig()
        self.rate = rate_hz
        self.model = length_model or BounceHeightLength()
        self.att = AttitudeFilter(self.cfg.attitude)
        b, a = signal.butter(2, self.cfg.lowpass_hz / (rate_hz / 2.0))
        self._b, self._a = b.tolist(), a.tolist()
        self._zi = None
        self.stats = PdrStats()
        # History long enough to release every candidate held while walking was being confirmed.
        self._retain = self.cfg.nasc_window + self.cfg.confirm_candidates * self.cfg.step_lag_range[1]
        n_hist = int(round((self._retain + self.cfg.max_step_interval + 0.5) * rate_hz))
        # per-sample history: (t, filtered |a|, vertical accel, cos fwd, sin fwd, ax_h, ay_h)
        self._hist: deque = deque(maxlen=n_hist)
        self._y1 = self._y2 = None  # previous two filtered values (for local maxima)
        self._t1 = None
        self._mean = None
        self._var = 0.0
        self._mean_fast = None
        self._var_fast = 0.0
        self._valley = math.inf
        self._last_step_t: float | None = None
        self._last_cand_t: float | None = None
        self._pending: list[float] = []
        self._prev_periodic_lag: float | None = None
        self._walking = False
        self._consistent = 0
        self._last_t: float | None = None
        self._prev_heading: float | None = None
        self._heading0 = heading0  # if set, output headings are relative: heading0 + (psi - psi_first)
        self._yaw_ref: float | None = None
        self._mag_clean_t: float | None = None
        self._degraded_next = ""
        self._period = 0.55
        self._offset = self.cfg.walking_offset
        # weighted sum of unit vectors of the per-step offsets (the prior counts as a few clear steps)
        self._offset_sum = complex(math.cos(self._offset), math.sin(self._offset)) * self.cfg.offset_gain * self.cfg.offset_prior_steps
        self.accel_range, self.gyro_range = accel_range, gyro_range
        self._plateau = [[0, 0, 0], [0, 0, 0]]  # per axis, consecutive identical extreme readings (accelerometer, gyroscope)
        self._prev_raw: tuple | None = None
        self._sat_angle = 0.0  # rad: how far the clipped gyro readings may have left the heading off
        self.steps: list[StepEvent] = []
        #: The features behind each emitted step (same order as ``steps``), for length calibration.
        self.features: list[StepFeatures] = []

    # ------------------------------------------------------------------
    def update(self, t: float, acc, gyr, mag=None) -> list[StepEvent]:
        """Feed one sample (s, m/s^2, rad/s, T or None); returns the steps it completed."""
        # one sum is finite when every term is (and almost always is): the per-value test only on a miss
        if not math.isfinite(t + acc[0] + acc[1] + acc[2] + gyr[0] + gyr[1] + gyr[2]) and not (
            math.isfinite(t) and all(map(math.isfinite, acc)) and all(map(math.isfinite, gyr))
        ):
            self.stats.reject("non-finite")
            return []
        if mag is not None and not math.isfinite(mag[0] + mag[1] + mag[2]) and not all(map(math.isfinite, mag)):
            mag = None
        if self._last_t is not None:
            dt = t - self._last_t
            if dt <= 0:
                self.stats.reject("not-increasing-time")
                return []
            if dt > self.cfg.max_step_interval:
                # A gap: whatever was in progress is lost; restart detection, keep attitude.
                self.stats.gaps += 1
                self._reset_detection()
                self._degraded_next = "gap"
        self._saturation(t, acc, gyr)
        self._last_t = t
        self.stats.samples += 1
        att = self.att
        att.update(t, acc, gyr, mag)
        if att.mag_ok:
            self._mag_clean_t = t
        amag = math.sqrt(acc[0] * acc[0] + acc[1] * acc[1] + acc[2] * acc[2])
        # causal biquad (direct form II transposed), state carried across calls
        if self._zi is None:
            self._zi = [amag * v for v in signal.lfilter_zi(self._b, self._a).tolist()]
        b, a, z = self._b, self._a, self._zi
        y = b[0] * amag + z[0]
        z[0] = b[1] * amag - a[1] * y + z[1]
        z[1] = b[2] * amag - a[2] * y
        # the attitude's forward heading, and the specific force in nav (horizontal; vertical minus g):
        # AttitudeFilter.forward_heading / horizontal_accel / vertical_accel on its R, written out once
        R = att.R
        r0, r1, r2 = R[0], R[1], R[2]
        fwd = math.atan2(r1[1] - r1[2], r0[1] - r0[2])
        self._hist.append(
            (
                t,
                y,
                r2[0] * acc[0] + r2[1] * acc[1] + r2[2] * acc[2] - G0,
                math.cos(fwd),
                math.sin(fwd),
                r0[0] * acc[0] + r0[1] * acc[1] + r0[2] * acc[2],
                r1[0] * acc[0] + r1[1] * acc[1] + r1[2] * acc[2],
            )
        )
        # running mean / variance over ~2 s (exponential)
        alpha = 1.0 / (2.0 * self.rate)
        if self._mean is None:
            # Start from g, the mean of |a| for a carried phone, not from the first sample: a recording
            # that starts mid-step would otherwise hold the threshold above the bounces for seconds
            # (ILC site1: walks starting with the recording lost their first 4-5 steps).
            self._mean = G0
        d = y - self._mean
        self._mean += alpha * d
        self._var = (1 - alpha) * (self._var + alpha * d * d)
        # a fast one (0.5 s) for the idle test, so the first steps after standing are not "still"
        af = 4.0 * alpha
        if self._mean_fast is None:
            self._mean_fast = y
        df = y - self._mean_fast
        self._mean_fast += af * df
        self._var_fast = (1 - af) * (self._var_fast + af * df * df)
        out: list[StepEvent] = []
        if self._y1 is not None and self._y2 is not None:
            if self._y1 < self._y2 and self._y1 <= y:
                self._valley = min(self._valley, self._y1)
            if self._y1 > self._y2 and self._y1 >= y:
                out = self._candidate(self._t1, self._y1)
        self._y2, self._y1, self._t1 = self._y1, y, t
        return out

    def _reset_detection(self) -> None:
        self._pending.clear()
        self._prev_periodic_lag = None
        self._walking = False
        self._consistent = 0
        self._last_step_t = None
        self._last_cand_t = None
        self._valley = math.inf
        self._hist.clear()
        self._prev_heading = None

    # ------------------------------------------------------------------
    def _nasc(self) -> tuple[float, float]:
        """Periodicity of the recent signal: (max NASC over one-step lags, that lag in s).

        NASC(m) = <x[:-m], x[m:]> / (|x[:-m]| |x[m:]|) (Zee's normalised auto-correlation). A smooth
        but aperiodic signal (a phone being handled) also correlates at short lags, so the peak
        counts only after the auto-correlation has first swung negative: that is, the signal really
        oscillates, and the peak is one cycle later.
        """
        # The window fills in nasc_window seconds after a start or a gap; until then the signal so far
        # is used once it spans nasc_min_window (at least two steps at the slowest walking lag that
        # fits, lag <= n / 2), so a walk that starts with the recording is recognised within ~2 s.
        n = min(int(self.cfg.nasc_window * self.rate), len(self._hist))
        if n < int(self.cfg.nasc_min_window * self.rate):
            return 0.0, self._period
        x = np.fromiter((h[1] for h in list(self._hist)[-n:]), float, n)
        x = x - x.mean()
        lo = max(1, int(self.cfg.step_lag_range[0] * self.rate))
        hi = min(int(self.cfg.step_lag_range[1] * self.rate), n // 2)
        full = np.correlate(x, x, mode="full")[n - 1 : n + hi]  # lags 0..hi
        cs = np.concatenate([[0.0], np.cumsum(x * x)])
        m = np.arange(1, hi + 1)
        den = np.sqrt(cs[n - m] * (cs[n] - cs[m]))
        r = np.where(den > 0, full[1:] / np.where(den > 0, den, 1.0), 0.0)  # r[m-1] = NASC(m)
        neg = np.flatnonzero(r < 0)
        if neg.size == 0:
            return 0.0, self._period
        start = max(lo, int(neg[0]) + 1)
        if start > hi:
            return 0.0, self._period
        seg = r[start - 1 : hi]
        kbest = int(np.argmax(seg))
        # The step, not the stride: a phone in the hand sees left and right steps differ, so the
        # two-step lag often correlates as well as (or better than) the one-step lag, and the "period"
        # would jump between them from one window to the next. Take the earliest local maximum nearly
        # as strong as the best one (Zee's NASC keeps step and stride apart the same way).
        for i in range(1, kbest):
            if seg[i] >= seg[i - 1] and seg[i] >= seg[i + 1] and seg[i] >= STEP_PEAK_SHARE * seg[kbest]:
                kbest = i
                break
        k = start - 1 + kbest
        return float(r[k]), (k + 1) / self.rate

    def _vertical_share(self) -> float:
        """Share of the vertical in the dynamic acceleration variance over the last ~1.5 s."""
        n = int(1.5 * self.rate)
        h = list(self._hist)[-n:]
        if len(h) < 10:
            return 0.0
        v = np.var([x[2] for x in h])
        hz = np.var([x[5] for x in h]) + np.var([x[6] for x in h])
        return float(v / (v + hz)) if v + hz > 0 else 0.0

    def _candidate(self, tp: float, yp: float) -> list[StepEvent]:
        cfg = self.cfg
        std = math.sqrt(self._var)
        if math.sqrt(max(self._var, self._var_fast)) < cfg.idle_std:
            self._valley = math.inf
            return []
        if cfg.detector == "peak":
            if yp < self._mean + cfg.k_sigma * std or yp - self._valley < cfg.min_swing:
                return []
            min_dt = cfg.min_step_interval
        else:  # autocorr: spacing from the step period only
            min_dt = max(cfg.min_step_interval * 0.8, 0.6 * self._period)
            if yp < self._mean:
                return []
        if self._last_cand_t is not None and tp - self._last_cand_t < min_dt:
            return []
        self.stats.candidates += 1
        self._last_cand_t = tp
        self._valley = math.inf
        nasc, lag = self._nasc()
        # Walking = periodic now AND at the previous candidate with a consistent period: a handled
        # phone can look periodic for one window, but its "period" jumps from one window to the next.
        # And walking bounces the body: the vertical (gravity-aligned) acceleration must carry a
        # good share of the dynamic acceleration; a phone turned in the hand shakes every axis.
        vshare = self._vertical_share()
        periodic = nasc >= cfg.nasc_walking and vshare >= cfg.min_vertical_share
        prev = self._prev_periodic_lag
        if periodic and prev is not None and abs(lag - prev) <= cfg.period_tolerance * lag:
            self._consistent += 1
        else:
            self._consistent = 1 if periodic else 0
        walking = periodic and (self._walking or self._consistent >= cfg.confirm_candidates)
        self._prev_periodic_lag = lag if periodic else None
        self._walking = walking
        if not walking:
            self._pending = [(p, vs) for p, vs in self._pending if tp - p <= self._retain] + [(tp, vshare)]
            return []
        self._period = lag
        # The candidates held back while walking was being confirmed are steps if they lead up to this
        # one like walking: counted back from here, each either a period after the one before it
        # (gap within ``release_tolerance`` of the period) or with the body bouncing as in walking
        # (vertical share, as for "periodic" above); the first that is neither ends the walk's start.
        # A phone handled just before walking off leaves irregular candidates that shook every axis:
        # on simulated walks every false step while handling was one of those (released with the
        # walk's first steps). Chosen on simulator seeds 1-4 and ILC site1, checked on fresh seeds
        # 5-7: false steps handling 3.7 -> 0.12/min, count error -0.2 to -0.4 %; ILC segment length
        # and waypoint errors unchanged (a strict period chain alone dropped real first steps there).
        held = [(p, vs) for p, vs in self._pending if tp - p <= self._retain and (self._last_step_t is None or p > self._last_step_t)]
        released: list[float] = []
        nxt = tp
        for p, vs in reversed(held):
            if abs((nxt - p) - lag) > cfg.release_tolerance * lag and vs < cfg.release_vertical_share:
                break
            released.append(p)
            nxt = p
        released.reverse()
        self._pending = []
        out = []
        for ts in released + [tp]:
            ev = self._emit(ts)
            if ev is not None:
                out.append(ev)
        return out

    def _emit(self, ts: float) -> StepEvent | None:
        cfg = self.cfg
        t_prev = self._last_step_t
        if t_prev is None or ts - t_prev > cfg.max_step_interval:
            t_prev = ts - self._period
        dur = ts - t_prev
        if dur <= 0:
            return None
        seg = [h for h in self._hist if t_prev < h[0] <= ts]
        if not seg:
            return None
        av = [h[2] for h in seg]
        c = sum(h[3] for h in seg)
        s = sum(h[4] for h in seg)
        fwd = math.atan2(s, c)
        if cfg.estimate_offset and len(seg) >= 5:
            self._update_offset(seg, fwd)
        psi = wrap_angle(fwd + self._offset)
        feats = StepFeatures(dur, max(av) - min(av), sum(abs(v) for v in av) / len(av))
        L = self.model.length(feats)
        if self._heading0 is not None:
            if self._yaw_ref is None:
                self._yaw_ref = psi
            psi = wrap_angle(self._heading0 + psi - self._yaw_ref)
        dpsi = None if self._prev_heading is None else wrap_angle(psi - self._prev_heading)
        since_mag = math.inf if self._mag_clean_t is None else max(0.0, ts - self._mag_clean_t)
        sig_h = math.hypot(
            cfg.sigma_mag_heading if since_mag < math.inf else math.pi / 2, cfg.gyro_drift * (since_mag if since_mag < math.inf else 0.0)
        )
        sig_h = min(math.hypot(sig_h, cfg.sigma_offset, self._sat_angle), math.pi)
        degraded = self._degraded_next
        if not self.att.has_mag:
            degraded = degraded or "no-mag"
        elif not self.att.mag_ok:
            degraded = degraded or "mag-disturbed"
        ev = StepEvent(
            t=ts,
            length=L,
            heading=psi,
            sigma_length=self.model.relative_sigma * L,
            sigma_heading=sig_h,
            heading_change=dpsi,
            sigma_heading_change=None if dpsi is None else math.hypot(cfg.sigma_turn_floor, cfg.turn_scale_sigma * abs(dpsi)),
            degraded=degraded,
        )
        self._degraded_next = ""
        self._prev_heading = psi
        self._last_step_t = ts
        self.stats.steps += 1
        self.steps.append(ev)
        self.features.append(feats)
        return ev

    def _update_offset(self, seg, fwd: float) -> None:
        """Walking direction over the step, for the device-to-walking offset (phone in a pocket or a
        bag, or held sideways).

        The axis: the principal axis of the horizontal acceleration over the step (walking shakes the
        phone most along the way it goes). Its 180 degree ambiguity is resolved by the gait, not by
        continuity with a prior: along the way forward the horizontal acceleration rises and falls
        with the vertical one (the body brakes as it lands and pushes off as it rises; ILC site1,
        phones in hand: positive correlation in 95 % of 4 s windows, median 0.48). Each step's
        direction, weighted by how clear its axis and its sign are, enters a running circular mean
        (about ``1 / offset_gain`` steps) that starts at ``walking_offset`` with the weight of
        ``offset_prior_steps`` steps.

        Known limit: for a phone held in front, the principal axis leans ~20 deg (median, ILC site1)
        into the sway, so the estimate is for carrying modes where the offset is unknown and large;
        a phone in the hand is better served by ``walking_offset`` = 0 and no estimate (the default).
        """
        ax = np.array([h[5] for h in seg])
        ay = np.array([h[6] for h in seg])
        av = np.array([h[2] for h in seg])
        ax -= ax.mean()
        ay -= ay.mean()
        av -= av.mean()
        cxx, cyy, cxy = float(ax @ ax), float(ay @ ay), float(ax @ ay)
        if cxx + cyy <= 0:
            return
        axis = 0.5 * math.atan2(2 * cxy, cxx - cyy)
        along = ax * math.cos(axis) + ay * math.sin(axis)
        sv = float(along @ av)
        if self.cfg.offset_sign == "continuity":
            sv = math.cos(wrap_angle(axis - fwd - self._offset)) * abs(sv)
        if sv < 0:
            axis += math.pi
        ecc = math.sqrt((cxx - cyy) ** 2 + 4 * cxy * cxy) / (cxx + cyy)  # 1 for a line, 0 for a circle
        den = math.sqrt(float(along @ along) * float(av @ av))
        w = ecc * (abs(sv) / den if den > 0 else 0.0)
        off = wrap_angle(axis - fwd)
        g = self.cfg.offset_gain
        self._offset_sum = (1 - g) * self._offset_sum + g * w * complex(math.cos(off), math.sin(off))
        self._offset = math.atan2(self._offset_sum.imag, self._offset_sum.real)

    def _saturation(self, t: float, acc, gyr) -> None:
        """Flag readings at the sensors' full scale: the motion they stand for was larger, so the step
        they fall in carries a "saturated" note, and a clipped gyro leaves the heading off by up to
        about the clipped rate times the sample interval per sample (added to the steps' heading
        sigma until the magnetometer is trusted again). With the full scale unknown, a reading
        repeated exactly on ``SATURATION_REPEATS`` consecutive samples beyond a walking phone's
        plausible range (``PLATEAU_ACCEL`` m/s^2, ``PLATEAU_GYRO`` rad/s) is taken as a clipped plateau."""
        dt = t - self._last_t if self._last_t is not None else 1.0 / self.rate
        prev_raw = self._prev_raw
        sat_acc = self._saturated(acc, self.accel_range, PLATEAU_ACCEL, prev_raw[0] if prev_raw is not None else None, self._plateau[0])
        sat_gyr = self._saturated(gyr, self.gyro_range, PLATEAU_GYRO, prev_raw[1] if prev_raw is not None else None, self._plateau[1])
        self._prev_raw = (tuple(acc), tuple(gyr))
        if sat_gyr:
            self._sat_angle += max(abs(gyr[0]), abs(gyr[1]), abs(gyr[2])) * min(max(dt, 0.0), 0.1)
        elif self.att.mag_ok:
            self._sat_angle = 0.0
        if sat_acc or sat_gyr:
            self.stats.saturated += 1
            self._degraded_next = self._degraded_next or "saturated"

    @staticmethod
    def _saturated(v, full: float | None, plausible: float, prev, run: list[int]) -> bool:
        """One sensor's reading at full scale (known), or ending a clipped plateau (full scale unknown):
        ``run`` counts per axis the consecutive identical readings beyond ``plausible``."""
        if full is not None:
            return max(abs(v[0]), abs(v[1]), abs(v[2])) >= SATURATION_SHARE * full
        v0, v1, v2 = abs(v[0]), abs(v[1]), abs(v[2])
        if v0 < plausible and v1 < plausible and v2 < plausible:  # the usual sample: no plateau on any axis
            run[0] = run[1] = run[2] = 0
            return False
        for i in range(3):  # per axis, as ImuBlock.saturated (streaming: from the plateau's last sample on)
            run[i] = run[i] + 1 if prev is not None and v[i] == prev[i] and abs(v[i]) >= plausible else 0
        return max(run) >= SATURATION_REPEATS - 1

    # ------------------------------------------------------------------
    def process(self, imu: ImuBlock) -> list[StepEvent]:
        """Feed a whole block; returns the steps it completed."""
        if self.accel_range is None:
            self.accel_range = imu.accel_range
        if self.gyro_range is None:
            self.gyro_range = imu.gyro_range
        out: list[StepEvent] = []
        t = imu.t.tolist()
        acc = imu.accel_body.tolist()
        gyr = imu.gyro_body.tolist()
        mag = imu.mag_body.tolist() if imu.mag_body is not None else None
        upd = self.update
        for i in range(len(t)):
            r = upd(t[i], acc[i], gyr[i], mag[i] if mag is not None else None)
            if r:
                out.extend(r)
        return out


def run_phone_pdr(
    imu: ImuBlock, length_model: LengthModel | None = None, config: PhonePdrConfig | None = None, heading0: float | None = 0.0
) -> tuple[list[StepEvent], PdrStats]:
    """Batch wrapper: all steps of a recording. ``heading0`` makes headings relative to the first step."""
    pdr = PhonePdr(imu.rate_hz, length_model, config, heading0)
    steps = pdr.process(imu)
    return steps, pdr.stats


def dead_reckon(steps: list[StepEvent], x0: float = 0.0, y0: float = 0.0, t0: float | None = None) -> Trajectory:
    """Positions after each step (Kourogi eq 12) and their sigmas (eq 13), starting at (x0, y0) at ``t0``
    (default: 1 s before the first step; no later than 1 ms before it): :class:`.deadreckoning.DeadReckoning`."""
    if steps and t0 is not None:
        t0 = min(t0, steps[0].t - 1e-3)
    return DeadReckoning.from_steps(steps, (x0, y0), 0.0 if t0 is None and not steps else t0).to_trajectory()

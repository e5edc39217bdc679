"""Realism checks: statistics of simulated data against the same statistics of real recordings.

* **RSSI versus distance**: slope of RSSI against log10(distance) per access point, dB/decade
  (-10 n for a path-loss exponent n). Real access point positions are unknown: each is placed at the
  RSSI-weighted centroid of the labelled positions of its 5 strongest readings (a standard crowd
  estimate), which biases real slopes a little towards 0.
* **Fingerprint similarity versus distance**: median cosine similarity (shifted dBm) of scan pairs in
  distance bins.
* **Step frequency** while walking, Hz (real: our phone PDR's steps on waypointed walks; simulated:
  the truth).
* **Acceleration spectrum peak**: the dominant frequency of |a| in 10 s walking windows, Hz.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..radio.similarity import cosine_shifted
from ..radio.survey import LabelledScan
from ..types import ImuBlock

DIST_BINS = (0.0, 2.0, 5.0, 10.0, 20.0, 40.0)


@dataclass
class RealismStats:
    slopes: np.ndarray  # dB/decade per transmitter
    similarity: list[float]  # median cosine per DIST_BINS interval
    step_freq: np.ndarray  # Hz samples
    spectrum_peak: np.ndarray  # Hz samples


def rssi_slopes(labelled: list[LabelledScan], tx_pos: dict[str, np.ndarray] | None = None, min_readings: int = 30) -> np.ndarray:
    readings: dict[str, list[tuple[np.ndarray, float]]] = {}
    for ls in labelled:
        for k, r in ls.scan.rssi_dbm.items():
            readings.setdefault(k, []).append((ls.pos_enu, r))
    out = []
    for k, rows in readings.items():
        if len(rows) < min_readings:
            continue
        P = np.array([p for p, _ in rows])
        R = np.array([r for _, r in rows])
        if tx_pos is not None and k in tx_pos:
            ap = tx_pos[k]
        else:
            top = np.argsort(-R)[:5]
            w = 10 ** (R[top] / 10)
            ap = (P[top] * w[:, None]).sum(0) / w.sum()
        d = np.linalg.norm(P - ap, axis=1)
        ok = (d > 1.0) & (d < 50.0)
        if ok.sum() < min_readings or np.ptp(np.log10(d[ok])) < 0.5:
            continue
        slope = np.polyfit(np.log10(d[ok]), R[ok], 1)[0]
        out.append(slope)
    return np.array(out)


def similarity_by_distance(labelled: list[LabelledScan], rng: np.random.Generator, n_pairs: int = 4000) -> list[float]:
    n = len(labelled)
    sims: list[list[float]] = [[] for _ in range(len(DIST_BINS) - 1)]
    for _ in range(n_pairs):
        i, j = rng.integers(n, size=2)
        if i == j or labelled[i].floor != labelled[j].floor:
            continue
        d = float(np.linalg.norm(labelled[i].pos_enu - labelled[j].pos_enu))
        k = int(np.searchsorted(DIST_BINS, d, side="right")) - 1
        if 0 <= k < len(sims):
            sims[k].append(cosine_shifted(labelled[i].scan, labelled[j].scan))
    return [float(np.median(s)) if s else float("nan") for s in sims]


def spectrum_peaks(imu: ImuBlock, walking: np.ndarray | None = None, window: float = 10.0) -> list[float]:
    """Dominant frequency of |a| (0.5-4 Hz) in each window of ``window`` s that is walking throughout."""
    a = np.linalg.norm(imu.accel_body, axis=1)
    rate = imu.rate_hz
    n = int(window * rate)
    out = []
    for s in range(0, len(a) - n, n):
        if walking is not None and not walking[s : s + n].all():
            continue
        x = a[s : s + n] - a[s : s + n].mean()
        if x.std() < 0.5:  # standing
            continue
        f = np.fft.rfftfreq(n, 1 / rate)
        P = np.abs(np.fft.rfft(x * np.hanning(n))) ** 2
        band = (f >= 0.5) & (f <= 4.0)
        out.append(float(f[band][np.argmax(P[band])]))
    return out


def in_range(sim_value: float, real_values: np.ndarray, lo_q: float = 10, hi_q: float = 90) -> bool:
    lo, hi = np.percentile(real_values, [lo_q, hi_q])
    return bool(lo <= sim_value <= hi)

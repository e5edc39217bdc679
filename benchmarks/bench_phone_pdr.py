"""Phone PDR throughput: one hour of 50 Hz 9-axis data on one core (goal <= 5 s, >= 700x real time).

Prints samples per second and the real-time factor for our streaming PDR, and, as the plain method
measured in the same run, a vectorised offline peak picker (scipy.signal.find_peaks on the low-passed
|a|, no attitude, no heading) with the ratio of the two.

    python -m benchmarks.bench_phone_pdr [--minutes 60]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from scipy import signal

from benchmarks import headline
from hybridloc.pdr import run_phone_pdr
from hybridloc.types import ImuBlock
from hybridloc.units import G0


def synth_hour(minutes: float, rng: np.random.Generator, rate: float = 50.0) -> ImuBlock:
    """Hand-held walking with turns and pauses: vertical bounce at ~1.8 Hz, heading random walk."""
    n = int(minutes * 60 * rate)
    t = np.arange(n) / rate
    walking = (np.floor(t / 60.0) % 5) != 4  # one minute in five standing
    f = 1.8 + 0.1 * np.sin(2 * math.pi * t / 300.0)
    phase = 2 * math.pi * np.cumsum(f) / rate
    av = np.where(walking, 2.5 * np.sin(phase), 0.0)
    yaw_rate = np.convolve(rng.standard_normal(n), np.ones(100) / 100, mode="same") * 2.0
    psi = np.cumsum(yaw_rate) / rate
    c, s = np.cos(psi - math.pi / 2), np.sin(psi - math.pi / 2)
    acc = np.column_stack([np.zeros(n), np.zeros(n), G0 + av]) + 0.08 * rng.standard_normal((n, 3))
    gyr = np.column_stack([np.zeros(n), np.zeros(n), yaw_rate]) + 0.003 * rng.standard_normal((n, 3))
    m_n = np.array([0.0, 32e-6, -32e-6])
    mag = np.column_stack([c * m_n[0] + s * m_n[1], -s * m_n[0] + c * m_n[1], np.full(n, m_n[2])]) + 0.3e-6 * rng.standard_normal((n, 3))
    return ImuBlock(t, acc, gyr, mag)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=60.0)
    args = ap.parse_args(argv)
    imu = synth_hour(args.minutes, np.random.default_rng(42))
    n = len(imu)
    t0 = time.perf_counter()
    steps, _ = run_phone_pdr(imu)
    ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    b, a = signal.butter(2, 3.0 / 25.0)
    y = signal.lfilter(b, a, np.linalg.norm(imu.accel_body, axis=1))
    peaks, _ = signal.find_peaks(y, height=G0 + 1.0, distance=14)
    plain = time.perf_counter() - t0
    dur = imu.duration
    print(
        f"phone PDR: {n} samples ({dur / 60:.0f} min at 50 Hz, 9-axis) in {ours:.2f} s = {n / ours:,.0f} samples/s, "
        f"{dur / ours:,.0f}x real time (goal: <= 5 s per hour, >= 700x); {len(steps)} steps"
    )
    print(
        f"plain offline peak picker (scipy find_peaks, no heading): {plain:.3f} s, {len(peaks)} peaks; "
        f"ratio ours/plain = {ours / plain:,.0f}x slower (the price of streaming attitude + heading per sample)"
    )
    headline({"samples_per_s": n / ours, "real_time_factor": dur / ours, "wall_s": ours, "steps": len(steps), "ratio_to_peak_picker": ours / plain})


if __name__ == "__main__":
    main()

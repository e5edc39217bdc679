"""Foot INS throughput: one hour of 200 Hz IMU data on one core (goal >= 100x real time, <= 36 s).

The hour is a real PyShoe VICON trial repeated end to end (when ../shared/data is present) or a
synthetic stance/swing gait otherwise; detection + ZUPT-aided 15-state ESKF both count. The plain
method in the same run is DEDRIFT-I (Ojeda & Borenstein: strapdown with velocity resets, no filter).

    python -m benchmarks.bench_foot_ins [--minutes 60]
"""

from __future__ import annotations

import argparse
import glob
import math
import time
from pathlib import Path

import numpy as np

from benchmarks import headline
from hybridloc.ins.foot import dedrift_i, run_foot_ins
from hybridloc.ins.stance import gyro_minimum
from hybridloc.types import ImuBlock
from hybridloc.units import G0

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "pyshoe-vicon"


def one_hour(minutes: float, rng: np.random.Generator) -> tuple[ImuBlock, str]:
    n_target = int(minutes * 60 * 200)
    files = sorted(glob.glob(str(SHARED / "*.mat")))
    if files:
        from hybridloc.io.imu_files import read_pyshoe_mat

        rec = read_pyshoe_mat(files[0])
        reps = math.ceil(n_target / len(rec.imu))
        acc = np.tile(rec.imu.accel_body, (reps, 1))[:n_target]
        gyr = np.tile(rec.imu.gyro_body, (reps, 1))[:n_target]
        src = f"PyShoe trial {Path(files[0]).stem} repeated"
    else:
        k = np.arange(n_target) % 200
        swing = k >= 80
        tau = np.where(swing, (k - 80) / 120.0, 0.0)
        acc = np.column_stack([np.where(swing, 17.5 * np.sin(2 * math.pi * tau), 0.0), np.zeros(n_target), np.full(n_target, G0)])
        gyr = np.column_stack([np.zeros(n_target), np.where(swing, 4.0 * np.sin(2 * math.pi * tau), 0.0), np.zeros(n_target)])
        acc += 0.02 * rng.standard_normal(acc.shape)
        gyr += 0.002 * rng.standard_normal(gyr.shape)
        src = "synthetic gait"
    t = np.arange(n_target) / 200.0
    return ImuBlock(t, acc, gyr), src


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=60.0)
    args = ap.parse_args(argv)
    imu, src = one_hour(args.minutes, np.random.default_rng(7))
    # The filter's arithmetic is compiled by Numba on its first call in a fresh install (then cached on
    # disk): a one-off cost, reported apart from the throughput of a running filter.
    t0 = time.perf_counter()
    run_foot_ins(ImuBlock(imu.t[:2000], imu.accel_body[:2000], imu.gyro_body[:2000]))
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    run_foot_ins(imu)
    ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    dedrift_i(imu, gyro_minimum(imu.gyro_body, n=100)[1])
    plain = time.perf_counter() - t0
    print(
        f"foot INS: {len(imu)} samples ({imu.duration / 60:.0f} min at 200 Hz, {src}) in {ours:.1f} s = {len(imu) / ours:,.0f} samples/s, "
        f"{imu.duration / ours:.0f}x real time (goal >= 100x, one hour in <= 36 s)"
    )
    print(f"plain DEDRIFT-I (no filter): {plain:.1f} s; ratio ours/plain = {ours / plain:.2f}")
    print(f"first call, 10 s of samples, with the compiled kernels loaded (or compiled when not cached yet): {warm:.2f} s")
    headline(
        {
            "samples_per_s": len(imu) / ours,
            "real_time_factor": imu.duration / ours,
            "wall_s": ours,
            "ratio_to_dedrift": ours / plain,
            "first_call_s": warm,
        }
    )


if __name__ == "__main__":
    main()

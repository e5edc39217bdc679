"""Simulator speed: 1,000 walkers x 10 minutes of phone data (IMU and Android's rotation vector at
50 Hz, WiFi, BLE, RFID, GPS) in memory (goal <= 60 s on this machine: what the server load benchmark
needs), the same walkers' step and scan events alone (the true steps and the radio, no IMU: what a load
generator sending steps and scans needs), and the foot IMU at 200 Hz (goal >= 200x real time). Files
are not written (writing text traces is I/O, measured apart by ``hybridloc sim walk``).

    python -m benchmarks.bench_sim [--walkers 1000] [--minutes 10]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks import headline
from hybridloc.sim.building import generate_world
from hybridloc.sim.imu import disturbance_field, foot_imu, phone_sensors
from hybridloc.sim.radio import make_radio_model, simulate_radio
from hybridloc.sim.walker import simulate_walk


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--walkers", type=int, default=1000)
    ap.add_argument("--minutes", type=float, default=10.0)
    args = ap.parse_args(argv)
    world = generate_world(np.random.default_rng(1), 3, 1)
    t0 = time.perf_counter()
    model = make_radio_model(world, np.random.default_rng(2))
    field = disturbance_field(np.random.default_rng(3))
    prep = time.perf_counter() - t0
    root = np.random.default_rng(4)
    t0 = time.perf_counter()
    n_samples = n_scans = 0
    for i in range(args.walkers):
        rng = np.random.default_rng(root.integers(2**63))
        walk = simulate_walk(world, rng, args.minutes, walker=i)
        phone = phone_sensors(walk, rng, mag_field=field)
        radio = simulate_radio(model, walk, rng)
        n_samples += len(phone.imu)
        n_scans += len(radio.wifi) + len(radio.ble)
    phone_s = time.perf_counter() - t0
    print(
        f"simulator: {args.walkers} walkers x {args.minutes:g} min of phone data ({n_samples:,} IMU + rotation vector samples, {n_scans:,} scans) "
        f"in {phone_s:.1f} s (+{prep:.1f} s radio model set-up); goal <= 60 s for 1,000 x 10 min"
    )
    # the same walkers' events alone: true steps and scans (the IMU's draws skipped, so other walks)
    root = np.random.default_rng(4)
    t0 = time.perf_counter()
    n_steps = n_ev_scans = 0
    for i in range(args.walkers):
        rng = np.random.default_rng(root.integers(2**63))
        walk = simulate_walk(world, rng, args.minutes, walker=i)
        radio = simulate_radio(model, walk, rng)
        n_steps += len(walk.steps)
        n_ev_scans += len(radio.wifi) + len(radio.ble)
    events_s = time.perf_counter() - t0
    print(f"step and scan events alone: {n_steps:,} steps and {n_ev_scans:,} scans in {events_s:.1f} s")
    rng = np.random.default_rng(5)
    walk = simulate_walk(world, rng, args.minutes)
    t0 = time.perf_counter()
    imu, _ = foot_imu(walk, rng)
    foot = time.perf_counter() - t0
    print(f"foot IMU at 200 Hz: {imu.duration:.0f} s of data in {foot:.2f} s = {imu.duration / foot:.0f}x real time (goal >= 200x)")
    headline(
        {
            "phone_wall_s": phone_s,
            "phone_samples_per_s": n_samples / phone_s,
            "events_wall_s": events_s,
            "events_steps_per_s": n_steps / events_s,
            "foot_real_time_factor": imu.duration / foot,
        }
    )


if __name__ == "__main__":
    main()

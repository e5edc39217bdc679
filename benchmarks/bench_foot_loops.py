"""Foot INS closed loops on simulated walks: return-to-start error in % of distance travelled
(Ojeda & Borenstein eqs 7-9; goal <= 0.5 %, Ojeda 0.6-0.9 %, Godha 1.2 %), industrial-grade IMU,
10-minute walks through a generated 3-floor building (corridors, rooms, stairs), each ending where it
started. The plain method in the same run is DEDRIFT-I.

    python -m benchmarks.bench_foot_loops [--walks 6] [--minutes 10]
"""

from __future__ import annotations

import argparse

import numpy as np

from benchmarks import headline
from hybridloc.ins.foot import FootInsConfig, dedrift_i, run_foot_ins
from hybridloc.ins.stance import gyro_minimum
from hybridloc.sim.building import generate_world
from hybridloc.sim.imu import foot_imu
from hybridloc.sim.walker import simulate_walk


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--walks", type=int, default=6)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--grade", default="industrial")
    args = ap.parse_args(argv)
    world = generate_world(np.random.default_rng(21), 3, 21)
    rows = []
    for i in range(args.walks):
        rng = np.random.default_rng([21, i])
        walk = simulate_walk(world, rng, args.minutes, walker=i, close_loop=True)
        imu, truth = foot_imu(walk, rng, grade=args.grade)
        D = float(np.linalg.norm(np.diff(truth.pos[:, :2], axis=0), axis=1).sum())
        closure = float(np.linalg.norm(truth.pos[-1, :2] - truth.pos[0, :2]))
        res = run_foot_ins(imu, FootInsConfig())
        e_r = float(np.linalg.norm(res.pos_enu[-1, :2] - res.pos_enu[0, :2]))
        dd = dedrift_i(imu, gyro_minimum(imu.gyro_body, n=100)[1])
        e_dd = float(np.linalg.norm(dd[-1, :2] - dd[0, :2]))
        rows.append((D, e_r, e_dd))
        print(
            f"walk {i}: {imu.duration / 60:.1f} min, {D:.0f} m travelled (truth closes to {closure:.2f} m): return-to-start {e_r:.2f} m = "
            f"{100 * e_r / D:.2f}% (DEDRIFT-I {100 * e_dd / D:.1f}%)"
        )
    r = np.array(rows)
    E_r = r[:, 1].mean()  # Ojeda eq 8
    print(
        f"mean return-to-start error E_r {E_r:.2f} m over mean distance {r[:, 0].mean():.0f} m: E_p = {100 * E_r / r[:, 0].mean():.2f}% "
        f"(goal <= 0.5 %); DEDRIFT-I {100 * r[:, 2].mean() / r[:, 0].mean():.1f}%; ratio ours/DEDRIFT-I {r[:, 1].mean() / r[:, 2].mean():.3f}"
    )
    headline(
        {
            "return_to_start_mean_m": E_r,
            "return_to_start_pct": 100 * E_r / r[:, 0].mean(),
            "dedrift_return_to_start_pct": 100 * r[:, 2].mean() / r[:, 0].mean(),
            "distance_mean_m": r[:, 0].mean(),
        }
    )


if __name__ == "__main__":
    main()

"""``hybridloc sim world`` and ``hybridloc sim walk``: simulated buildings and walks."""

from __future__ import annotations

import argparse

from ..progress import Progress


def _cmd_sim_world(args: argparse.Namespace) -> int:
    from ..sim.run import make_world

    w = make_world(args.seed, args.floors, args.out, args.floorplan)
    print(
        f"world {args.seed}{' on ' + args.floorplan if args.floorplan else ''}: {w.n_floors} floors of {w.width - w.x_min:.1f} m x {w.depth - w.y_min:.1f} m, {len(w.rooms)} rooms, {len(w.aps)} WiFi APs, "
        f"{len(w.beacons)} BLE beacons, {len(w.rfid)} RFID readers -> {args.out}"
    )
    return 0


def _cmd_sim_walk(args: argparse.Namespace) -> int:
    from ..sim.run import load_world, simulate_walks

    world = load_world(args.world)

    bar = Progress("[sim] walker", args.walkers)
    out = simulate_walks(world, args.walkers, args.minutes, args.carrier, args.out, args.seed, lambda i, n: bar.update(i))
    print(f"{len(out)} walks of {args.minutes:g} min ({args.carrier}) -> {args.out}")
    return 0


def register(sub) -> None:
    sm = sub.add_parser("sim", help="simulated buildings and walks with ground truth")
    ssub = sm.add_subparsers(dest="sim_command", required=True)
    sw = ssub.add_parser("world", help="generate a multi-floor building with WiFi, BLE and RFID infrastructure")
    sw.add_argument("--seed", type=int, required=True)
    sw.add_argument("--floors", type=int, default=3, help="floors of a generated building (default 3)")
    sw.add_argument(
        "--floorplan",
        metavar="DIR",
        help="build the world on a real floor plan instead: a site folder in the Indoor Location "
        "Competition layout (<floor>/geojson_map.json); walkers route through its corridors",
    )
    sw.add_argument("--out", required=True)
    sw.set_defaults(func=_cmd_sim_world)
    sk = ssub.add_parser("walk", help="simulate walkers in a world: traces in the ILC format, foot IMU CSV, truth")
    sk.add_argument("--world", required=True)
    sk.add_argument("--walkers", type=int, default=1)
    sk.add_argument("--minutes", type=float, default=5.0)
    sk.add_argument("--carrier", choices=("phone", "foot", "both"), default="phone")
    sk.add_argument("--seed", type=int, default=0, help="seed of the walkers (the world has its own)")
    sk.add_argument("--out", required=True)
    sk.set_defaults(func=_cmd_sim_walk)

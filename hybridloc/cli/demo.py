"""``hybridloc demo``: the platform end to end."""

from __future__ import annotations

import argparse
from pathlib import Path


def _cmd_demo(args: argparse.Namespace) -> int:
    from ..demo import run_demo
    from ._common import pyplot

    pyplot("the demo's figure")  # before minutes of work, not after

    if args.dashboard:
        from ..server.dashboard.run import parse_listen

        parse_listen(args.dashboard)  # a bad HOST:PORT is one line before minutes of work
    return run_demo(Path(args.out), sim=args.sim, speed=args.speed, slam=not args.no_slam, dashboard=args.dashboard)


def register(sub) -> None:
    demo = sub.add_parser("demo", help="the platform end to end: server, surveys, radio map, phone clients, scores, PNG")
    demo.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    demo.add_argument("--sim", action="store_true", help="use a simulated building instead of the bundled real sample")
    demo.add_argument("--speed", type=float, default=20.0, help="replay speed of the phone clients (default 20x)")
    demo.add_argument(
        "--no-slam",
        action="store_true",
        help="the server without its crowd SLAM (the demo as it was before it: no corrected tracks, the survey map alone)",
    )
    demo.add_argument(
        "--dashboard",
        nargs="?",
        const="127.0.0.1:8080",
        metavar="HOST:PORT",
        help="keep the operator dashboard up while the replay runs (default 127.0.0.1:8080) and print its URL",
    )
    demo.set_defaults(func=_cmd_demo)

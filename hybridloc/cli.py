"""The ``hybridloc`` command.

Layering (as in evo): this module only parses arguments, calls pure library functions and prints.
Every library error derived from :class:`hybridloc.io.DataFormatError` or :class:`ValueError` is
reported as one line on stderr with exit status 1 (2 for usage errors, from argparse).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from . import __version__

log = logging.getLogger("hybridloc")


def _cmd_data_inspect(args: argparse.Namespace) -> int:
    from .inspect import inspect_file

    status = 0
    for p in args.files:
        try:
            print(inspect_file(p, args.format, args.rate).render())
        except (ValueError, OSError) as exc:  # DataFormatError is a ValueError
            print(f"{p}: error: {exc}", file=sys.stderr)
            status = 1
        print()
    return status


def _cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(Path(args.out), sim=args.sim)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="hybridloc", description="Crowd-sourced hybrid PDR + WiFi/RF SLAM for indoor positioning.")
    ap.add_argument("--version", action="version", version=f"hybridloc {__version__}")
    ap.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = ap.add_subparsers(dest="command", required=True)

    data = sub.add_parser("data", help="inspect recordings")
    dsub = data.add_subparsers(dest="data_command", required=True)
    ins = dsub.add_parser("inspect", help="print what recordings hold: duration, rates, scans, APs, waypoints, gaps, problems")
    ins.add_argument("files", nargs="+", metavar="FILE")
    ins.add_argument("--format", choices=("msft", "pyshoe", "openshoe", "csv", "ujiindoorloc"), help="skip format detection")
    ins.add_argument("--rate", type=float, default=None, metavar="HZ", help="sample rate for files without timestamps (OpenShoe; default 100)")
    ins.set_defaults(func=_cmd_data_inspect)

    demo = sub.add_parser("demo", help="run the platform end to end on the bundled sample")
    demo.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    demo.add_argument("--sim", action="store_true", help="use a simulated building instead of the bundled real sample")
    demo.set_defaults(func=_cmd_demo)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2), format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except (ValueError, OSError) as exc:
        print(f"hybridloc: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""``hybridloc data inspect``: what recordings hold."""

from __future__ import annotations

import argparse

from ._common import report_input_error


def _cmd_data_inspect(args: argparse.Namespace) -> int:
    from ..inspect import inspect_file

    status = 0
    for p in args.files:
        try:
            print(inspect_file(p, args.format, args.rate).render())
        except Exception as exc:  # one line per unreadable input, then the next input
            status = max(status, report_input_error(p, exc))
        print()
    return status


def register(sub) -> None:
    data = sub.add_parser("data", help="inspect recordings")
    dsub = data.add_subparsers(dest="data_command", required=True)
    ins = dsub.add_parser("inspect", help="print what recordings hold: duration, rates, scans, APs, waypoints, gaps, problems")
    ins.add_argument("files", nargs="+", metavar="FILE")
    ins.add_argument(
        "--format", choices=("msft", "pyshoe", "openshoe", "csv", "ujiindoorloc", "sensorconnect", "footprints"), help="skip format detection"
    )
    ins.add_argument("--rate", type=float, default=None, metavar="HZ", help="sample rate for files without timestamps (OpenShoe; default 100)")
    ins.set_defaults(func=_cmd_data_inspect)

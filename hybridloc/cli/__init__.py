"""The ``hybridloc`` command.

Layering (as in evo): this package only parses arguments, calls pure library functions and prints.
Each command module (:mod:`.data`, :mod:`.pdr`, :mod:`.radiomap`, :mod:`.locate`, :mod:`.sim`,
:mod:`.server`, :mod:`.client`, :mod:`.slam`, :mod:`.eval`, :mod:`.demo`) registers its sub-commands on the parser
with ``register(subparsers)`` and holds their ``_cmd_*`` functions. The library reports failures
with :class:`hybridloc.errors.HybridlocError` (and the builtin ``ValueError`` / ``OSError``); they
become one line on stderr (``hybridloc: error: ...``) and exit status 2 for what the user can mend
(bad input, a missing, empty or unreadable file, a missing optional package), 1 for a computation
that failed (:class:`~hybridloc.errors.ComputationFailed`); argparse's usage errors are 2 as well.

Options that the settings file (``--config FILE``) and the ``HYBRIDLOC_*`` environment variables
also give (:mod:`hybridloc.settings`) default to ``None`` here and are resolved after parsing: the
option, else the environment, else the file, else the built-in default.
"""

from __future__ import annotations

import argparse
import logging
import sys

from .. import __version__
from ._common import LENGTH_MODELS, apply_settings, input_error_status, one_line

__all__ = ["LENGTH_MODELS", "build_parser", "main"]

log = logging.getLogger("hybridloc")


def build_parser() -> argparse.ArgumentParser:
    from . import client, data, demo, eval, floorplan, locate, pdr, radiomap, server, sim, slam

    ap = argparse.ArgumentParser(prog="hybridloc", description="Crowd-sourced hybrid PDR + WiFi/RF SLAM for indoor positioning.")
    ap.add_argument("--version", action="version", version=f"hybridloc {__version__}")
    ap.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    ap.add_argument(
        "--config",
        metavar="FILE",
        help="settings file (TOML: site, endpoint, db, [security], [filter]; see hybridloc.settings); "
        "HYBRIDLOC_* environment variables override it, options override both",
    )
    sub = ap.add_subparsers(dest="command", required=True)

    data.register(sub)
    pdr.register(sub)
    mp = sub.add_parser("map", help="radio maps: build, show")
    msub = mp.add_subparsers(dest="map_command", required=True)
    radiomap.register(msub)
    server.register_map(msub)
    client.register(sub)
    server.register(sub)
    locate.register(sub)
    sim.register(sub)
    slam.register(sub)
    floorplan.register(sub)
    eval.register(sub)
    demo.register(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2), format="%(levelname)s %(name)s: %(message)s")
    try:
        apply_settings(args)
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        status = input_error_status(exc)
        if status is None:
            raise  # a bug: keep its traceback
        log.debug("exit status %d", status, exc_info=True)
        print(f"hybridloc: error: {one_line(exc)}", file=sys.stderr)
        return status

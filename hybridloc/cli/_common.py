"""Helpers shared by the command modules: recordings to IMU data, calibration files, number lists, security options."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from ..errors import BadInput, MissingData

#: step length models of ``pdr phone --model`` and ``eval pdr-phone --model`` (hybridloc.pdr.steplength.MODELS)
LENGTH_MODELS = ("constant", "weinberg", "frequency", "kim", "height")


def load_imu(path: str, fmt: str | None, rate: float | None, accel_unit: str = "m/s^2"):
    """(imu, read report, device model, waypoints or None, format read) of a recording."""
    from ..errors import check_input_file
    from ..io import detect_format

    check_input_file(path, "recording")
    fmt = fmt or detect_format(path)
    if fmt == "msft":
        from ..io.msft import read_ilc_trace

        tr = read_ilc_trace(path)
        if tr.imu is None:
            raise MissingData(f"{path}: no usable IMU data ({tr.report.summary()})")
        return tr.imu, tr.report, tr.device_model, tr.waypoints, fmt
    from ..io.imu_files import read_imu_csv, read_openshoe_mat, read_pyshoe_mat, read_sensorconnect_csv

    if fmt == "footprints":
        raise MissingData(f"{path}: a footprint truth file holds no IMU data (give the SensorConnect CSV beside it)")
    if fmt == "sensorconnect":
        rec = read_sensorconnect_csv(path)
    elif fmt == "csv":
        rec = read_imu_csv(path, accel_unit=accel_unit)
    elif fmt == "pyshoe":
        rec = read_pyshoe_mat(path)
    elif fmt == "openshoe":
        rec = read_openshoe_mat(path, rate or 100.0)
    else:
        raise MissingData(f"{path}: format {fmt} holds no IMU data")
    return rec.imu, rec.report, "", None, fmt


def open_calibration(path: str | None, update: bool, model_name: str):
    """(calibrator, path) of --calibration FILE, created from ``model_name`` when absent and
    ``update`` (--update-calibration) asks for it; (None, None) without a file."""
    from ..pdr import LengthCalibrator, make_model

    if path is None:
        if update:
            raise BadInput("--update-calibration needs --calibration FILE (the device's calibration; created when absent)")
        return None, None
    p = Path(path)
    if p.is_file():
        return LengthCalibrator.load(p), p
    if not update:
        raise MissingData(f"calibration {p} not found (add --update-calibration to create it)")
    return LengthCalibrator(make_model(model_name)), p


def security(args: argparse.Namespace):
    from ..wire.zconfig import Security

    devices = []
    if getattr(args, "acl_devices", None):
        devices = [ln.split(":")[0].strip() for ln in Path(args.acl_devices).read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    extra = {}
    if getattr(args, "acl_operator", None):
        extra["acl_operators"] = list(args.acl_operator)
    return Security(
        **extra,
        users_file=getattr(args, "users", None),
        user=getattr(args, "user", None),
        password=getattr(args, "password", None),
        tls_cert=getattr(args, "tls_cert", None),
        tls_key=getattr(args, "tls_key", None),
        tls_ca=getattr(args, "tls_ca", None),
        acl_devices=devices,
    )


def parse_floats(text: str, n: int, what: str) -> tuple[float, ...]:
    import math

    try:
        vals = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise BadInput(f"{what} expected, got {text!r}") from None
    if len(vals) != n or not all(math.isfinite(v) for v in vals):
        raise BadInput(f"{what} expected ({n} finite numbers), got {text!r}")
    return vals


def stem_safe(path: str) -> str:
    import re

    from ..io.common import stem_of

    return re.sub(r"[^A-Za-z0-9_.-]", "_", stem_of(path))[:40]


def _json_number(v):
    """A figure for the JSON line: floats rounded to 6 significant digits, NaN and infinities as null."""
    import math

    if isinstance(v, bool) or v is None or isinstance(v, (int, str)):
        return v
    f = float(v)
    return float(f"{f:.6g}") if math.isfinite(f) else None


def print_headline(figures: dict) -> None:
    """The last line of an ``eval`` command or a benchmark: one JSON object of its headline figures,
    named with their units (``cold_mean_m``, ``floor_hit_pct``...), for scripts and CI; the table above
    it is for people."""
    import json

    print(json.dumps({k: _json_number(v) for k, v in figures.items()}), flush=True)


def pyplot(needed_for: str):
    """matplotlib.pyplot on the file-only Agg backend, or :class:`~hybridloc.errors.MissingDependency`
    naming the ``plot`` extra (matplotlib is a core dependency; this covers a trimmed install)."""
    from ..errors import require

    matplotlib = require("matplotlib", "plot", needed_for)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def input_error_status(exc: BaseException) -> int | None:
    """The exit status of an exception the user can mend, or of a computation that failed (1); None
    for anything else (a bug, which keeps its traceback).

    2: :class:`~hybridloc.errors.HybridlocError` of the user's side (bad input, missing data, missing
    package), ``ValueError`` (a bad value, a file not in its format, bytes that are not text),
    ``OSError`` (a missing or unreadable file, a folder where a file is expected, a corrupt gzip
    stream), ``EOFError`` (a truncated file), and the readers' own complaints about files that are not
    what they claim (a .mat file that is not MATLAB, a zip that is not one, a database file that is
    not SQLite). 1: :class:`~hybridloc.errors.ComputationFailed` and other ``RuntimeError``.
    """
    from ..errors import HybridlocError

    if isinstance(exc, HybridlocError):
        return exc.exit_code
    if isinstance(exc, (ValueError, OSError, EOFError)):
        return 2
    if type(exc).__name__ in ("MatReadError", "BadZipFile") or type(exc).__module__.startswith("sqlalchemy."):
        return 2
    if isinstance(exc, RuntimeError):
        return 1
    return None


def report_input_error(path, exc: BaseException) -> int:
    """One line on stderr for an input a per-file command could not use, and its exit status
    (:func:`input_error_status`); a bug is re-raised with its traceback."""
    code = input_error_status(exc)
    if code is None:
        raise exc
    msg, where = one_line(exc), f"{path}"
    # the readers name the file (and often the line) themselves: "FILE: error: FILE:12: ..." reads as
    # "FILE:12: error: ...", the usual form of a message about a place in a file
    if msg.startswith(f"{path}:"):
        rest = msg[len(f"{path}") :]
        m = re.match(r":(\d+): (.*)", rest, re.S)
        if m:
            where, msg = f"{path}:{m.group(1)}", m.group(2)
        elif rest.startswith(": "):
            msg = rest[2:]
    print(f"{where}: error: {msg}", file=sys.stderr)
    return code


def one_line(exc: BaseException) -> str:
    """The first line of an exception's message (database drivers append the SQL and a link)."""
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def apply_settings(args: argparse.Namespace) -> None:
    """Options a command takes from the settings (``_settings``: option dest -> dotted setting key,
    ``site[]`` for a repeatable option): the option when given, else the environment, else the
    settings file, else the built-in default. Then the options the command requires (``_required``)."""
    from ..settings import load_settings

    settings = load_settings(args.config)
    for dest, key in getattr(args, "_settings", {}).items():
        if getattr(args, dest, None) is not None:
            continue
        if key.endswith("[]"):
            v = settings.get(key[:-2])
            setattr(args, dest, None if v is None else [v])
        else:
            setattr(args, dest, settings.get(key))
    for dest in getattr(args, "_required", ()):
        if getattr(args, dest, None) is None:
            args._parser.error(
                f"the following arguments are required: --{dest.replace('_', '-')} (or set {dest} in the settings: --config FILE, "
                f"HYBRIDLOC_{dest.upper()})"
            )


def check_db_driver(url: str) -> None:
    """A PostgreSQL URL needs psycopg, the ``postgres`` extra: :class:`~hybridloc.errors.MissingDependency`
    in one line before any connection is tried (SQLite needs nothing beyond the core set)."""
    from ..errors import require

    if str(url).startswith(("postgresql", "postgres:")):
        require("psycopg", "postgres", "a PostgreSQL database")


# ------------------------------------------------------------------------------------------ batch work on Dask
def add_batch_arguments(p: argparse.ArgumentParser) -> None:
    """``--scheduler ADDRESS``, ``--workers N``, ``--serial``: where ``map rebuild`` / ``slam rebuild`` run
    (hybridloc.server.dask_batch)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--scheduler", metavar="ADDRESS", help="run the tasks on this Dask scheduler (tcp://HOST:PORT; its workers need hybridloc)")
    g.add_argument("--serial", action="store_true", help="no Dask: everything in this process, one task after another")
    p.add_argument("--workers", type=int, metavar="N", help="worker processes of the local Dask cluster (default: the usable cores)")


def check_batch_arguments(args: argparse.Namespace) -> None:
    """The batch options that cannot go together (before the command reads anything)."""
    if args.workers is not None and (args.serial or args.scheduler):
        raise BadInput("--workers sizes the local Dask cluster: not with --serial or --scheduler")
    if args.workers is not None and args.workers < 1:
        raise BadInput(f"--workers must be at least 1 (got {args.workers})")


def batch_client(args: argparse.Namespace, label: str):
    """The Dask client of a batch command's options (a context manager; None with ``--serial``); says on
    stderr where the tasks run."""
    import contextlib

    check_batch_arguments(args)
    if args.serial:
        return contextlib.nullcontext(None)
    from ..server.dask_batch import batch_client as open_client
    from ..server.dask_batch import usable_cores

    where = (
        f"the Dask scheduler at {args.scheduler}"
        if args.scheduler
        else f"a local Dask cluster of {args.workers if args.workers is not None else usable_cores()} worker processes"
    )
    print(f"{label} tasks on {where}", file=sys.stderr)
    return open_client(args.scheduler, args.workers)


def executor_of(args: argparse.Namespace, client) -> dict:
    """Where a batch command's tasks ran (its JSON line's ``executor``): serial, or Dask with its workers."""
    if client is None:
        return {"kind": "serial", "workers": 1}
    return {"kind": "dask-scheduler" if args.scheduler else "dask-local", "workers": len(client.nthreads())}

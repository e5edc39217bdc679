"""The library's exceptions: one base, :class:`HybridlocError`, and a subclass per kind of failure.

The command line turns them into one line on stderr and an exit status: 2 for what the user can
mend (:class:`BadInput`, :class:`DataFormatError`, :class:`MissingData`, :class:`MissingDependency`),
1 for a computation that failed on good input (:class:`ComputationFailed`). Each also derives from
the builtin a caller catching the old way expects (``ValueError``, ``FileNotFoundError``,
``ImportError``, ``RuntimeError``), so ``except ValueError`` around a reader keeps working.
"""

from __future__ import annotations

import os


class HybridlocError(Exception):
    """Base of every error the library raises on purpose. The message is one line for the user."""

    #: exit status the command line gives it
    exit_code = 2


class BadInput(HybridlocError, ValueError):
    """An argument, option, setting or value the library cannot use (the message names it)."""


class DataFormatError(BadInput):
    """A file cannot be read as the format claims. The message names file, line and reason."""

    def __init__(self, path: str | os.PathLike, line: int | None = None, reason: str | None = None):
        self.path = str(path)
        self.line = line
        self.reason = reason
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {reason}" if reason is not None else where)  # one argument: the whole message


class MissingData(HybridlocError, FileNotFoundError):
    """A file or folder that is absent, empty, a folder where a file is expected (or the reverse), or
    that holds none of the records asked for."""

    def __init__(self, message: str):
        # FileNotFoundError's (errno, strerror) form is not used: str(exc) is the message alone
        super().__init__(message)

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class MissingDependency(HybridlocError, ImportError):
    """An optional package is not installed; the message names the extra that brings it
    (``pip install 'hybridloc[EXTRA]'``)."""

    def __init__(self, package: str, extra: str, needed_for: str = ""):
        self.package = package
        self.extra = extra
        what = f" (needed for {needed_for})" if needed_for else ""
        super().__init__(f"{package} is not installed{what}: pip install 'hybridloc[{extra}]'")


class ComputationFailed(HybridlocError, RuntimeError):
    """Good input, but the computation could not produce its result (no map could be built, a
    server did not answer...)."""

    exit_code = 1


def require(module: str, extra: str, needed_for: str = ""):
    """``importlib.import_module(module)``, or :class:`MissingDependency` naming ``extra``."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if exc.name is not None and exc.name.split(".")[0] != module.split(".")[0]:
            raise  # the package is there but broken: not a missing extra
        raise MissingDependency(module.split(".")[0], extra, needed_for) from exc


def check_input_file(path: str | os.PathLike, what: str = "input file") -> None:
    """:class:`MissingData` unless ``path`` is an existing, non-empty file (the one line the
    command line prints names it and what it should have been)."""
    p = os.fspath(path)
    if os.path.isdir(p):
        raise MissingData(f"{p}: is a folder, expected a {what}")
    if not os.path.exists(p):
        raise MissingData(f"{p}: no such {what}")
    if os.path.getsize(p) == 0:
        raise MissingData(f"{p}: empty {what}")


def check_input_dir(path: str | os.PathLike, what: str = "folder") -> None:
    """:class:`MissingData` unless ``path`` is an existing folder."""
    p = os.fspath(path)
    if not os.path.exists(p):
        raise MissingData(f"{p}: no such {what}")
    if not os.path.isdir(p):
        raise MissingData(f"{p}: is a file, expected a {what}")

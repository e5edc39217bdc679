"""Shared fixtures and safety nets.

* ``shared_data``: the path of ``../shared/data``; tests that need it skip with a reason when absent.
* ``db_url``: the store's URL on both engines (parametrised ``sqlite`` / ``postgresql``): a SQLite file
  in the test's folder, or a fresh database on one PostgreSQL server the session starts
  (:class:`hybridloc.server.pgtemp.TempPostgres`; skipped with the reason when PostgreSQL is missing).
* Zenoh safety net: every session opened through ``zenoh.open`` during the run is recorded and any
  still open at the end is closed, because a live session with a callback subscriber keeps the
  interpreter from exiting (see ../shared/notes/zenoh.md, section 6). Tests still close their own.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("HYBRIDLOC_SHARED_DATA", ROOT.parent / "shared" / "data"))

#: Every session opened during the run (Session objects are not weak-referenceable).
_sessions: list = []
_original_open = None


def pytest_configure(config):
    global _original_open
    try:
        import zenoh
    except ImportError:  # pragma: no cover - zenoh is a hard dependency
        return
    _original_open = zenoh.open

    def recording_open(*args, **kwargs):
        s = _original_open(*args, **kwargs)
        _sessions.append(s)
        return s

    zenoh.open = recording_open


def _close_leftovers() -> int:
    n = 0
    for s in _sessions:
        try:
            if not s.is_closed():
                s.close()
                n += 1
        except Exception:  # noqa: BLE001 - best effort at shutdown
            pass
    _sessions.clear()
    return n


def pytest_unconfigure(config):
    n = _close_leftovers()
    if n:
        print(f"\nconftest: closed {n} Zenoh session(s) a test leaked")
    if _original_open is not None:
        import zenoh

        zenoh.open = _original_open


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (clone next to ../shared to run these tests)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def ilc_site1(shared_data) -> Path:
    p = shared_data / "msft-ilc" / "site1"
    if not p.is_dir():
        pytest.skip(f"{p} is absent")
    return p


@pytest.fixture(scope="session")
def pyshoe_dir(shared_data) -> Path:
    p = shared_data / "pyshoe-vicon"
    if not p.is_dir():
        pytest.skip(f"{p} is absent")
    return p


@pytest.fixture(scope="session")
def postgres_server():
    """One throwaway PostgreSQL server for the whole run (started on first use)."""
    from hybridloc.server.pgtemp import TempPostgres, find_binaries

    if find_binaries() is None:
        pytest.skip("PostgreSQL server binaries not found (make test installs Debian's postgresql where it can)")
    try:
        import psycopg  # noqa: F401
    except ImportError:
        pytest.skip("psycopg is not installed (make install)")
    pg = TempPostgres().start()
    try:
        yield pg
    finally:
        pg.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def db_url(request, tmp_path) -> str:
    """The store on each engine: a SQLite file path, or a fresh PostgreSQL database's URL."""
    if request.param == "sqlite":
        return str(tmp_path / "store.db")
    return request.getfixturevalue("postgres_server").database()

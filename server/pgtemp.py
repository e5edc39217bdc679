"""A throwaway PostgreSQL server in a temporary folder, for the test suite and the benchmarks.

Debian's ``postgresql`` package (``make test`` installs it when missing) provides the binaries;
``initdb`` refuses to run as root, so under root every server command runs as the ``postgres`` user
(``runuser``), which then owns the folder. The server listens on 127.0.0.1 at a free port with trust
authentication and ``fsync=off`` (a test cluster: durability across a machine crash is not wanted,
a killed *client* process is what the SIGKILL tests exercise). ``database()`` creates a fresh database
per caller, so tests share one server and never each other's tables.
"""

from __future__ import annotations

import atexit
import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

#: where Debian's package puts the server binaries (one folder per major version)
DEBIAN_PG_ROOT = Path("/usr/lib/postgresql")


def find_binaries() -> Path | None:
    """The newest ``/usr/lib/postgresql/<major>/bin`` with ``initdb`` and ``pg_ctl``, else the ones on
    PATH, else None."""
    if DEBIAN_PG_ROOT.exists():
        dirs = sorted(
            (p for p in DEBIAN_PG_ROOT.glob("*/bin") if (p / "initdb").exists()), key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0
        )
        if dirs:
            return dirs[-1]
    initdb, pg_ctl = shutil.which("initdb"), shutil.which("pg_ctl")
    if initdb and pg_ctl and Path(initdb).parent == Path(pg_ctl).parent:
        return Path(initdb).parent
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class TempPostgres:
    """``with TempPostgres() as pg: url = pg.database("t1")``; stopped and removed on exit."""

    def __init__(self, bin_dir: Path | None = None):
        self.bin = bin_dir or find_binaries()
        if self.bin is None:
            raise RuntimeError("PostgreSQL server binaries not found (Debian: apt-get install postgresql; `make test` does it)")
        self.dir = Path(tempfile.mkdtemp(prefix="hybridloc-pg-"))
        self.data = self.dir / "data"
        self.port = _free_port()
        self.as_root = os.geteuid() == 0
        self._n = 0
        self.running = False

    def _run(self, *args: str) -> subprocess.CompletedProcess:
        cmd = [str(a) for a in args]
        if self.as_root:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            log = self.dir / "log"
            tail = log.read_text()[-2000:] if log.exists() else ""
            raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr.strip()[-1000:]} {tail}")
        return r

    def start(self) -> TempPostgres:
        # stopped when this process exits, whatever the way out: pg_ctl runs the server in a session of
        # its own, so a Ctrl-C that ends this process (a benchmark interrupted) never reaches it and it
        # would run on, its folder left behind (stop() is idempotent: after an explicit stop, nothing)
        atexit.register(self.stop)
        if self.as_root:
            shutil.chown(self.dir, "postgres")
        self._run(self.bin / "initdb", "-D", self.data, "-A", "trust", "-U", "postgres", "--no-sync", "-E", "UTF8")
        self.resume()
        return self

    def url(self, name: str = "postgres") -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/{name}"

    def database(self, prefix: str = "t") -> str:
        """A new empty database; its SQLAlchemy URL."""
        self._n += 1
        name = f"{prefix}{self._n}"
        self._run(self.bin / "createdb", "-h", "127.0.0.1", "-p", str(self.port), "-U", "postgres", name)
        return self.url(name)

    def stop(self) -> None:
        """Stop the server (fast shutdown) and remove its folder."""
        if self.running:
            try:
                self._run(self.bin / "pg_ctl", "-D", self.data, "-m", "fast", "-w", "stop")
            finally:
                self.running = False
        shutil.rmtree(self.dir, ignore_errors=True)

    def pause(self) -> None:
        """Stop the server, keeping its data (``resume`` starts it again on the same port)."""
        self._run(self.bin / "pg_ctl", "-D", self.data, "-m", "fast", "-w", "stop")
        self.running = False

    def resume(self) -> None:
        """Start the server on its port (after ``start``'s initdb, or after ``pause``)."""
        opts = f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 -c fsync=off -c synchronous_commit=off -c max_connections=200"
        self._run(self.bin / "pg_ctl", "-D", self.data, "-o", opts, "-l", self.dir / "log", "-w", "start")
        self.running = True

    def __enter__(self) -> TempPostgres:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

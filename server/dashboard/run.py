"""The dashboard as a running web server: uvicorn on a thread of its own, beside Zenoh and ingest.

:class:`Dashboard` ties the parts together on a Zenoh session and a database: the live hub, the feed
that fills it, the site data, the application; :meth:`Dashboard.start` serves it on HOST:PORT (port 0:
any free port, :attr:`Dashboard.url` names the one taken) and returns once uvicorn listens.

uvicorn runs ``Server.run`` on a daemon thread with its own event loop; it installs no signal
handlers there (only the main thread may), so the hosting command keeps its own SIGTERM/SIGINT
handling and calls :meth:`Dashboard.stop`. WebSockets go through the ``websockets`` library's
sans-I/O implementation (uvicorn alone serves none); open WebSockets are closed after
``timeout_graceful_shutdown`` s at shutdown (uvicorn otherwise waits for them forever).
"""

from __future__ import annotations

import logging
import threading
import time

from ..store import Store
from .app import create_app
from .auth import Access
from .data import SiteData
from .feed import Feed
from .live import LOST_AFTER_S, STALE_AFTER_S, Hub

log = logging.getLogger("hybridloc.dashboard")

#: Largest WebSocket message accepted from a browser, bytes (the page sends none but pings).
WS_MAX_BYTES = 64 * 1024


def parse_listen(text: str) -> tuple[str, int]:
    """HOST:PORT (``[::1]:8080`` for IPv6; PORT 0: any free port) -> (host, port); ValueError otherwise."""
    host, sep, port = str(text).rpartition(":")
    if not sep or not host:
        raise ValueError(f"--http expects HOST:PORT (e.g. 127.0.0.1:8080), got {text!r}")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"--http expects HOST:PORT with a port number, got {text!r}") from None
    if not 0 <= p <= 65535:
        raise ValueError(f"--http port {p} is outside 0-65535")
    return host.strip("[]"), p


def open_session(endpoint: str, security=None):
    """A client session to a running server (as the operator user under its ACL); OSError naming the
    endpoint when it cannot be reached or refuses the credentials."""
    import zenoh

    from hybridloc.wire.zconfig import client_config, zenoh_reason

    try:
        return zenoh.open(client_config(endpoint, security))
    except zenoh.ZError as exc:
        raise OSError(f"cannot reach the server at {endpoint}: {zenoh_reason(exc, security=security)}") from None


class Dashboard:
    def __init__(
        self,
        session,
        store: Store,
        access: Access,
        host: str = "127.0.0.1",
        port: int = 0,
        stale_after_s: float = STALE_AFTER_S,
        lost_after_s: float = LOST_AFTER_S,
        status_every_s: float = 2.0,
        tls_cert: str | None = None,
        tls_key: str | None = None,
    ):
        self.hub = Hub(stale_after_s, lost_after_s)
        self.feed = Feed(session, self.hub, status_every_s=status_every_s)
        self.data = SiteData(store)
        self.access = access
        self.host, self.port = host, port
        self.tls = (tls_cert, tls_key) if tls_cert and tls_key else None
        self.app = create_app(self.hub, self.data, access, on_start=self.feed.start, on_stop=self.feed.stop)
        self._server = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        scheme = "https" if self.tls else "http"
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{scheme}://{host}:{self.port}/"

    def start(self, timeout: float = 20.0) -> Dashboard:
        import uvicorn

        kwargs = {}
        if self.tls:
            kwargs.update(ssl_certfile=self.tls[0], ssl_keyfile=self.tls[1])
        config = uvicorn.Config(
            self.app,
            host=self.host,
            port=self.port,
            ws="websockets-sansio",
            ws_max_size=WS_MAX_BYTES,
            lifespan="on",
            log_level="warning",
            access_log=False,
            timeout_graceful_shutdown=2,
            server_header=False,
            **kwargs,
        )
        if self.port:
            _check_bindable(self.host, self.port)
        self._server = server = uvicorn.Server(config)
        failed: list[BaseException] = []

        def run() -> None:
            try:
                server.run()
            except BaseException as exc:  # noqa: BLE001 - reported to start()
                failed.append(exc)

        self._thread = threading.Thread(target=run, name="hybridloc-dashboard", daemon=True)
        self._thread.start()
        t_end = time.monotonic() + timeout
        while not server.started:
            if failed or not self._thread.is_alive():
                why = f": {failed[0]}" if failed and not isinstance(failed[0], SystemExit) else " (see the web server's message above)"
                raise OSError(f"the dashboard could not listen on {self.host}:{self.port}{why}")
            if time.monotonic() > t_end:
                raise OSError(f"the dashboard did not start within {timeout:g} s")
            time.sleep(0.01)
        if self.port == 0:  # the port the system gave
            self.port = int(server.servers[0].sockets[0].getsockname()[1])
        return self

    def stop(self, timeout: float = 10.0) -> None:
        if self._server is not None:
            self._server.should_exit = True
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("the dashboard's web server did not stop within %.0f s", timeout)
        self._thread = None

    def __enter__(self) -> Dashboard:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def _check_bindable(host: str, port: int) -> None:
    """:class:`OSError` naming ``host:port`` when the page cannot listen there (in use, not this
    machine's address), before the web server tries: it would log the failure and exit with a bare
    status instead."""
    import socket

    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise OSError(f"the dashboard could not listen on {host}:{port}: {exc.strerror}") from None
    family, kind, proto, _, addr = infos[0]
    with socket.socket(family, kind, proto) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the web server does
        try:
            sock.bind(addr)
        except OSError as exc:
            raise OSError(f"the dashboard could not listen on {host}:{port}: {exc.strerror}") from None

"""The dashboard's ASGI application (Starlette): the page, its JSON API, the live WebSocket.

Routes (every one behind the token, see :mod:`.auth`; ``/`` exchanges ``?token=`` for the cookie):

================================  =======================================================================
``GET /``                         the page (``static/index.html``)
``GET /static/...``               the page's ES modules, style sheet and the vendored Leaflet
``GET /api/sites``                the sites the token allows: floors, map version, whether a plan exists
``GET /api/plan?site=S``          the site's floor plan (GeoJSON, site frame, m)
``GET /api/coverage?site&floor``  the radio map's coverage grid of a floor (``&tx=ID``: one transmitter)
``GET /api/transmitters?...``     a floor's transmitters, widest heard first
``GET /api/tracks.csv?site&floor``      the tracks the page shows (raw and corrected), CSV
``GET /api/tracks.geojson?site&floor``  the same as GeoJSON (WGS84 when the site has an origin)
``WS /ws``                        ``snapshot`` then ``delta`` frames, at most 10 per second (:mod:`.live`)
================================  =======================================================================

Every response carries a strict Content-Security-Policy (:data:`CSP`: nothing but the page's own
origin, no inline script or style) and ``Referrer-Policy: no-referrer``. A bad request is answered
4xx with one line of plain text, an unexpected failure 500 with no detail; never a traceback.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import io
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import anyio
from starlette.applications import Starlette
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, PlainTextResponse, RedirectResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocket

from hybridloc.wire.protocol import check_id

from .auth import COOKIE, Access, origin_allowed
from .data import NotFound, SiteData
from .live import Client, Hub

log = logging.getLogger("hybridloc.dashboard")

STATIC = Path(__file__).resolve().parent / "static"
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; connect-src 'self'; "
    "worker-src 'self' blob:; object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'self'"
)
SECURITY_HEADERS = [
    (b"content-security-policy", CSP.encode()),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"x-frame-options", b"DENY"),
]
#: Longest floor name and transmitter id accepted in a query (the wire's own cuts).
MAX_FLOOR_CHARS, MAX_TX_CHARS = 32, 64

_UNAUTHORIZED = "401 Unauthorized: open the dashboard with its token, http://HOST:PORT/?token=TOKEN (printed when the server started)\n"


def _token_of(headers: dict[bytes, bytes]) -> str | None:
    """The token a request carries: its Bearer header, else the dashboard's cookie."""
    auth = headers.get(b"authorization", b"").decode("latin-1")
    if auth.lower().startswith("bearer "):
        return auth[7:].strip()
    for part in headers.get(b"cookie", b"").decode("latin-1").split(";"):
        name, _, value = part.strip().partition("=")
        if name == COOKIE:
            return value
    return None


class Guard:
    """Outermost ASGI middleware: security headers on every response; the token on every route but
    ``/`` (which exchanges it itself); the token and the Origin on every WebSocket handshake. The
    token's sites go to ``scope["state"]["hl_sites"]``."""

    def __init__(self, app, access: Access, extra_origins: tuple[str, ...] = ()):
        self.app = app
        self.access = access
        self.extra_origins = extra_origins

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        ok, sites = self.access.sites_for(_token_of(headers))
        state = scope.setdefault("state", {})
        state["hl_ok"], state["hl_sites"] = ok, sites
        if scope["type"] == "websocket":
            origin = headers.get(b"origin")
            host = headers.get(b"host", b"").decode("latin-1") or None
            if not ok or not origin_allowed(
                None if origin is None else origin.decode("latin-1"), scope.get("scheme", "ws"), host, self.extra_origins
            ):
                await receive()  # websocket.connect
                await send({"type": "websocket.close", "code": 1008})  # before accept: HTTP 403
                return None
            return await self.app(scope, receive, send)

        async def send_with_headers(message):
            if message["type"] == "http.response.start":
                message = dict(message)
                have = {k.lower() for k, _ in message.get("headers", [])}
                message["headers"] = [*message.get("headers", []), *((k, v) for k, v in SECURITY_HEADERS if k not in have)]
            await send(message)

        if not ok and scope["path"] != "/":
            return await PlainTextResponse(_UNAUTHORIZED, status_code=401, headers={"www-authenticate": "Bearer"})(scope, receive, send_with_headers)
        return await self.app(scope, receive, send_with_headers)


def _param(request: Request, name: str, max_chars: int, required: bool = True) -> str | None:
    v = request.query_params.get(name)
    if v is None or v == "":
        if required:
            raise HTTPException(400, f"missing query parameter {name!r}")
        return None
    if len(v) > max_chars or any(ord(ch) < 32 for ch in v):
        raise HTTPException(400, f"query parameter {name!r} is not a valid value (at most {max_chars} printable characters)")
    return v


def _site(request: Request) -> str:
    site = _param(request, "site", 64)
    try:
        check_id(site, "site")
    except ValueError as exc:
        raise HTTPException(400, str(exc)) from None
    allowed = request.state.hl_sites
    if allowed is not None and site not in allowed:
        raise HTTPException(403, f"this token does not allow site {site!r}")
    return site


def create_app(
    hub: Hub,
    data: SiteData,
    access: Access,
    on_start: Callable[[asyncio.AbstractEventLoop], None] | None = None,
    on_stop: Callable[[], None] | None = None,
    extra_origins: tuple[str, ...] = (),
) -> Any:
    """The dashboard as an ASGI application. ``on_start(loop)`` runs in the lifespan once the event
    loop runs (the Zenoh feed starts there: it needs the loop), ``on_stop()`` at shutdown."""

    @contextlib.asynccontextmanager
    async def lifespan(app):
        if on_start is not None:
            on_start(asyncio.get_running_loop())
        try:
            yield
        finally:
            if on_stop is not None:
                on_stop()

    async def index(request: Request) -> Response:
        token = request.query_params.get("token")
        if token is not None:
            ok, _ = access.sites_for(token)
            if not ok:
                return PlainTextResponse("401 Unauthorized: wrong token\n", status_code=401)
            resp = RedirectResponse("/", status_code=303)
            resp.set_cookie(COOKIE, token, httponly=True, samesite="strict", secure=request.url.scheme == "https", path="/")
            return resp
        if not request.state.hl_ok:
            return PlainTextResponse(_UNAUTHORIZED, status_code=401, headers={"www-authenticate": "Bearer"})
        return FileResponse(STATIC / "index.html", headers={"cache-control": "no-store"})

    def _allowed_sites(request: Request) -> list[str]:
        known = set(data.sites()) | set(hub.sites)
        allowed = request.state.hl_sites
        return sorted(known if allowed is None else allowed)

    def sites(request: Request) -> Response:
        out = []
        for s in _allowed_sites(request):
            info = data.site_info(s)
            live = hub.sites.get(s)
            if live is not None and live.map_version is not None and (info["map_version"] or 0) < live.map_version:
                info["map_version"] = live.map_version
            out.append(info)
        return JSONResponse({"sites": out}, headers={"cache-control": "no-store"})

    def plan(request: Request) -> Response:
        site = _site(request)
        doc = data.plan(site)
        if doc is None:
            raise HTTPException(404, f"site {site!r} has no floor plan (hybridloc floorplan import)")
        return JSONResponse(doc)

    def coverage(request: Request) -> Response:
        site, floor, tx = _site(request), _param(request, "floor", MAX_FLOOR_CHARS), _param(request, "tx", MAX_TX_CHARS, required=False)
        try:
            return JSONResponse(data.coverage(site, floor, tx))
        except NotFound as exc:
            raise HTTPException(404, str(exc)) from None

    def transmitters(request: Request) -> Response:
        site, floor = _site(request), _param(request, "floor", MAX_FLOOR_CHARS)
        try:
            return JSONResponse(data.transmitters(site, floor))
        except NotFound as exc:
            raise HTTPException(404, str(exc)) from None

    async def tracks_csv(request: Request) -> Response:
        site, floor = _site(request), _param(request, "floor", MAX_FLOOR_CHARS, required=False)
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["device", "kind", "t", "x", "y", "floor"])
        for tr in hub.shown_tracks(site, floor):
            for t, (x, y), fl in zip(tr["t"], tr["xy"], tr["floor"]):
                w.writerow([tr["device"], tr["kind"], f"{t:.3f}", f"{x:.2f}", f"{y:.2f}", fl or ""])
        name = f"tracks-{site}{'-' + floor if floor else ''}.csv"
        return Response(buf.getvalue(), media_type="text/csv", headers={"content-disposition": f'attachment; filename="{_safe(name)}"'})

    async def tracks_geojson(request: Request) -> Response:
        site, floor = _site(request), _param(request, "floor", MAX_FLOOR_CHARS, required=False)
        shown = hub.shown_tracks(site, floor)
        origin = await asyncio.to_thread(data.origin, site)
        doc = _tracks_geojson(shown, origin)
        name = f"tracks-{site}{'-' + floor if floor else ''}.geojson"
        return Response(json.dumps(doc), media_type="application/geo+json", headers={"content-disposition": f'attachment; filename="{_safe(name)}"'})

    async def live_ws(ws: WebSocket) -> None:
        await ws.accept()
        client = Client(ws.state.hl_sites)
        async with anyio.create_task_group() as tg:

            async def read() -> None:  # notices the browser leaving (a pump blocked in a wait would not)
                while (await ws.receive())["type"] != "websocket.disconnect":
                    pass
                tg.cancel_scope.cancel()

            tg.start_soon(read)
            with contextlib.suppress(Exception):  # a send to a browser that left
                await hub.pump(client, ws.send_text)
            tg.cancel_scope.cancel()

    async def http_error(request: Request, exc: Exception) -> Response:
        assert isinstance(exc, HTTPException)
        return PlainTextResponse(f"{exc.status_code} {exc.detail}\n", status_code=exc.status_code, headers=getattr(exc, "headers", None))

    async def server_error(request: Request, exc: Exception) -> Response:
        log.error("dashboard request %s failed", request.url.path, exc_info=exc)
        return PlainTextResponse("500 Internal Server Error\n", status_code=500)

    app = Starlette(
        routes=[
            Route("/", index),
            Route("/api/sites", sites),
            Route("/api/plan", plan),
            Route("/api/coverage", coverage),
            Route("/api/transmitters", transmitters),
            Route("/api/tracks.csv", tracks_csv),
            Route("/api/tracks.geojson", tracks_geojson),
            WebSocketRoute("/ws", live_ws),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ],
        lifespan=lifespan,
        exception_handlers={HTTPException: http_error, Exception: server_error},
    )
    return Guard(app, access, extra_origins)


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)


def _tracks_geojson(shown: list[dict], origin) -> dict:
    """One LineString per device, kind and run of one floor (site-frame m, or WGS84 with an origin)."""
    import numpy as np

    from hybridloc.io.writers import geojson_collection, track_feature
    from hybridloc.types import Trajectory

    feats = []
    for tr in shown:
        start = 0
        fl = tr["floor"]
        for i in range(1, len(fl) + 1):
            if i == len(fl) or fl[i] != fl[start]:
                if i - start >= 2:
                    traj = Trajectory(np.array(tr["t"][start:i], float), np.array(tr["xy"][start:i], float))
                    feats.append(track_feature(traj, origin, device=tr["device"], track=tr["kind"], floor=fl[start]))
                start = i
    return geojson_collection(feats, origin)

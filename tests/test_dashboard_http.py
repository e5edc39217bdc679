"""The dashboard without a browser: security over HTTP and WebSocket (Starlette's TestClient on httpx),
the coalescing push, the live feed from a real server's Zenoh session, the operator ACL, the vendored
files and the page's pure logic (``node --test``).

Real parts: a real :class:`~hybridloc.server.service.Server` (Zenoh router on a unix socket, SQLite
file, Alembic migrations), a real floor plan (the bundled Indoor Location Competition sample) and a
real radio map built by :func:`hybridloc.radio.radiomap.build_radio_map`.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import shutil
import subprocess
import time
from fnmatch import fnmatch
from pathlib import Path

import numpy as np
import pytest
import zenoh
from starlette.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from hybridloc.errors import BadInput
from hybridloc.server.dashboard.app import CSP, create_app
from hybridloc.server.dashboard.auth import COOKIE, Access, read_tokens_file
from hybridloc.server.dashboard.data import SiteData
from hybridloc.server.dashboard.feed import Feed
from hybridloc.server.dashboard.live import MIN_PUSH_INTERVAL_S, Client, Hub
from hybridloc.server.service import Server
from hybridloc.types import Pose
from hybridloc.wire import codecs as C
from hybridloc.wire import protocol as P
from hybridloc.wire.messages import Batch
from hybridloc.wire.zconfig import Security, client_config, free_port

from .helpers import wait_until

ROOT = Path(__file__).resolve().parents[1]
STATIC = ROOT / "server" / "dashboard" / "static"
TOKEN = "all-sites-token-0123456789"
TOKEN_A = "site-a-only-token-0123456789"
SITE = "siteA"


def _radio_map(site: str):
    """A real radio map of one floor F1 (four transmitters, log-distance RSSI, a seeded survey)."""
    from hybridloc.radio.radiomap import BuildParams, build_radio_map
    from hybridloc.radio.survey import LabelledScan
    from hybridloc.types import RfScan

    rng = np.random.default_rng(7)
    aps = {"ap1": (10, 10), "ap2": (60, 10), "ap3": (10, 40), "ap4": (60, 40)}

    def reading(p):
        return {k: -40 - 30 * np.log10(max(1.0, np.hypot(p[0] - q[0], p[1] - q[1]))) + rng.normal(0, 1.5) for k, q in aps.items()}

    pts = rng.uniform((5, 5), (70, 45), (400, 2))
    refs = [LabelledScan(RfScan(float(i), "wifi", reading(p)), p, 0.5, "F1") for i, p in enumerate(pts)]
    return build_radio_map(refs, site=site, params=BuildParams(cell=2.0))


@pytest.fixture
def server(tmp_path):
    """A real server with siteA's floor plan (the bundled sample's F1) and radio map, and a device's
    rejection stored for siteB's device."""
    import io

    from hybridloc.io.msft import read_ilc_site
    from hybridloc.samples import ILC_SITE1_F1

    srv = Server(f"unixsock-stream/{tmp_path}/srv.sock", str(tmp_path / "s.db")).start()
    try:
        srv.store.save_floor_plan(SITE, read_ilc_site(ILC_SITE1_F1))
        buf = io.BytesIO()
        _radio_map(SITE).save(tmp_path / "m.npz")
        buf.write((tmp_path / "m.npz").read_bytes())
        srv.load_map(SITE, buf.getvalue())
        yield srv
    finally:
        srv.stop()


def _app(srv: Server, access: Access, status_every_s: float = 0.2):
    hub = Hub(stale_after_s=2.0, lost_after_s=30.0)
    feed = Feed(srv.session, hub, status_every_s=status_every_s)
    return create_app(hub, SiteData(srv.store), access, on_start=feed.start, on_stop=feed.stop), hub, feed


def _no_traceback(r) -> None:
    assert "Traceback" not in r.text and 'File "' not in r.text, r.text


def test_token_cookie_csp_and_bad_requests(server):
    app, _, _ = _app(server, Access({TOKEN: None}))
    with TestClient(app) as c:
        # every route answers 401 without the token, with the policy headers
        for path in ("/", "/api/sites", "/static/js/main.js", "/static/vendor/leaflet/leaflet.js", "/api/plan?site=siteA", "/nowhere"):
            r = c.get(path)
            assert r.status_code == 401, path
            assert r.headers["content-security-policy"] == CSP
            _no_traceback(r)
        with pytest.raises(WebSocketDisconnect) as refused:
            with c.websocket_connect("/ws"):
                pass
        assert refused.value.code == 1008
        assert c.get("/?token=wrong-token-0123456789").status_code == 401
        # the token is exchanged for an HttpOnly, SameSite=Strict cookie, and leaves the URL
        r = c.get(f"/?token={TOKEN}", follow_redirects=False)
        assert r.status_code == 303 and r.headers["location"] == "/"
        cookie = r.headers["set-cookie"]
        assert cookie.startswith(f"{COOKIE}=") and "HttpOnly" in cookie and "SameSite=strict" in cookie
        r = c.get("/")  # the cookie now rides along
        assert r.status_code == 200 and '<script type="module" src="/static/js/main.js">' in r.text
        csp = r.headers["content-security-policy"]
        assert "default-src 'self'" in csp and "unsafe-inline" not in csp and "unsafe-eval" not in csp
        assert r.headers["referrer-policy"] == "no-referrer"
        assert "<script>" not in r.text and " style=" not in r.text  # nothing inline for the policy to refuse
        assert c.get("/static/vendor/leaflet/leaflet.js").status_code == 200
        sites = c.get("/api/sites").json()["sites"]
        assert [s["id"] for s in sites] == [SITE] and sites[0]["floors"] == [{"name": "F1", "level": 0}] and sites[0]["map_version"] == 1
        plan = c.get("/api/plan?site=siteA").json()
        assert {f["properties"]["category"] for f in plan["features"]} >= {"floor", "walkable", "walls", "room"}
        cov = c.get("/api/coverage?site=siteA&floor=F1").json()
        assert cov["nx"] * cov["ny"] == len(cov["values"]) and cov["cell"] == 2.0 and cov["vmax"] > cov["vmin"] > 0
        txs = c.get("/api/transmitters?site=siteA&floor=F1").json()["transmitters"]
        assert {t["id"] for t in txs} == {"ap1", "ap2", "ap3", "ap4"}
        one = c.get("/api/coverage?site=siteA&floor=F1&tx=ap1").json()
        assert one["unit"] == "dBm" and -100 < one["vmin"] < one["vmax"] < 0
        # bad input: 4xx with one line of text, never a traceback
        for path, code in (
            ("/api/plan", 400),
            ("/api/plan?site=a%20b", 400),
            ("/api/plan?site=" + "x" * 65, 400),
            ("/api/plan?site=nosuchsite", 404),
            ("/api/coverage?site=siteA", 400),
            ("/api/coverage?site=siteA&floor=F9", 404),
            ("/api/coverage?site=siteA&floor=" + "F" * 40, 400),
            ("/api/coverage?site=siteA&floor=F1&tx=nosuchap", 404),
            ("/api/coverage?site=siteA&floor=F1%00", 400),
            ("/api/transmitters?site=nosuchsite&floor=F1", 404),
            ("/api/tracks.csv", 400),
            ("/nowhere", 404),
        ):
            r = c.get(path)
            assert r.status_code == code, (path, r.status_code, r.text)
            assert r.text.count("\n") <= 1 and r.headers["content-security-policy"] == CSP
            _no_traceback(r)
        assert c.post("/api/sites").status_code == 405
        # a script may send the token as a Bearer header instead
        c.cookies.clear()
        assert c.get("/api/sites", headers={"authorization": f"Bearer {TOKEN}"}).status_code == 200
        assert c.get("/api/sites", headers={"authorization": "Bearer nope"}).status_code == 401


def test_websocket_origin_check(server):
    app, _, _ = _app(server, Access({TOKEN: None}))
    with TestClient(app) as c:
        c.get(f"/?token={TOKEN}")
        for origin in ("http://evil.example", "http://testserver.evil.example", "null"):
            with pytest.raises(WebSocketDisconnect) as refused:
                with c.websocket_connect("/ws", headers={"origin": origin}):
                    pass
            assert refused.value.code == 1008, origin
        for headers in ({"origin": "http://testserver"}, {}):  # the page's own origin; a non-browser client
            with c.websocket_connect("/ws", headers=headers) as ws:
                assert ws.receive_json()["type"] == "snapshot"


def test_tokens_file_limits_sites(server, tmp_path):
    tokens = tmp_path / "tokens"
    tokens.write_text(f"# operators\n{TOKEN_A}: {SITE}\n{TOKEN}: *\n")
    access = Access(read_tokens_file(tokens))
    app, hub, _ = _app(server, access)
    with zenoh.open(client_config(server.endpoint)) as dev, TestClient(app) as c:
        if True:  # the dashboard subscribes in its lifespan: the devices publish after it started
            for site, device in ((SITE, "devA"), ("siteB", "devB")):
                dev.put(P.key_pose(site, device), C.POSE.encode(Pose(1.0, 5.0, 6.0, "F1", np.eye(2))), encoding=C.POSE.encoding)
            assert wait_until(lambda: len(hub.devices) == 2, 10)
            c.get(f"/?token={TOKEN_A}")
            assert [s["id"] for s in c.get("/api/sites").json()["sites"]] == [SITE]
            assert c.get("/api/plan?site=siteB").status_code == 403
            assert c.get("/api/tracks.csv?site=siteB").status_code == 403
            with c.websocket_connect("/ws") as ws:
                snap = ws.receive_json()
            assert [d["id"] for d in snap["devices"]] == ["devA"] and {s["id"] for s in snap["sites"]} == {SITE}
            csv = c.get(f"/api/tracks.csv?site={SITE}&floor=F1")
            assert csv.text.splitlines() == ["device,kind,t,x,y,floor", "devA,raw,1.000,5.00,6.00,F1"]
            assert "attachment" in csv.headers["content-disposition"]
            dev.put(P.key_pose(SITE, "devA"), C.POSE.encode(Pose(2.0, 15.0, 6.0, "F1", None)), encoding=C.POSE.encoding)
            assert wait_until(lambda: len(hub.devices[(SITE, "devA")].points) == 2, 10)
            gj = c.get(f"/api/tracks.geojson?site={SITE}&floor=F1").json()
            (line,) = gj["features"]
            assert line["geometry"]["type"] == "LineString" and line["properties"]["device"] == "devA"
            # the sample's plan has a geodetic origin: WGS84 (RFC 7946), 10 m east is ~1e-4 degrees of longitude
            assert "crs_note" not in gj
            (lon0, lat0), (lon1, lat1) = line["geometry"]["coordinates"]
            assert 0 < lon1 - lon0 < 2e-4 and abs(lat1 - lat0) < 1e-6
            c.cookies.clear()
            c.get(f"/?token={TOKEN}")
            assert {s["id"] for s in c.get("/api/sites").json()["sites"]} == {SITE, "siteB"}


def test_tokens_file_errors_name_the_line(tmp_path):
    f = tmp_path / "t"
    for text, words in (
        ("short: siteA\n", "at least 16"),
        (f"{TOKEN}\n", "token: site1,site2"),
        (f"{TOKEN}:\n", "no site"),
        (f"{TOKEN}: bad site\n", "invalid site"),
        (f"{TOKEN}: a\n{TOKEN}: b\n", "twice"),
        ("# nothing\n", "no token"),
    ):
        f.write_text(text)
        with pytest.raises(BadInput, match=words):
            read_tokens_file(f)


def test_push_is_coalesced_to_ten_frames_per_second():
    """500 poses of 5 devices in 0.5 s reach a browser as at most one frame per 0.1 s; the last frame
    holds the newest pose and every track point arrives once, in order."""

    async def run():
        hub = Hub()
        client = Client(None)
        sent: list[tuple[float, dict]] = []
        loop = asyncio.get_running_loop()

        async def send(text: str) -> None:
            sent.append((loop.time(), json.loads(text)))

        pump = asyncio.create_task(hub.pump(client, send))
        t0 = loop.time()
        for i in range(500):
            hub.apply_pose("s", f"d{i % 5}", Pose(float(i), float(i), 0.0, "F1", None))
            await asyncio.sleep(0.001)
        span = loop.time() - t0
        await asyncio.sleep(3 * MIN_PUSH_INTERVAL_S)
        pump.cancel()
        await asyncio.gather(pump, return_exceptions=True)
        return sent, span

    sent, span = asyncio.run(run())
    times = [t for t, _ in sent]
    gaps = np.diff(times)
    assert gaps.min() >= MIN_PUSH_INTERVAL_S - 0.01, gaps.min()  # event-loop timer resolution: 10 ms
    assert len(sent) <= 1 + int(span / MIN_PUSH_INTERVAL_S) + 3
    got: dict[str, list[float]] = {}
    for _, frame in sent:
        for d in frame["devices"]:
            got.setdefault(d["id"], []).extend(p[3] for p in d.get("pts", []))
    for k in range(5):
        assert got[f"d{k}"] == [float(i) for i in range(k, 500, 5)]  # each point once, in order
    last = {d["id"]: d["x"] for _, f in sent for d in f["devices"]}
    assert last["d4"] == 499.0


def test_live_feed_from_zenoh_to_the_websocket(server):
    """A device's pose (with its covariance), its stored rejections (status), and the server's own
    progress and map-version puts reach the browser over the WebSocket."""
    from hybridloc.wire.messages import MapVersion, Progress

    app, hub, feed = _app(server, Access({TOKEN: None}))
    with TestClient(app) as c, zenoh.open(client_config(server.endpoint)) as dev:
        c.get(f"/?token={TOKEN}")
        with c.websocket_connect("/ws") as ws:
            assert ws.receive_json()["type"] == "snapshot"
            cov = np.array([[2.0, 0.5], [0.5, 1.0]])
            dev.put(P.key_pose(SITE, "dev1"), C.POSE.encode(Pose(10.0, 12.5, 7.25, "F1", cov)), encoding=C.POSE.encoding)
            # an out-of-order batch: a stored rejection, reported per device by the status
            dev.put(P.key_batch(SITE, "dev1"), C.BATCH.encode(Batch(SITE, "dev1", 5)), encoding=C.BATCH.encoding)
            server.session.put(P.key_progress(SITE), C.PROGRESS.encode(Progress(SITE, "solve", "F1", 2, 7, time.time())))
            server.session.put(P.key_map_version(SITE), C.MAP_VERSION.encode(MapVersion(SITE, 3, "slam", time.time(), 4, 0.5)))
            dev.put(P.key_pose(SITE, "dev1"), b"{not json")  # refused and counted, nothing else
            seen: dict = {}
            t_end = time.monotonic() + 15
            while time.monotonic() < t_end and not (seen.get("rej") and seen.get("progress") and seen.get("version") == 3):
                frame = ws.receive_json()
                for d in frame["devices"]:
                    if d["id"] == "dev1":
                        seen.setdefault("pose", d) if "x" in d else None
                        if d.get("rej"):
                            seen["rej"] = d["rej"]
                for s in frame["sites"]:
                    if s.get("progress"):
                        seen["progress"] = s["progress"]
                    seen["version"] = s.get("map_version")
    pose = seen["pose"]
    assert (pose["x"], pose["y"], pose["floor"], pose["cov"]) == (12.5, 7.25, "F1", [2.0, 0.5, 1.0])
    assert seen["rej"] == {"out-of-order": 1}
    assert seen["progress"]["stage"] == "solve" and (seen["progress"]["done"], seen["progress"]["total"]) == (2, 7)
    assert seen["version"] == 3
    assert feed.counts["refused:malformed-json"] == 1 and feed.counts["status"] >= 1


def test_operator_user_hears_and_asks_but_never_touches_batches_or_acks(tmp_path):
    """Under --acl-devices the operator (the dashboard's user) hears poses and may ask the status; its
    put on a device's batch key is never stored, and it hears no ack."""
    users = tmp_path / "users"
    users.write_text("server:srvpw\ndev01:pw1\noperator:oppw\n")
    ep = f"tcp/127.0.0.1:{free_port()}"
    srv = Server(ep, str(tmp_path / "s.db"), Security(users_file=str(users), acl_devices=["dev01", "operator"])).start()
    try:
        with (
            zenoh.open(client_config(ep, Security(user="dev01", password="pw1"))) as dev,
            zenoh.open(client_config(ep, Security(user="operator", password="oppw"))) as op,
        ):
            poses = op.declare_subscriber(f"{P.PREFIX}/*/*/pose", zenoh.handlers.FifoChannel(100))
            acks = op.declare_subscriber(f"{P.PREFIX}/*/*/ack", zenoh.handlers.FifoChannel(100))
            time.sleep(0.3)  # the declarations reach the router before the puts
            dev.put(P.key_pose(SITE, "dev01"), C.POSE.encode(Pose(1.0, 2.0, 3.0, "F1", None)))
            dev.put(P.key_batch(SITE, "dev01"), C.BATCH.encode(Batch(SITE, "dev01", 1)))
            op.put(P.key_batch(SITE, "dev01"), C.BATCH.encode(Batch(SITE, "dev01", 2)))  # refused by the ACL
            got = []
            assert wait_until(lambda: (s := poses.try_recv()) is not None and got.append(s) is None, 5)
            assert C.POSE.decode(got[0].payload.to_bytes()).x == 2.0
            assert wait_until(lambda: srv.store.last_seq("dev01") == 1, 5)
            replies = [r for r in op.get(P.KEY_STATUS, timeout=5.0) if r.ok]
            assert replies and C.STATUS.decode(replies[0].ok.payload.to_bytes()).counts["batches-persisted"] == 1
            time.sleep(0.5)
            assert acks.try_recv() is None  # the device's ack never reaches the operator
            assert srv.store.last_seq("dev01") == 1  # the operator's batch was never stored
            poses.undeclare()
            acks.undeclare()
    finally:
        srv.stop()


def test_cli_refuses_bad_dashboard_options(tmp_path, capsys):
    from hybridloc.cli import main

    db = str(tmp_path / "s.db")
    for argv, words in (
        (["serve", "--db", db, "--http", "nowhere"], "HOST:PORT"),
        (["serve", "--db", db, "--http", "127.0.0.1:99999"], "outside"),
        (["serve", "--db", db, "--http", "127.0.0.1:0", "--http-token", "short"], "at least 16"),
        (["serve", "--db", db, "--http", "127.0.0.1:0", "--http-stale", "30", "--http-lost", "10"], "longer than"),
        (["serve", "--db", db, "--http", "127.0.0.1:0", "--http-tokens", str(tmp_path / "none")], "no such tokens file"),
        (["dashboard", "--db", str(tmp_path / "none.db"), "--http", "127.0.0.1:0"], "no such database"),
        (["dashboard", "--db", db], "--http"),
    ):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err and "Traceback" not in err, (argv, err)


def test_dashboard_on_a_port_in_use_says_so_in_one_line(tmp_path, capsys):
    """The page's port taken by another program: exit 2 and one error line naming it (the web server's
    own log line and bare exit status are not shown), the server stopped behind it."""
    import socket

    from hybridloc.cli import main
    from hybridloc.wire.zconfig import free_port

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        argv = ["serve", "--endpoint", f"tcp/127.0.0.1:{free_port()}", "--db", str(tmp_path / "s.db"), "--ingest-workers", "0"]
        assert main([*argv, "--http", f"127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"127.0.0.1:{port}" in err and "in use" in err and "Traceback" not in err, err


def test_vendored_leaflet_matches_its_manifest_and_ships_in_the_package():
    import tomllib

    manifest = json.loads((STATIC / "vendor" / "MANIFEST.json").read_text())
    lf = manifest["leaflet"]
    assert lf["version"] == "1.9.4"
    for rel, sha in lf["files"].items():
        assert hashlib.sha256((STATIC / "vendor" / "leaflet" / rel).read_bytes()).hexdigest() == sha, rel
    assert "BSD 2-Clause" in (STATIC / "vendor" / "leaflet" / "LICENSE").read_text()
    assert json.loads((STATIC / "vendor" / "leaflet" / "package.json").read_text())["version"] == "1.9.4"
    # every file of the page is package data (the wheel ships it), and the page's own modules import
    # nothing bare (no bundler, no import map)
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["hybridloc.server.dashboard"]
    for f in STATIC.rglob("*"):
        if f.is_file():
            rel = f.relative_to(STATIC.parent).as_posix()
            assert any(fnmatch(rel, p) and rel.count("/") == p.count("/") for p in patterns), rel
    import re

    for js in (STATIC / "js").glob("*.js"):
        specs = re.findall(r"""(?:\bfrom|^import)\s*["']([^"']+)["']""", js.read_text(), flags=re.M)
        assert all(s.startswith("./") for s in specs), f"{js.name}: bare imports {specs}"


def test_page_logic_under_node():
    node = shutil.which("node")
    if node is None:
        pytest.skip("Node is not installed: the page's pure logic (tests/js/) is not run")
    r = subprocess.run([node, "--test", str(ROOT / "tests" / "js")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-2000:]
    assert "# fail 0" in r.stdout

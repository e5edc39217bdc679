"""The dashboard in a real browser: Playwright for Python driving Debian's chromium (no browser download)
against a real ``hybridloc serve --http`` on loopback, with the Indoor Location Competition's site1
(three floors: its floor plan, a radio map built from real surveys of F1 and F2), simulated devices
publishing poses through Zenoh and a real ``hybridloc client phone`` replaying a site1 walk.

Every wait is on DOM state the page keeps for tests (body[data-floor], body[data-markers],
tr[data-device], body[data-coverage], body[data-map-version]; Playwright's ``expect`` polls them),
never a sleep. Skipped, with the reason, where chromium, Playwright or ../shared/data is missing
(``make test`` installs chromium with apt where it can).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = os.environ.get("DASHBOARD_CHROMIUM", "/usr/bin/chromium")
TOKEN = "browser-test-token-0123456789"
SITE = "site1"

pytestmark = pytest.mark.shared_data
if not Path(CHROMIUM).is_file():
    pytest.skip(f"no chromium at {CHROMIUM} (make test installs Debian's chromium with apt where it can)", allow_module_level=True)
playwright_sync = pytest.importorskip("playwright.sync_api", reason="Playwright is not installed (make install: the test extra)")


def _traces(site_dir: Path, floor: str, k: int) -> list[str]:
    return sorted(str(p) for p in (site_dir / floor / "path_data_files").glob("*.txt*"))[:k]


class Devices:
    """Simulated devices on one Zenoh client session: each publishes a pose (with its covariance) 10
    times a second from a thread, walking a small circle around its floor's walkable centroid."""

    def __init__(self, endpoint: str, centres: dict[str, tuple[float, float]]):
        import zenoh

        from hybridloc.wire.zconfig import client_config

        self.session = zenoh.open(client_config(endpoint))
        self.centres = centres
        self.floor = {"simA": "F1", "simB": "F2"}
        self.silent: set[str] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from hybridloc.types import Pose
        from hybridloc.wire import codecs as C
        from hybridloc.wire import protocol as P

        k = 0
        cov = np.array([[4.0, 1.5], [1.5, 2.0]])
        while not self._stop.wait(0.1):
            k += 1
            for dev, floor in list(self.floor.items()):
                if dev in self.silent:
                    continue
                cx, cy = self.centres[floor]
                a = 0.05 * k + (0.0 if dev == "simA" else np.pi)
                pose = Pose(0.1 * k, cx + 4.0 * np.cos(a), cy + 4.0 * np.sin(a), floor, cov)
                self.session.put(P.key_pose(SITE, dev), C.POSE.encode(pose), encoding=C.POSE.encoding)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.session.close()


@pytest.fixture(scope="module")
def site(ilc_site1, tmp_path_factory):
    """A database holding site1's floor plan and a radio map built from 3 surveys each of F1 and F2."""
    from hybridloc.io.msft import read_ilc_site
    from hybridloc.radio.radiomap import BuildParams, build_radio_map
    from hybridloc.radio.sources import labelled_from_inputs
    from hybridloc.server.store import Store

    tmp = tmp_path_factory.mktemp("dash")
    db = tmp / "server.db"
    plan = read_ilc_site(ilc_site1)
    labelled, _, _ = labelled_from_inputs("msft", _traces(ilc_site1, "F1", 3) + _traces(ilc_site1, "F2", 3), str(ilc_site1))
    rmap = build_radio_map(labelled, site=SITE, plan=plan, params=BuildParams())
    rmap.save(tmp / "map.npz")
    st = Store(str(db))
    st.save_floor_plan(SITE, plan)
    st.save_map(SITE, (tmp / "map.npz").read_bytes(), source="survey")
    st.close()
    centres = {f.name: (f.walkable.centroid.x, f.walkable.centroid.y) for f in plan.floors}
    return tmp, db, centres


@pytest.fixture(scope="module")
def served(site):
    """``hybridloc serve --http 127.0.0.1:0`` (stale after 2 s), the simulated devices, and a real phone
    client replaying a site1 F1 walk; (URL, endpoint, db, devices, server process)."""
    from hybridloc.wire.zconfig import free_port

    tmp, db, centres = site
    ep = f"tcp/127.0.0.1:{free_port()}"
    cmd = [sys.executable, "-m", "hybridloc.cli", "serve", "--endpoint", ep, "--db", str(db), "--site", SITE, "--no-slam"]
    cmd += ["--http", "127.0.0.1:0", "--http-token", TOKEN, "--http-stale", "2", "--http-lost", "30"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp)
    lines = []
    while not lines or not lines[-1].startswith("hybridloc dashboard on"):
        line = proc.stdout.readline()
        if not line:
            pytest.fail(f"the server ended before its dashboard started: {lines}")
        lines.append(line.strip())
    url = re.search(r"(http://\S+/)", lines[-1]).group(1)
    threading.Thread(target=proc.stdout.read, daemon=True).start()  # drain
    devices = Devices(ep, centres)
    from hybridloc.samples import ILC_SITE1_F1  # a real site1 F1 walk (bundled), replayed by the real client

    walk = sorted((ILC_SITE1_F1 / "F1" / "path_data_files").glob("*.txt*"))[5]
    phone = subprocess.Popen(
        [sys.executable, "-m", "hybridloc.cli", "client", "phone", "--endpoint", ep, "--site", SITE, "--device", "phone1"]
        + ["--replay", str(walk), "--speed", "2", "--spool", str(tmp / "spool")],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=tmp,
    )
    try:
        yield url, ep, db, devices, proc
    finally:
        phone.terminate()
        phone.wait(20)
        devices.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(20)


@pytest.fixture(scope="module")
def browser():
    with playwright_sync.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM)
        try:
            yield b
        finally:
            b.close()


def test_live_page_floors_coverage_staleness_follow(served, browser, tmp_path):
    from playwright.sync_api import expect

    url, ep, db, devices, _ = served
    page = browser.new_page(viewport={"width": 1400, "height": 850})
    problems: list[str] = []
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type in ("error", "warning") else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    page.goto(f"{url}?token={TOKEN}")
    expect(page).to_have_url(url)  # the token was exchanged for the cookie and left the address bar
    body = page.locator("body")
    row = lambda d: page.locator(f'tr[data-device="{d}"]')  # noqa: E731

    # the devices on their floors; the map and the list agree on who is on the shown floor
    expect(body).to_have_attribute("data-floor", "F1")
    expect(body).to_have_attribute("data-map-version", "1")
    expect(row("simA")).to_have_attribute("data-state", "live")
    expect(row("simA").locator("td.floor")).to_have_text("F1")
    expect(row("simB").locator("td.floor")).to_have_text("F2")
    expect(row("simA")).to_have_attribute("data-ellipse", "1")
    page.wait_for_function(
        "() => document.body.dataset.markers === String([...document.querySelectorAll('tr[data-device]')]"
        ".filter(r => r.querySelector('td.floor').textContent === 'F1').length)"
    )
    assert int(body.get_attribute("data-markers")) >= 1
    expect(page.locator('button[data-floor-button="F3"] .count')).to_have_text("0")
    expect(page.locator('button[data-floor-button="F2"] .count')).to_have_text(re.compile(r"^[12]$"))

    # the coverage layer is drawn for the shown floor and follows a floor switch
    page.check("#show-coverage")
    expect(body).to_have_attribute("data-coverage", "F1")
    expect(page.locator("img.cov")).to_have_count(1)
    page.click('button[data-floor-button="F2"]')
    expect(body).to_have_attribute("data-floor", "F2")
    expect(body).to_have_attribute("data-coverage", "F2")
    expect(page.locator("img.cov")).to_have_count(1)
    page.wait_for_function("() => Number(document.body.dataset.markers) >= 1")  # simB
    # switches faster than the answers come: only the shown floor's layer is ever drawn
    page.evaluate("['F1', 'F2', 'F1'].forEach(f => document.querySelector(`button[data-floor-button=\"${f}\"]`).click())")
    page.wait_for_load_state("networkidle")
    expect(body).to_have_attribute("data-floor", "F1")
    expect(body).to_have_attribute("data-coverage", "F1")
    expect(page.locator("img.cov")).to_have_count(1)
    # a floor the map has no cell on: no layer, a note
    page.click('button[data-floor-button="F3"]')
    expect(body).to_have_attribute("data-coverage-empty", "F3")
    expect(page.locator("img.cov")).to_have_count(0)
    assert body.get_attribute("data-coverage") is None

    # a device that stops publishing turns stale (after --http-stale 2 s)
    devices.silent.add("simB")
    expect(row("simB")).to_have_attribute("data-state", "stale", timeout=10_000)
    expect(row("simA")).to_have_attribute("data-state", "live")

    # follow a device: the page switches to its floor, and again when it changes floor
    row("simA").locator("td.follow button").click()
    expect(body).to_have_attribute("data-follow", "simA")
    expect(body).to_have_attribute("data-floor", "F1")
    devices.floor["simA"] = "F3"
    expect(body).to_have_attribute("data-floor", "F3", timeout=10_000)
    expect(row("simA").locator("td.floor")).to_have_text("F3")

    # a refused message is counted per device (the server's status), a new map version shown
    from hybridloc.server.store import Store
    from hybridloc.wire import protocol as P

    devices.session.put(P.key_batch(SITE, "simA"), b"{not json")
    expect(row("simA")).to_have_attribute("data-rejections", "1", timeout=10_000)
    st = Store(str(db), migrate=False)
    st.save_map(SITE, st.load_map(SITE)[1], source="import")
    st.close()
    expect(body).to_have_attribute("data-map-version", "2", timeout=10_000)

    # the real phone client: its pose, with the covariance its filter publishes
    expect(row("phone1")).to_have_attribute("data-ellipse", "1", timeout=30_000)

    # the shown tracks download (the cookie rides along)
    r = page.request.get(f"{url}api/tracks.csv?site={SITE}&floor=F3")
    assert r.status == 200 and "simA,raw," in r.text()
    r = page.request.get(f"{url}api/tracks.geojson?site={SITE}&floor=F3")
    assert r.status == 200 and r.json()["features"][0]["properties"]["device"] == "simA"

    shot = tmp_path / "dashboard.png"
    page.click('button[data-floor-button="F1"]')  # a person's view: F1 with its coverage
    expect(body).to_have_attribute("data-coverage", "F1")
    page.screenshot(path=str(shot))
    if os.environ.get("DASHBOARD_SHOT"):
        shutil.copy(shot, os.environ["DASHBOARD_SHOT"])
    assert shot.stat().st_size > 20_000
    assert problems == [], problems  # no CSP violation, no 404, no script error
    page.close()


def test_wrong_token_and_cross_origin_websocket_refused_then_shutdown_with_a_page_open(served, browser):
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    url, _, _, _, proc = served
    page = browser.new_page()
    assert page.goto(f"{url}?token=wrong-token-0123456789").status == 401
    assert page.goto(url).status == 401  # no cookie: the page itself is refused
    assert page.goto(f"{url}?token={TOKEN}").status == 200
    ws_url = url.replace("http://", "ws://") + "ws"
    cookie = f"hybridloc_dashboard={TOKEN}"
    with pytest.raises(InvalidStatus) as refused:
        connect(ws_url, origin="http://evil.example", additional_headers={"Cookie": cookie}, open_timeout=5).close()
    assert refused.value.response.status_code == 403
    with pytest.raises(InvalidStatus):
        connect(ws_url, origin=url.rstrip("/"), open_timeout=5).close()  # the right origin without the cookie
    with connect(ws_url, origin=url.rstrip("/"), additional_headers={"Cookie": cookie}, open_timeout=5) as ws:
        assert '"type":"snapshot"' in ws.recv(timeout=5)
    # the server stops promptly with a browser still connected (open WebSockets closed after 2 s)
    page.wait_for_function("() => document.body.dataset.connected === '1'")
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(20) == 0
    page.close()

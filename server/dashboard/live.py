"""The dashboard's live state and its coalescing push to browsers (asyncio; no Zenoh, no database).

Everything here runs on the dashboard's event loop. Zenoh callbacks never call into it directly:
they hand decoded records over with ``loop.call_soon_threadsafe(hub.apply_*, ...)``
(:mod:`.feed`), so no lock is needed and no Zenoh thread ever waits for the loop.

State: per (site, device) the newest pose (position, 2x2 covariance, floor), the server's wall-clock
time it arrived (what staleness is measured from), a ring of recent raw track points, the newest
corrected track (the crowd SLAM's ``track`` message) and the newest fix's containment region; per
site the newest map version and the running job's progress; from the server's status the devices
online, their rejection counts and the sites' SLAM figures.

Push: each browser has a :class:`Client` holding what it was last sent (a revision per device and
per site, the last raw track point per device). A change bumps a revision and wakes every client;
a client's pump then sends one ``delta`` with everything newer than what it holds and sleeps until
:data:`MIN_PUSH_INTERVAL_S` has passed since that send began. So a browser gets at most 10 frames per
second whatever the input rate, never a stale intermediate state (a frame is built from the newest
state when it is sent), and a slow browser delays only itself: while its send waits, changes pile
up as revisions, not as queued frames (memory is bounded by the number of devices).
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

#: Shortest time between two frames to one browser, s: at most 10 updates per second.
MIN_PUSH_INTERVAL_S = 0.1
#: Raw track points kept per device (a pose per step: ~2.5 minutes of walking at 2 steps/s).
TRACK_POINTS = 300
#: Points of a corrected track sent to browsers (the newest; the server keeps 10,000 on the wire).
CORRECTED_POINTS = 1000
#: Default staleness thresholds of the page, s since the newest pose or fix arrived.
STALE_AFTER_S = 10.0
LOST_AFTER_S = 60.0


def _r(v: float) -> float:
    """Metres rounded to cm for the browser (the page draws at cm at most)."""
    return round(float(v), 2)


@dataclass
class DeviceLive:
    site: str
    device: str
    t: float | None = None  # pose time, s (device clock)
    x: float | None = None
    y: float | None = None
    floor: str | None = None
    cov: tuple[float, float, float] | None = None  # upper triangle xx, xy, yy, m^2
    seen: float = 0.0  # server wall clock (Unix s) of the newest pose or fix
    points: deque = field(default_factory=lambda: deque(maxlen=TRACK_POINTS))  # (seq, t, x, y, floor)
    next_point: int = 1
    corrected: dict | None = None  # the page's form of the newest corrected track
    region: dict | None = None  # {"floor", "mass", "geometry"} of the newest fix with one
    fix_floor_prob: float | None = None
    rev: int = 0  # revision of the fields above (but the points, sent by sequence number)
    corr_rev: int = 0
    region_rev: int = 0


@dataclass
class SiteLive:
    site: str
    map_version: int | None = None
    map_source: str | None = None
    map_created_at: float | None = None
    progress: dict | None = None
    slam: dict | None = None
    rev: int = 0


@dataclass(eq=False)
class Client:
    """One browser: the sites it may see (None: all), what it was sent, a wake-up event."""

    sites: frozenset[str] | None
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    sent_rev: dict = field(default_factory=dict)  # (site, device) -> rev
    sent_point: dict = field(default_factory=dict)  # (site, device) -> last point seq sent
    sent_corr: dict = field(default_factory=dict)
    sent_region: dict = field(default_factory=dict)
    sent_site: dict = field(default_factory=dict)
    sent_status: int = -1
    frames: int = 0

    def may_see(self, site: str) -> bool:
        return self.sites is None or site in self.sites


class Hub:
    """The live state and the browsers it is pushed to (module docstring). Loop thread only."""

    def __init__(self, stale_after_s: float = STALE_AFTER_S, lost_after_s: float = LOST_AFTER_S, clock: Callable[[], float] = time.time):
        if not 0 < stale_after_s < lost_after_s:
            raise ValueError(f"staleness thresholds must be 0 < stale ({stale_after_s:g} s) < lost ({lost_after_s:g} s)")
        self.stale_after_s = stale_after_s
        self.lost_after_s = lost_after_s
        self.clock = clock
        self.devices: dict[tuple[str, str], DeviceLive] = {}
        self.sites: dict[str, SiteLive] = {}
        self.online: frozenset[str] = frozenset()
        self.rejections: dict[str, dict[str, int]] = {}
        self.status_rev = 0
        self.status_at: float | None = None
        self.clients: set[Client] = set()
        self.counts: dict[str, int] = {}
        self._rev = itertools.count(1)

    # ------------------------------------------------------------------ input (from the feed)
    def _count(self, key: str) -> None:
        self.counts[key] = self.counts.get(key, 0) + 1

    def _device(self, site: str, device: str) -> DeviceLive:
        d = self.devices.get((site, device))
        if d is None:
            d = self.devices[(site, device)] = DeviceLive(site, device)
            self._site(site)
        return d

    def _site(self, site: str) -> SiteLive:
        s = self.sites.get(site)
        if s is None:
            s = self.sites[site] = SiteLive(site)
            s.rev = next(self._rev)
        return s

    def _wake(self) -> None:
        for c in self.clients:
            c.wake.set()

    def apply_pose(self, site: str, device: str, pose, received: float | None = None) -> None:
        """A device's live pose (:class:`hybridloc.types.Pose`)."""
        d = self._device(site, device)
        d.t, d.x, d.y, d.floor = float(pose.t), float(pose.x), float(pose.y), pose.floor
        c = pose.cov
        d.cov = None if c is None else (float(c[0][0]), float(c[0][1]), float(c[1][1]))
        d.seen = self.clock() if received is None else received
        d.points.append((d.next_point, d.t, d.x, d.y, d.floor))
        d.next_point += 1
        d.rev = next(self._rev)
        self._count("poses")
        self._wake()

    def apply_fix(self, site: str, device: str, fix, received: float | None = None) -> None:
        """The server's answer to a device's scan (:class:`hybridloc.types.Fix`): its containment
        region is drawn; a device with no pose yet is placed at the fix."""
        self._count("fixes")
        if fix.fix is None:
            return
        from shapely.geometry import mapping

        d = self._device(site, device)
        f = fix.fix
        d.seen = self.clock() if received is None else received
        if d.x is None:  # a device whose client publishes no pose: the fix is its position
            d.t, d.x, d.y, d.floor = float(f.t), float(f.pos_enu[0]), float(f.pos_enu[1]), f.floor
            d.cov = (float(f.cov[0, 0]), float(f.cov[0, 1]), float(f.cov[1, 1]))
        d.fix_floor_prob = float(f.floor_prob)
        if fix.region is not None:
            geom = json.loads(json.dumps(mapping(fix.region.area)))  # tuples -> lists
            d.region = {"floor": fix.region.floor, "mass": float(fix.region.mass), "geometry": _round_geometry(geom)}
            d.region_rev = next(self._rev)
        d.rev = next(self._rev)
        self._wake()

    def apply_track(self, site: str, device: str, track) -> None:
        """The crowd SLAM's corrected track of the device's walk (:class:`hybridloc.wire.messages.Track`);
        a newer run of the same walk, or another walk, replaces it."""
        self._count("tracks")
        d = self._device(site, device)
        tr = track.track
        if d.corrected is not None and d.corrected["walk"] == track.walk_id and d.corrected["run"] >= track.run:
            return  # an older or repeated run
        if tr.anchored == "relative" or len(tr) == 0:
            return  # a shape in its own frame, never a position
        start = max(0, len(tr) - CORRECTED_POINTS)
        d.corrected = {
            "walk": int(track.walk_id),
            "run": int(track.run),
            "anchored": tr.anchored,
            "map_version": track.map_version,
            "t": [round(float(v), 3) for v in tr.t[start:]],
            "xy": [[_r(p[0]), _r(p[1])] for p in tr.pos_enu[start:]],
            "floor": list(tr.floor[start:]),
        }
        d.corr_rev = next(self._rev)
        d.rev = next(self._rev)
        self._wake()

    def apply_map_version(self, mv) -> None:
        s = self._site(mv.site)
        if s.map_version is not None and mv.version < s.map_version:
            return
        s.map_version, s.map_source, s.map_created_at = int(mv.version), mv.source, float(mv.created_at)
        s.rev = next(self._rev)
        self._count("map-versions")
        self._wake()

    def apply_progress(self, p) -> None:
        s = self._site(p.site)
        s.progress = {"stage": p.stage, "floor": p.floor, "done": int(p.done), "total": int(p.total), "t": float(p.t)}
        s.rev = next(self._rev)
        self._count("progress")
        self._wake()

    def apply_statuses(self, statuses: Iterable) -> None:
        """The servers' answers to a status query (one per server process on the mesh)."""
        online: set[str] = set()
        rejections: dict[str, dict[str, int]] = {}
        for st in statuses:
            online.update(st.online)
            for dev, by in st.rejections.items():
                rejections.setdefault(dev, {}).update(by)
            for site, v in (st.db.get("maps") or {}).items():
                s = self._site(site)
                if s.map_version is None or int(v) > s.map_version:
                    s.map_version = int(v)
                    s.rev = next(self._rev)
            for site, sm in st.slam.items():
                s = self._site(site)
                slim = {
                    k: sm.get(k) for k in ("walks_corrected", "walks_relative", "walks_quarantined", "walks_pending", "loops_accepted", "coverage")
                }
                busy = (sm.get("worker") or {}).get("busy")
                slim["busy"] = busy or None
                if s.slam != slim:
                    s.slam = slim
                    s.rev = next(self._rev)
                if sm.get("map_source") and s.map_source is None and sm.get("map_version") == s.map_version:
                    s.map_source = sm["map_source"]
        self.status_at = self.clock()
        if frozenset(online) != self.online or rejections != self.rejections:
            self.online, self.rejections = frozenset(online), rejections
            self.status_rev = next(self._rev)
            for d in self.devices.values():
                d.rev = next(self._rev)  # online and rejections are shown per device
        self._count("statuses")
        self._wake()

    # ------------------------------------------------------------------ output (to browsers)
    def _device_entry(self, c: Client, key: tuple[str, str], d: DeviceLive, full: bool) -> dict:
        e: dict[str, Any] = {"id": d.device, "site": d.site, "floor": d.floor, "seen": round(d.seen, 3)}
        if d.x is not None:
            e.update(t=d.t, x=_r(d.x), y=_r(d.y))
            e["cov"] = None if d.cov is None else [round(v, 4) for v in d.cov]
        e["online"] = d.device in self.online
        e["rej"] = self.rejections.get(d.device, {})
        last = 0 if full else c.sent_point.get(key, 0)
        pts = [[_r(x), _r(y), fl, t] for seq, t, x, y, fl in d.points if seq > last]
        if full or pts:
            e["pts"] = pts
            if full or (d.points and d.points[0][0] > last + 1):  # points the browser missed fell off the ring
                e["reset"] = True
        if d.points:
            c.sent_point[key] = d.points[-1][0]
        if full or c.sent_corr.get(key, 0) < d.corr_rev:
            e["corr"] = d.corrected
            c.sent_corr[key] = d.corr_rev
        if full or c.sent_region.get(key, 0) < d.region_rev:
            e["region"] = d.region
            c.sent_region[key] = d.region_rev
        c.sent_rev[key] = d.rev
        return e

    @staticmethod
    def _site_entry(s: SiteLive) -> dict:
        return {
            "id": s.site,
            "map_version": s.map_version,
            "map_source": s.map_source,
            "progress": s.progress,
            "slam": s.slam,
        }

    def snapshot(self, c: Client) -> dict:
        """Everything the client may see (the first frame of a connection)."""
        c.sent_rev.clear()
        c.sent_point.clear()
        c.sent_corr.clear()
        c.sent_region.clear()
        c.sent_site.clear()
        devices = [self._device_entry(c, k, d, True) for k, d in self.devices.items() if c.may_see(d.site)]
        sites = []
        for s in self.sites.values():
            if c.may_see(s.site):
                sites.append(self._site_entry(s))
                c.sent_site[s.site] = s.rev
        c.sent_status = self.status_rev
        c.frames += 1
        return {
            "type": "snapshot",
            "now": round(self.clock(), 3),
            "stale_s": self.stale_after_s,
            "lost_s": self.lost_after_s,
            "sites": sites,
            "devices": devices,
        }

    def delta(self, c: Client) -> dict | None:
        """What changed since the client's last frame, or None."""
        devices = [self._device_entry(c, k, d, False) for k, d in self.devices.items() if c.may_see(d.site) and c.sent_rev.get(k, -1) < d.rev]
        sites = []
        for s in self.sites.values():
            if c.may_see(s.site) and c.sent_site.get(s.site, -1) < s.rev:
                sites.append(self._site_entry(s))
                c.sent_site[s.site] = s.rev
        if not devices and not sites:
            return None
        c.frames += 1
        return {"type": "delta", "now": round(self.clock(), 3), "sites": sites, "devices": devices}

    async def pump(self, c: Client, send: Callable[[str], Awaitable[None]], min_interval_s: float = MIN_PUSH_INTERVAL_S) -> None:
        """Send ``c`` its snapshot, then a delta per wake-up, at most one per ``min_interval_s``.
        Returns when ``send`` raises (the browser left) or the task is cancelled."""
        loop = asyncio.get_running_loop()
        self.clients.add(c)
        try:
            c.wake.clear()
            began = loop.time()
            await send(_dumps(self.snapshot(c)))
            await asyncio.sleep(max(0.0, min_interval_s - (loop.time() - began)))
            while True:
                await c.wake.wait()
                c.wake.clear()
                began = loop.time()
                frame = self.delta(c)
                if frame is not None:
                    await send(_dumps(frame))
                await asyncio.sleep(max(0.0, min_interval_s - (loop.time() - began)))
        finally:
            self.clients.discard(c)

    # ------------------------------------------------------------------ exports
    def shown_tracks(self, site: str, floor: str | None) -> list[dict]:
        """The tracks the page shows for ``site`` on ``floor`` (None: every floor): per device its raw
        points and its corrected track's points on that floor, as {device, kind, t, xy, floor}."""
        out = []
        for (s, dev), d in sorted(self.devices.items()):
            if s != site:
                continue
            raw = [(t, x, y, fl) for _, t, x, y, fl in d.points if floor is None or fl == floor]
            if raw:
                out.append({"device": dev, "kind": "raw", "t": [p[0] for p in raw], "xy": [[p[1], p[2]] for p in raw], "floor": [p[3] for p in raw]})
            if d.corrected is not None:
                c = d.corrected
                keep = [i for i, fl in enumerate(c["floor"]) if floor is None or fl == floor]
                if keep:
                    out.append(
                        {
                            "device": dev,
                            "kind": "corrected",
                            "t": [c["t"][i] for i in keep],
                            "xy": [c["xy"][i] for i in keep],
                            "floor": [c["floor"][i] for i in keep],
                        }
                    )
        return out


def _round_geometry(g: dict) -> dict:
    def rnd(v):
        if isinstance(v, list):
            return [rnd(x) for x in v]
        return _r(v) if isinstance(v, float) and math.isfinite(v) else v

    return {"type": g["type"], "coordinates": rnd(g["coordinates"])}


def _dumps(frame: dict) -> str:
    return json.dumps(frame, separators=(",", ":"), allow_nan=False)

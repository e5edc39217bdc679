"""What the dashboard reads from the server's database: sites, floor plans, radio-map coverage.

Read only (the server owns the schema and its migrations). Called from Starlette's thread pool, never
on the event loop. Parsed plans and maps are cached by their row id / version, so a page reload or
a floor switch costs one small query.

Coverage (the heat layer) comes from the site's newest radio map (:mod:`hybridloc.radio.radiomap`):
per floor a grid of cells of ``cell_size`` m. Without a transmitter the value is the cell's support
n_eff, the kernel-weighted number of labelled scans behind the cell's statistics (how much the map
knows there; drawn on a log scale, where at least :data:`MIN_SUPPORT`); for one transmitter it is its mean RSSI mu (dBm) where its
detection probability pd reaches :data:`MIN_DETECTION`, and nothing elsewhere.
"""

from __future__ import annotations

import io
import json
import math
import threading
from collections import OrderedDict

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from hybridloc.radio.radiomap import RadioMap

from .. import db as m
from ..store import Store

#: A transmitter's cell is drawn where it is detected at least this often.
MIN_DETECTION = 0.1
#: A cell is drawn in the support layer where at least this many effective scans are behind it (the
#: kernel's weight falls off as exp(-d^2 / 2 bandwidth^2): 0.05 is a scan ~2.4 bandwidths away).
MIN_SUPPORT = 0.05
#: Transmitters listed per floor (by detected area), for the per-transmitter layer.
MAX_TRANSMITTERS = 300


class NotFound(LookupError):
    """A site, floor or transmitter the database does not hold (HTTP 404)."""


def _round_coords(v):
    if isinstance(v, list):
        return [_round_coords(x) for x in v]
    if isinstance(v, float):
        return round(v, 2) if math.isfinite(v) else None
    return v


class SiteData:
    def __init__(self, store: Store, maps_cached: int = 4):
        self.store = store
        self._lock = threading.Lock()
        self._plans: dict[str, tuple[int, dict]] = {}
        self._maps: OrderedDict[tuple[str, int], RadioMap] = OrderedDict()
        self._maps_cached = maps_cached

    # ------------------------------------------------------------------ sites
    def sites(self) -> list[str]:
        """Every site the database knows (a site row, a floor plan or a radio map)."""
        with Session(self.store.engine) as s:
            ids = set(s.execute(select(m.Site.id)).scalars())
            ids.update(s.execute(select(m.RadioMapVersion.site_id).distinct()).scalars())
        return sorted(ids)

    def origin(self, site: str):
        """The site's geodetic origin (:class:`hybridloc.geo.GeodeticOrigin`) when stored, else None."""
        from hybridloc.geo import GeodeticOrigin

        with Session(self.store.engine) as s:
            row = s.get(m.Site, site)
            if row is None or row.origin_lat_deg is None or row.origin_lon_deg is None:
                return None
            return GeodeticOrigin.from_degrees(row.origin_lat_deg, row.origin_lon_deg)

    def site_info(self, site: str) -> dict:
        """Floors (from the floor plan, else the radio map), map version, whether a plan exists."""
        plan = self.plan(site)
        floors: dict[str, int | None] = {}
        if plan is not None:
            for f in plan["features"]:
                p = f["properties"]
                if p.get("category") == "floor":
                    floors[p["floor"]] = p.get("level")
        got = self._map(site)
        if got is not None:
            version, rmap = got
            for name in rmap.floors:
                floors.setdefault(name, rmap.floor_levels.get(name))
        else:
            version = None
        ordered = sorted(floors.items(), key=lambda kv: (kv[1] is None, kv[1] if kv[1] is not None else 0, kv[0]))
        return {"id": site, "floors": [{"name": n, "level": lv} for n, lv in ordered], "map_version": version, "has_plan": plan is not None}

    # ------------------------------------------------------------------ floor plans
    def plan(self, site: str) -> dict | None:
        """The site's newest floor plan as stored (GeoJSON in the site frame, m; features with
        ``category`` floor / walkable / walls / room / transition), coordinates rounded to cm; None without one."""
        with Session(self.store.engine) as s:
            newest = s.execute(select(func.max(m.FloorPlanVersion.id)).where(m.FloorPlanVersion.site_id == site)).scalar_one_or_none()
            if newest is None:
                return None
            with self._lock:
                hit = self._plans.get(site)
            if hit is not None and hit[0] == newest:
                return hit[1]
            text = s.get(m.FloorPlanVersion, newest).geojson
        doc = json.loads(text)
        for f in doc.get("features", []):
            g = f.get("geometry") or {}
            if "coordinates" in g:
                g["coordinates"] = _round_coords(g["coordinates"])
        doc["crs_note"] = "coordinates are hybridloc site-frame metres (x east, y north), not WGS84"
        with self._lock:
            self._plans[site] = (newest, doc)
        return doc

    # ------------------------------------------------------------------ radio maps
    def _map(self, site: str) -> tuple[int, RadioMap] | None:
        with Session(self.store.engine) as s:
            v = s.execute(select(func.max(m.RadioMapVersion.version)).where(m.RadioMapVersion.site_id == site)).scalar_one_or_none()
        if v is None:
            return None
        with self._lock:
            hit = self._maps.get((site, v))
            if hit is not None:
                self._maps.move_to_end((site, v))
                return v, hit
        got = self.store.load_map(site)
        if got is None:
            return None
        v, blob = got
        rmap = RadioMap.load(io.BytesIO(blob))
        with self._lock:
            self._maps[(site, v)] = rmap
            while len(self._maps) > self._maps_cached:
                self._maps.popitem(last=False)
        return v, rmap

    def _floor_map(self, site: str, floor: str):
        """(version, map, floor map or None). None: a floor of the site's plan the map has no cell on
        yet (an empty layer, not an error); NotFound for a floor neither knows, or no map at all."""
        got = self._map(site)
        if got is None:
            raise NotFound(f"site {site!r} has no radio map")
        version, rmap = got
        fm = rmap.floors.get(floor)
        if fm is None:
            plan = self.plan(site)
            if plan is not None and any(f["properties"].get("floor") == floor for f in plan["features"]):
                return version, rmap, None
            raise NotFound(f"the radio map of site {site!r} (version {version}) has no floor {floor!r} (floors: {', '.join(rmap.floors) or '-'})")
        return version, rmap, fm

    def transmitters(self, site: str, floor: str) -> dict:
        """The floor's transmitters, those detected over the largest area first."""
        version, rmap, fm = self._floor_map(site, floor)
        if fm is None:
            return {"site": site, "floor": floor, "map_version": version, "transmitters": []}
        area = (fm.pd >= MIN_DETECTION).sum(axis=0) * fm.cell_size**2
        order = np.argsort(-area, kind="stable")[:MAX_TRANSMITTERS]
        return {
            "site": site,
            "floor": floor,
            "map_version": version,
            "transmitters": [{"id": rmap.transmitters[int(fm.tx[j])], "area_m2": round(float(area[j]), 1)} for j in order if area[j] > 0],
        }

    def coverage(self, site: str, floor: str, tx: str | None = None) -> dict:
        """The heat layer of ``floor``: a grid (row-major from the south-west cell, ``null`` where the
        map has no cell or the transmitter is not heard) with its extent in the site frame, m."""
        version, rmap, fm = self._floor_map(site, floor)
        if fm is None:
            note = f"the radio map (version {version}) has no cell on floor {floor} yet"
            return {"site": site, "floor": floor, "tx": tx, "map_version": version, "cell": None, "nx": 0, "ny": 0, "values": [], "note": note}
        cell = float(fm.cell_size)
        cells = np.asarray(fm.cells, float).reshape(-1, 2)
        if tx is None:
            values = np.asarray(fm.support, float)
            values = np.where(values >= MIN_SUPPORT, values, np.nan)
            unit, label, scale = "scans", "radio map support (effective scans per cell)", "log"
        else:
            col = {rmap.transmitters[int(t)]: j for j, t in enumerate(fm.tx)}.get(tx)
            if col is None:
                raise NotFound(f"transmitter {tx!r} is not in the radio map of site {site!r} floor {floor!r}")
            values = np.where(fm.pd[:, col] >= MIN_DETECTION, fm.mu[:, col], np.nan).astype(float)
            unit, label, scale = "dBm", f"mean RSSI of {tx}", "linear"
        if len(cells) == 0:
            return {"site": site, "floor": floor, "tx": tx, "map_version": version, "cell": cell, "nx": 0, "ny": 0, "values": []}
        # the cells lie on a lattice of pitch `cell` (hybridloc.radio.radiomap._grid_cells): index them
        x0, y0 = cells.min(axis=0)
        ix = np.rint((cells[:, 0] - x0) / cell).astype(int)
        iy = np.rint((cells[:, 1] - y0) / cell).astype(int)
        nx, ny = int(ix.max()) + 1, int(iy.max()) + 1
        grid = np.full(nx * ny, np.nan)
        grid[iy * nx + ix] = values
        finite = grid[np.isfinite(grid)]
        return {
            "site": site,
            "floor": floor,
            "tx": tx,
            "map_version": version,
            "label": label,
            "unit": unit,
            "scale": scale,
            "cell": cell,
            # the grid's south-west corner (cell centre minus half a cell) and its size in cells
            "x0": round(float(x0) - cell / 2, 3),
            "y0": round(float(y0) - cell / 2, 3),
            "nx": nx,
            "ny": ny,
            "vmin": float(finite.min()) if finite.size else None,
            "vmax": float(finite.max()) if finite.size else None,
            "values": [None if not math.isfinite(v) else round(float(v), 2) for v in grid],
        }

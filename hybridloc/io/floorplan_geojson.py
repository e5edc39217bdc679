"""A site's floor plan as one GeoJSON document, written and read back without loss (the server's
``floor_plan`` table stores it; ``hybridloc floorplan import`` writes it).

Coordinates are the site frame in metres (not WGS84: the walkable area and walls are what positioning
uses, and the frame is the one every position of the site is in). The document is a FeatureCollection
with a foreign member ``hybridloc``: ``{"format": "hybridloc-floorplan", "version": 1, "site": ...,
"origin": {"lat_deg", "lon_deg", "height_m"} or null}``. Per floor (``properties.floor``, ``level``,
``height``) the features are, by ``properties.category``:

* ``floor``: the outline (MultiPolygon);
* ``walkable``: where a person can be (MultiPolygon);
* ``walls``: the wall segments (MultiLineString of two-point lines);
* ``room``: a named unit (Polygon, ``properties.name``).

Transitions between floors (stairs, lifts) are features of category ``transition`` (LineString from
the ``floor_from`` to the ``floor_to`` position, ``properties.kind``).
"""

from __future__ import annotations

import json
import math

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, mapping, shape

from ..geo import GeodeticOrigin
from ..types import Floor, FloorPlan, FloorTransition, TransitionKind
from .common import DataFormatError

FORMAT_NAME = "hybridloc-floorplan"
FORMAT_VERSION = 1


def _multi(geom) -> MultiPolygon:
    if isinstance(geom, MultiPolygon):
        return geom
    if isinstance(geom, Polygon):
        return MultiPolygon([geom])
    return MultiPolygon([g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon)])


def floorplan_to_geojson(plan: FloorPlan) -> str:
    """The plan as one GeoJSON text (module docstring)."""
    feats = []
    for f in plan.floors:
        base = {"floor": f.name, "level": int(f.level), "height": float(f.height)}
        feats.append({"type": "Feature", "geometry": mapping(f.outline), "properties": {**base, "category": "floor"}})
        feats.append({"type": "Feature", "geometry": mapping(f.walkable), "properties": {**base, "category": "walkable"}})
        walls = np.asarray(f.walls, float).reshape(-1, 2, 2)
        feats.append(
            {"type": "Feature", "geometry": {"type": "MultiLineString", "coordinates": walls.tolist()}, "properties": {**base, "category": "walls"}}
        )
        for name, poly in f.rooms:
            feats.append({"type": "Feature", "geometry": mapping(poly), "properties": {**base, "category": "room", "name": name}})
    for tr in plan.transitions:
        feats.append(
            {
                "type": "Feature",
                "geometry": {"type": "LineString", "coordinates": [list(tr.pos_from), list(tr.pos_to)]},
                "properties": {"category": "transition", "kind": tr.kind.value, "floor_from": tr.floor_from, "floor_to": tr.floor_to},
            }
        )
    o = plan.origin
    head = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "site": plan.site,
        "origin": None if o is None else {"lat_deg": math.degrees(o.lat), "lon_deg": math.degrees(o.lon), "height_m": o.height},
    }
    return json.dumps({"type": "FeatureCollection", "hybridloc": head, "features": feats})


def floorplan_from_geojson(text: str | bytes, source: str = "floor plan") -> FloorPlan:
    """The plan of :func:`floorplan_to_geojson`'s text; :class:`DataFormatError` for anything else."""
    try:
        doc = json.loads(text)
        head = doc["hybridloc"]
        feats = doc["features"]
    except (ValueError, KeyError, TypeError) as exc:
        raise DataFormatError(source, None, f"not a hybridloc floor plan ({exc})") from exc
    if not isinstance(head, dict) or head.get("format") != FORMAT_NAME:
        raise DataFormatError(source, None, f"not a hybridloc floor plan (format {head.get('format') if isinstance(head, dict) else head!r})")
    if int(head.get("version", 0)) > FORMAT_VERSION:
        raise DataFormatError(source, None, f"floor plan version {head['version']} is newer than this hybridloc understands ({FORMAT_VERSION})")
    parts: dict[str, dict] = {}
    transitions = []
    try:
        for ft in feats:
            p = ft.get("properties") or {}
            cat = p.get("category")
            if cat == "transition":
                c = ft["geometry"]["coordinates"]
                transitions.append(
                    FloorTransition(TransitionKind(p["kind"]), str(p["floor_from"]), str(p["floor_to"]), tuple(c[0][:2]), tuple(c[1][:2]))
                )
                continue
            d = parts.setdefault(str(p["floor"]), {"level": int(p.get("level", 0)), "height": float(p.get("height", 0.0)), "rooms": []})
            if cat == "floor":
                d["outline"] = _multi(shape(ft["geometry"]))
            elif cat == "walkable":
                d["walkable"] = _multi(shape(ft["geometry"]))
            elif cat == "walls":
                d["walls"] = np.asarray(ft["geometry"]["coordinates"], float).reshape(-1, 2, 2)
            elif cat == "room":
                d["rooms"].append((str(p.get("name") or ""), shape(ft["geometry"])))
        floors = []
        for name, d in parts.items():
            if "outline" not in d:
                raise KeyError(f"floor {name!r} has no outline")
            walk = d.get("walkable", d["outline"])
            floors.append(Floor(name, d["level"], d["height"], d["outline"], walk, d.get("walls", np.zeros((0, 2, 2))), tuple(d["rooms"])))
    except (KeyError, ValueError, TypeError, IndexError, shapely.errors.GEOSException) as exc:
        raise DataFormatError(source, None, f"bad floor plan feature: {exc}") from exc
    if not floors:
        raise DataFormatError(source, None, "the floor plan has no floor")
    floors.sort(key=lambda f: f.level)
    o = head.get("origin")
    origin = GeodeticOrigin.from_degrees(float(o["lat_deg"]), float(o["lon_deg"]), float(o.get("height_m", 0.0))) if o else None
    return FloorPlan(str(head.get("site") or ""), tuple(floors), tuple(transitions), origin)

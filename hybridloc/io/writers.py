"""Writers for GIS and navigation tools: trajectory CSV, GeoJSON and NMEA-0183.

* Trajectory CSV: ``t,x,y,z,floor`` plus ``sigma_x,sigma_y,sigma_z`` when the trajectory has them.
  SI units, site frame. :func:`read_trajectory_csv` reads it back.
* GeoJSON (RFC 7946): tracks as LineStrings, regions as (Multi)Polygons, floor plans as polygons.
  RFC 7946 requires WGS84 lon/lat; with a site origin the site-frame metres are converted, without
  one the file holds site-frame metres and says so in a top-level ``"crs_note"`` member (readable by
  GIS tools as a local engineering CRS).
* NMEA-0183: a GGA (position) and, when a heading is given, an HDT (true heading, degrees clockwise
  from North) sentence per epoch, from the site origin. Checksums are the XOR of the characters
  between ``$`` and ``*``.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable, Sequence

import numpy as np
import shapely
from shapely.geometry import mapping

from ..geo import GeodeticOrigin
from ..types import ContainmentRegion, FloorPlan, Trajectory
from ..units import DEG, heading_to_bearing_deg
from .common import DataFormatError

TRAJ_COLUMNS = ("t", "x", "y", "z", "floor")
SIGMA_COLUMNS = ("sigma_x", "sigma_y", "sigma_z")


def write_trajectory_csv(path: str | os.PathLike, traj: Trajectory) -> None:
    """Write ``t,x,y,z,floor[,sigma_x,sigma_y,sigma_z]``; an unknown floor is an empty field."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        cols = TRAJ_COLUMNS + (SIGMA_COLUMNS if traj.sigma_enu is not None else ())
        w.writerow(cols)
        for i in range(len(traj)):
            row = [f"{traj.t[i]:.6f}", *(f"{v:.4f}" for v in traj.pos_enu[i]), "" if traj.floor is None or traj.floor[i] is None else traj.floor[i]]
            if traj.sigma_enu is not None:
                row += [f"{v:.4f}" for v in traj.sigma_enu[i]]
            w.writerow(row)


def read_trajectory_csv(path: str | os.PathLike) -> Trajectory:
    """Read a trajectory CSV written by :func:`write_trajectory_csv` (``z``/``floor``/sigmas optional)."""
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    if not rows or not {"t", "x", "y"} <= set(rows[0]):
        raise DataFormatError(path, 1, "a trajectory CSV needs at least columns t,x,y")
    try:
        t = np.array([float(r["t"]) for r in rows])
        p = np.array([[float(r["x"]), float(r["y"]), float(r.get("z") or 0.0)] for r in rows])
        sig = np.array([[float(r[c]) for c in SIGMA_COLUMNS] for r in rows]) if all(c in rows[0] for c in SIGMA_COLUMNS) else None
    except (ValueError, TypeError) as exc:
        raise DataFormatError(path, None, f"bad number: {exc}") from exc
    floor = tuple((r.get("floor") or None) for r in rows) if "floor" in rows[0] else None
    return Trajectory(t, p, floor, sig)


# ----------------------------------------------------------------------------------------------
# GeoJSON
# ----------------------------------------------------------------------------------------------
def _to_lonlat(xy: np.ndarray, origin: GeodeticOrigin | None) -> np.ndarray:
    xy = np.asarray(xy, dtype=float)
    if origin is None:
        return xy[..., :2]
    lat, lon, _ = origin.enu_to_geodetic(xy[..., :2])
    return np.stack([lon / DEG, lat / DEG], axis=-1)


def track_feature(traj: Trajectory, origin: GeodeticOrigin | None = None, **properties) -> dict:
    coords = _to_lonlat(traj.pos_enu, origin)
    return {
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": coords.round(8).tolist()},
        "properties": {"kind": "track", "t_start": float(traj.t[0]), "t_end": float(traj.t[-1]), **properties},
    }


def _geom_feature(geom, origin: GeodeticOrigin | None, properties: dict) -> dict:
    if origin is not None:
        geom = shapely.transform(geom, lambda xy: _to_lonlat(xy, origin))
    return {"type": "Feature", "geometry": mapping(geom), "properties": properties}


def region_feature(region: ContainmentRegion, origin: GeodeticOrigin | None = None, **properties) -> dict:
    props = {"kind": "containment_region", "floor": region.floor, "mass": region.mass, "area_m2": region.area_m2, **properties}
    if math.isfinite(region.t):
        props["t"] = region.t
    return _geom_feature(region.area, origin, props)


def floorplan_features(plan: FloorPlan, origin: GeodeticOrigin | None = None) -> list[dict]:
    feats = []
    for fl in plan.floors:
        feats.append(_geom_feature(fl.outline, origin, {"kind": "floor", "floor": fl.name, "level": fl.level}))
        for name, room in fl.rooms:
            feats.append(_geom_feature(room, origin, {"kind": "room", "floor": fl.name, "name": name}))
    return feats


def point_features(t: Sequence[float], pos: np.ndarray, origin: GeodeticOrigin | None = None, **properties) -> list[dict]:
    ll = _to_lonlat(np.asarray(pos), origin)
    return [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": ll[i].round(8).tolist()}, "properties": {"t": float(t[i]), **properties}}
        for i in range(len(ll))
    ]


def geojson_collection(features: Iterable[dict], origin: GeodeticOrigin | None = None) -> dict:
    """A FeatureCollection of ``features``; without an origin it says its coordinates are site-frame
    metres (a ``crs_note`` foreign member: RFC 7946 itself allows only WGS84)."""
    fc: dict = {"type": "FeatureCollection", "features": list(features)}
    if origin is None:
        fc["crs_note"] = "coordinates are hybridloc site-frame metres (x east, y north), not WGS84"
    return fc


def write_geojson(path: str | os.PathLike, features: Iterable[dict], origin: GeodeticOrigin | None = None) -> None:
    with open(path, "w", encoding="utf-8") as f:
        json.dump(geojson_collection(features, origin), f, ensure_ascii=False)


# ----------------------------------------------------------------------------------------------
# NMEA-0183
# ----------------------------------------------------------------------------------------------
def nmea_checksum(body: str) -> str:
    c = 0
    for ch in body:
        c ^= ord(ch)
    return f"{c:02X}"


def _sentence(body: str) -> str:
    return f"${body}*{nmea_checksum(body)}"


def _dm(value_deg: float, deg_digits: int) -> tuple[str, float]:
    a = abs(value_deg)
    d = int(a)
    m = (a - d) * 60.0
    if round(m, 5) >= 60.0:  # 59.999995' rounds up to the next degree
        d, m = d + 1, 0.0
    return f"{d:0{deg_digits}d}{m:08.5f}", m


def gga_sentence(
    t_unix: float, lat_deg: float, lon_deg: float, height_m: float, quality: int = 6, n_sats: int = 0, hdop: float = 1.0, talker: str = "GN"
) -> str:
    """One GGA sentence. ``quality`` 6 = "estimated (dead reckoning)", the honest code for PDR."""
    hh = (t_unix % 86400.0) / 3600.0
    h = int(hh)
    mm = int((hh - h) * 60)
    ss = t_unix % 60.0
    lat_s, _ = _dm(lat_deg, 2)
    lon_s, _ = _dm(lon_deg, 3)
    body = (
        f"{talker}GGA,{h:02d}{mm:02d}{ss:05.2f},{lat_s},{'N' if lat_deg >= 0 else 'S'},{lon_s},{'E' if lon_deg >= 0 else 'W'},"
        f"{quality:d},{n_sats:02d},{hdop:.1f},{height_m:.2f},M,0.0,M,,"
    )
    return _sentence(body)


def hdt_sentence(heading_rad: float, talker: str = "GN") -> str:
    """One HDT sentence: true heading in degrees clockwise from North."""
    return _sentence(f"{talker}HDT,{heading_to_bearing_deg(heading_rad):.2f},T")


def nmea_lines(traj: Trajectory, origin: GeodeticOrigin, heading: Sequence[float] | None = None) -> list[str]:
    """GGA (+ HDT when ``heading`` is given, rad per sample) for every trajectory sample.

    ``traj.t`` must be Unix seconds for the UTC time field to mean anything.
    """
    lat, lon, h = origin.enu_to_geodetic(traj.pos_enu)
    out = []
    for i in range(len(traj)):
        out.append(gga_sentence(float(traj.t[i]), float(lat[i] / DEG), float(lon[i] / DEG), float(h[i])))
        if heading is not None:
            out.append(hdt_sentence(float(heading[i])))
    return out


def write_nmea(path: str | os.PathLike, traj: Trajectory, origin: GeodeticOrigin, heading: Sequence[float] | None = None) -> None:
    with open(path, "w", encoding="ascii", newline="\r\n") as f:
        for line in nmea_lines(traj, origin, heading):
            f.write(line + "\n")


def parse_nmea_gga(line: str) -> tuple[float, float, float]:
    """(lat_deg, lon_deg, height_m) of a GGA sentence, checksum verified."""
    line = line.strip()
    if not line.startswith("$") or "*" not in line:
        raise ValueError(f"not an NMEA sentence: {line!r}")
    body, cs = line[1:].split("*", 1)
    if nmea_checksum(body) != cs.upper():
        raise ValueError(f"NMEA checksum mismatch in {line!r}")
    f = body.split(",")
    if not f[0].endswith("GGA"):
        raise ValueError("not a GGA sentence")
    lat = int(f[2][:2]) + float(f[2][2:]) / 60.0
    lon = int(f[4][:3]) + float(f[4][3:]) / 60.0
    return (lat if f[3] == "N" else -lat), (lon if f[5] == "E" else -lon), float(f[9])

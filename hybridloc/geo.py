"""Geodesy: a site's geodetic origin and the WGS84 <-> local ENU conversion.

The site frame is East-North-Up with its origin at a geodetic point (latitude, longitude, height
above the ellipsoid). Conversions go through ECEF exactly (no flat-earth approximation), so they stay
right for any site size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .units import DEG

# WGS84 ellipsoid
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


def geodetic_to_ecef(lat_rad, lon_rad, h_m):
    """Geodetic (rad, rad, m) -> ECEF (m). Broadcasts; returns shape (..., 3)."""
    lat, lon, h = (np.asarray(v, dtype=float) for v in (lat_rad, lon_rad, h_m))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * np.sin(lat)
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(xyz):
    """ECEF (m), shape (..., 3) -> (lat_rad, lon_rad, h_m), by Bowring's iteration (mm-exact)."""
    xyz = np.asarray(xyz, dtype=float)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(6):
        n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
        h = p / np.cos(lat) - n
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n / (n + h)))
    n = WGS84_A / np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2)
    h = p / np.cos(lat) - n
    return lat, lon, h


@dataclass(frozen=True)
class GeodeticOrigin:
    """Origin of a site's ENU frame.

    Attributes
    ----------
    lat : float
        Geodetic latitude, rad.
    lon : float
        Longitude, rad.
    height : float
        Height above the WGS84 ellipsoid, m.
    """

    lat: float
    lon: float
    height: float = 0.0

    @classmethod
    def from_degrees(cls, lat_deg: float, lon_deg: float, height: float = 0.0) -> GeodeticOrigin:
        if not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 360.0):
            raise ValueError(f"geodetic origin out of range: lat={lat_deg}, lon={lon_deg} (degrees expected)")
        return cls(lat_deg * DEG, lon_deg * DEG, height)

    @property
    def R_ecef_to_enu(self) -> np.ndarray:
        sl, cl = math.sin(self.lat), math.cos(self.lat)
        so, co = math.sin(self.lon), math.cos(self.lon)
        return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])

    def geodetic_to_enu(self, lat_rad, lon_rad, h_m=0.0) -> np.ndarray:
        """Geodetic (rad) -> site ENU (m), shape (..., 3)."""
        d = geodetic_to_ecef(lat_rad, lon_rad, h_m) - geodetic_to_ecef(self.lat, self.lon, self.height)
        return d @ self.R_ecef_to_enu.T

    def enu_to_geodetic(self, pos_enu):
        """Site ENU (m), shape (..., 2 or 3) -> (lat_rad, lon_rad, h_m)."""
        p = np.asarray(pos_enu, dtype=float)
        if p.shape[-1] == 2:
            p = np.concatenate([p, np.zeros(p.shape[:-1] + (1,))], axis=-1)
        ecef = p @ self.R_ecef_to_enu + geodetic_to_ecef(self.lat, self.lon, self.height)
        return ecef_to_geodetic(ecef)


def wall_crossings(walls: np.ndarray, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Number of wall segments crossed by each segment p0[i] -> p1[i]; walls (M, 2, 2), p0/p1 (N, 2)."""
    if len(walls) == 0 or len(p0) == 0:
        return np.zeros(len(p0), int)
    a, b = walls[:, 0][None, :, :], walls[:, 1][None, :, :]
    c, d = p0[:, None, :], p1[:, None, :]

    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    o1, o2 = orient(a, b, c), orient(a, b, d)
    o3, o4 = orient(c, d, a), orient(c, d, b)
    hit = (o1 * o2 < 0) & (o3 * o4 < 0)
    return hit.sum(axis=1)


class WallIndex:
    """:func:`wall_crossings` for short moves, through a grid of cells that each list the walls near them.

    A move p -> q no longer than ``reach`` m lies within ``reach`` of p, so every wall it can cross
    passes within ``reach`` of p's cell: each cell lists the walls whose bounding box, grown by
    ``reach``, overlaps it, and a move is tested against its start cell's list only. Longer moves and
    moves starting outside the grid go through :func:`wall_crossings` against every wall. The answer is
    the same as :func:`wall_crossings`'s, at a cost per move of the walls near it instead of all of them
    (a particle filter's 50,000 steps against an Indoor Location Competition floor's ~600 shop-front
    segments: 30 million tests a step without the index).
    """

    def __init__(self, walls: np.ndarray, cell: float = 1.0, reach: float = 2.0):
        if not (cell > 0 and reach > 0):
            raise ValueError("WallIndex: cell and reach must be positive metres")
        self.walls = np.asarray(walls, float).reshape(-1, 2, 2)
        self.cell, self.reach = float(cell), float(reach)
        m = len(self.walls)
        if m == 0:
            self.x0 = self.y0 = 0.0
            self.nx = self.ny = 0
            self.table = np.zeros((0, 0), np.int64)
            return
        lo = self.walls.min(axis=1) - reach  # (M, 2) each wall's box grown by reach
        hi = self.walls.max(axis=1) + reach
        self.x0, self.y0 = float(lo[:, 0].min()), float(lo[:, 1].min())
        self.nx = int(np.floor((hi[:, 0].max() - self.x0) / cell)) + 1
        self.ny = int(np.floor((hi[:, 1].max() - self.y0) / cell)) + 1
        i0 = np.floor((lo - [self.x0, self.y0]) / cell).astype(np.int64)
        i1 = np.floor((hi - [self.x0, self.y0]) / cell).astype(np.int64)
        cells, owners = [], []
        for k in range(m):
            ix, iy = np.meshgrid(np.arange(i0[k, 0], i1[k, 0] + 1), np.arange(i0[k, 1], i1[k, 1] + 1))
            cells.append((iy * self.nx + ix).ravel())
            owners.append(np.full(ix.size, k))
        c, w = np.concatenate(cells), np.concatenate(owners)
        order = np.argsort(c, kind="stable")
        c, w = c[order], w[order]
        counts = np.bincount(c, minlength=self.nx * self.ny)
        k_max = int(counts.max())
        # (cells, k_max) wall indices, padded with m: a zero-length wall at the origin that nothing crosses
        self.table = np.full((self.nx * self.ny, k_max), m, np.int64)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.table[c, np.arange(len(c)) - start[c]] = w
        self.counts = counts  # walls listed per cell
        self._padded = np.concatenate([self.walls, np.zeros((1, 2, 2))])

    def crossings(self, p0: np.ndarray, p1: np.ndarray, chunk: int = 8192) -> np.ndarray:
        """Number of walls crossed by each move p0[i] -> p1[i] ((N, 2) each), as :func:`wall_crossings`."""
        p0, p1 = np.asarray(p0, float).reshape(-1, 2), np.asarray(p1, float).reshape(-1, 2)
        out = np.zeros(len(p0), int)
        if len(self.walls) == 0 or len(p0) == 0:
            return out
        ix = np.floor((p0[:, 0] - self.x0) / self.cell)
        iy = np.floor((p0[:, 1] - self.y0) / self.cell)
        short = np.einsum("ij,ij->i", p1 - p0, p1 - p0) <= self.reach**2
        inside = (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)
        near = short & inside
        far = ~short  # a short move outside the grid is more than reach from every wall: it crosses none
        if far.any():
            out[far] = wall_crossings(self.walls, p0[far], p1[far])
        sel = np.flatnonzero(near)
        cell = (iy[sel] * self.nx + ix[sel]).astype(np.int64)
        k = self.counts[cell]
        sel, cell, k = sel[k > 0], cell[k > 0], k[k > 0]  # a move from a cell with no wall near crosses none
        order = np.argsort(k, kind="stable")  # by walls listed, so each chunk gathers only as many as it needs
        sel, cell, k = sel[order], cell[order], k[order]
        for a in range(0, len(sel), chunk):  # (chunk, walls, 2, 2) at a time
            s, c = sel[a : a + chunk], cell[a : a + chunk]
            w = self._padded[self.table[c, : int(k[a : a + chunk].max())]]
            a_, b_ = w[:, :, 0], w[:, :, 1]
            c_, d_ = p0[s][:, None, :], p1[s][:, None, :]
            o1, o2 = _orient(a_, b_, c_), _orient(a_, b_, d_)
            o3, o4 = _orient(c_, d_, a_), _orient(c_, d_, b_)
            out[s] = ((o1 * o2 < 0) & (o3 * o4 < 0)).sum(axis=1)
        return out


def _orient(p, q, r):
    """Twice the signed area of the triangle p, q, r (broadcast over leading axes; last axis x, y)."""
    return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])


#: A floor has a dominant grid when at least this share of its wall length lies within
#: ``DOMINANT_AXIS_BAND`` of one axis (mod 90 deg).
DOMINANT_AXIS_MIN_SHARE = 0.3
DOMINANT_AXIS_BAND = 10.0 * DEG


def dominant_axis(walls: np.ndarray) -> tuple[float, float] | None:
    """The direction (rad, in [0, pi/2)) of a floor's dominant grid, mod 90 deg, and the share of wall
    length within ``DOMINANT_AXIS_BAND`` of it; None when no grid dominates (share below
    ``DOMINANT_AXIS_MIN_SHARE``) or there are no walls.

    The length-weighted histogram of wall orientations mod 90 deg (2 deg bins, circular) gives the
    peak; the axis is the circular mean (of 4 theta) of the walls within the band around it, so
    walls at other angles do not pull it (Borenstein's heuristic drift elimination assumes corridors
    along such a grid).
    """
    w = np.asarray(walls, float).reshape(-1, 2, 2)
    d = w[:, 1] - w[:, 0]
    length = np.hypot(d[:, 0], d[:, 1])
    ok = length > 0
    if not ok.any():
        return None
    theta = np.mod(np.arctan2(d[ok, 1], d[ok, 0]), math.pi / 2)
    length = length[ok]
    nb = 45
    hist = np.bincount(np.minimum((theta / (math.pi / 2) * nb).astype(int), nb - 1), weights=length, minlength=nb)
    hist = hist + np.roll(hist, 1) + np.roll(hist, -1)  # circular smoothing over +-1 bin
    peak = (np.argmax(hist) + 0.5) * (math.pi / 2) / nb
    dev = np.mod(theta - peak + math.pi / 4, math.pi / 2) - math.pi / 4
    near = np.abs(dev) <= DOMINANT_AXIS_BAND
    share = float(length[near].sum() / length.sum())
    if share < DOMINANT_AXIS_MIN_SHARE:
        return None
    z = np.sum(length[near] * np.exp(4j * theta[near]))
    return float(np.mod(np.angle(z) / 4.0, math.pi / 2)), share


def corridor_axes(plan) -> dict[str, float]:
    """Floor name -> the direction of its dominant grid of walls (:func:`dominant_axis`), for the
    fusion filters' heuristic drift elimination; floors without one (and a missing plan) are left out."""
    out = {}
    for f in plan.floors if plan is not None else ():
        ax = dominant_axis(f.walls)
        if ax is not None:
            out[f.name] = ax[0]
    return out

"""Walk prior: where on a floor people are, as a raster a particle filter weighs its particles with.

Crowd-sourced: the radio map already carries every labelled reference scan with its position (the
surveys and crowd traces the server labelled), so the places people walk are known without any
manual drawing - corridors come out dense, shop interiors and dead space sparse. The prior is

    pi(x) = eps + (1 - eps) * min(1, k(x) / k_ref)

with k the Gaussian kernel density of the reference positions (bandwidth ``bandwidth`` m), k_ref its
``saturation`` quantile over the places people were (so the well-walked half of the corridors all count
as fully walkable, the prior does not pull towards the single busiest spot), and eps the floor for
places walkable but never walked. Outside the floor plan's walkable area pi = 0 (a hard constraint),
and the plan's wall segments may not be crossed (:meth:`WalkPrior.crosses_wall`). Without a plan the
raster covers the data plus a margin and everything beyond it is eps.

Entrances come from the crowd too. Floor plans rarely show the doors in a building's outer wall (the
Indoor Location Competition's show none), so a walk that starts in the street is impossible for the
plan alone: its particles are pushed indoors and stay wrong (simulated site, 15 phone clients, 3 of
them starting 12 m outdoors: particle + map 7.0-7.4 m on those walks, 1.2-1.4 m without the map).
Where walked positions lie outside a floor's footprint, that ground is walkable with their own density
where it reaches ``door_share`` of the reference density (no eps: the rest of the outdoors stays
impossible), and the outer wall is opened, in pieces of ``door_piece`` m, wherever it does so at the
wall. With no walked position outdoors, nothing changes.

This is the causal, probabilistic form of what the Indoor Location Competition winners did offline by
snapping positions to the grid of training waypoints (Harle's survey sec. VII: maps from PDR traces,
particle filters constrained by the building).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely
from scipy import ndimage

from ..geo import WallIndex
from ..types import FloorPlan


@dataclass(frozen=True)
class FloorPrior:
    name: str
    x0: float  # lower-left corner of the raster, m
    y0: float
    cell: float  # m
    pi: np.ndarray  # (ny, nx) prior in [0, 1]
    outside: float  # prior beyond the raster
    walls: np.ndarray  # (M, 2, 2) wall segments, m

    def at(self, xy: np.ndarray) -> np.ndarray:
        """Prior at points ``xy`` (N, 2)."""
        ix = np.floor((xy[:, 0] - self.x0) / self.cell).astype(np.int64)
        iy = np.floor((xy[:, 1] - self.y0) / self.cell).astype(np.int64)
        ny, nx = self.pi.shape
        inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        out = np.full(len(xy), self.outside)
        out[inside] = self.pi[iy[inside], ix[inside]]
        return out


class WalkPrior:
    """Per-floor walk priors (see the module docstring)."""

    def __init__(self, floors: dict[str, FloorPrior]):
        self.floors = floors
        self._walls: dict[str, WallIndex] = {}  # per floor, built at its first wall test

    def __setstate__(self, state: dict) -> None:  # a prior pickled before the wall index existed
        self.__dict__.update(state)
        self.__dict__.setdefault("_walls", {})

    @classmethod
    def from_points(
        cls,
        points_by_floor: dict[str, np.ndarray],
        plan: FloorPlan | None = None,
        cell: float = 0.5,
        bandwidth: float = 1.5,
        eps: float = 1.0,
        saturation: float = 0.5,
        margin: float = 10.0,
        door_piece: float = 1.0,
        door_share: float = 0.1,
    ) -> WalkPrior:
        """Build from walked positions (per floor name, (N, 2) m) and an optional floor plan
        (``door_piece``, ``door_share``: the entrances learned from outdoor walks, module docstring)."""
        if not 0.0 <= eps <= 1.0:
            raise ValueError(f"eps must be in [0, 1], got {eps}")
        if cell <= 0 or bandwidth <= 0:
            raise ValueError("cell and bandwidth must be positive")
        floors: dict[str, FloorPrior] = {}
        names = set(points_by_floor) | ({f.name for f in plan.floors} if plan else set())
        for name in sorted(names):
            pts = np.asarray(points_by_floor.get(name, np.zeros((0, 2))), float).reshape(-1, 2)
            pts = pts[np.isfinite(pts).all(axis=1)]
            fl = None
            if plan is not None:
                try:
                    fl = plan.floor(name)
                except KeyError:
                    fl = None
            footprint = outdoor_pts = None
            if fl is not None:
                bx0, by0, bx1, by1 = fl.walkable.bounds
                footprint = shapely.union_all([shapely.Polygon(p.exterior) for p in fl.outline.geoms])
                outdoor_pts = pts[~shapely.contains_xy(footprint, pts[:, 0], pts[:, 1])] if len(pts) else pts
                if len(outdoor_pts):  # people walked outside: that ground is in the raster too
                    lo, hi = outdoor_pts.min(0) - margin, outdoor_pts.max(0) + margin
                    bx0, by0, bx1, by1 = min(bx0, lo[0]), min(by0, lo[1]), max(bx1, hi[0]), max(by1, hi[1])
            elif len(pts):
                (bx0, by0), (bx1, by1) = pts.min(0) - margin, pts.max(0) + margin
            else:
                continue
            nx, ny = int(np.ceil((bx1 - bx0) / cell)) + 1, int(np.ceil((by1 - by0) / cell)) + 1
            if nx * ny > 50_000_000:
                raise ValueError(f"floor {name}: a {nx} x {ny} raster at {cell} m is too large; use a coarser cell")

            def binned(p: np.ndarray, nx=nx, ny=ny, bx0=bx0, by0=by0) -> np.ndarray:  # points per raster cell (beyond it: edge cells)
                c = np.zeros((ny, nx))
                if len(p):
                    np.add.at(
                        c, (np.clip(((p[:, 1] - by0) / cell).astype(int), 0, ny - 1), np.clip(((p[:, 0] - bx0) / cell).astype(int), 0, nx - 1)), 1.0
                    )
                return c

            counts = binned(pts)
            dens = ndimage.gaussian_filter(counts, bandwidth / cell, mode="constant")
            pi = np.full((ny, nx), eps)
            ref = 1.0
            if len(pts):
                ref = max(float(np.quantile(dens[counts > 0], saturation)), 1e-12)
                pi = eps + (1.0 - eps) * np.minimum(1.0, dens / ref)
            if fl is not None:
                gx = bx0 + (np.arange(nx) + 0.5) * cell
                gy = by0 + (np.arange(ny) + 0.5) * cell
                X, Y = np.meshgrid(gx, gy)
                walls = np.asarray(fl.walls, float).reshape(-1, 2, 2)
                walked_outdoors = np.zeros((ny, nx))
                if len(outdoor_pts):
                    walked_outdoors = np.minimum(1.0, ndimage.gaussian_filter(binned(outdoor_pts), bandwidth / cell, mode="constant") / ref)
                    walked_outdoors[walked_outdoors < door_share] = 0.0  # the kernel's tail is not a path
                    walls = _open_doors(walls, footprint, walked_outdoors, bx0, by0, cell, door_piece, door_share)
                outdoors = ~shapely.contains_xy(footprint, X, Y)
                pi = np.where(shapely.contains_xy(fl.walkable, X, Y), pi, np.where(outdoors, walked_outdoors, 0.0))
            else:
                walls = np.zeros((0, 2, 2))
            floors[name] = FloorPrior(name, bx0, by0, cell, pi, 0.0 if fl is not None else eps, walls)
        return cls(floors)

    @classmethod
    def from_radio_map(cls, rmap, plan: FloorPlan | None = None, **kw) -> WalkPrior:
        """The positions of a radio map's labelled reference scans are where people walked."""
        by_floor: dict[str, list] = {}
        for r in rmap.references:
            by_floor.setdefault(r.floor or "", []).append(r.pos_enu)
        return cls.from_points({k: np.array(v) for k, v in by_floor.items()}, plan, **kw)

    def at(self, floor: str | None, xy: np.ndarray) -> np.ndarray:
        fp = self.floors.get(floor or "")
        return np.ones(len(xy)) if fp is None else fp.at(xy)

    def crosses_wall(self, floor: str | None, p: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Which moves p -> q ((N, 2) each) cross a wall segment of the floor."""
        fp = self.floors.get(floor or "")
        if fp is None:
            return np.zeros(len(p), bool)
        index = self._walls.get(fp.name)
        if index is None:  # the walls near each 1 m cell, for moves up to 2 m (longer ones: against every wall)
            index = self._walls[fp.name] = WallIndex(fp.walls, cell=1.0, reach=2.0)
        return index.crossings(p, q) > 0


def _open_doors(
    walls: np.ndarray, footprint, walked_outdoors: np.ndarray, x0: float, y0: float, cell: float, piece: float, share: float
) -> np.ndarray:
    """The wall segments with the outer wall cut into ``piece``-m pieces, those where people walked
    outdoors (``walked_outdoors`` >= ``share`` at the piece's middle) left out: entrances."""
    outer = footprint.boundary
    ny, nx = walked_outdoors.shape
    keep = []
    for a, b in walls:
        mid = 0.5 * (a + b)
        if shapely.distance(outer, shapely.Point(mid)) > 1e-6:  # not on the outer wall (a hole's, an inner wall)
            keep.append([a, b])
            continue
        n = max(1, int(np.ceil(np.hypot(*(b - a)) / piece)))
        for k in range(n):
            p, q = a + (b - a) * k / n, a + (b - a) * (k + 1) / n
            m = 0.5 * (p + q)
            ix, iy = int((m[0] - x0) / cell), int((m[1] - y0) / cell)
            if not (0 <= ix < nx and 0 <= iy < ny and walked_outdoors[iy, ix] >= share):
                keep.append([p, q])
    return np.asarray(keep, float).reshape(-1, 2, 2)

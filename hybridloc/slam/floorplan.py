"""The floor plan as a field for the crowd-SLAM optimiser: distance outside the walkable area.

A floor's walkable area (:attr:`hybridloc.types.Floor.walkable`) is rasterised on a grid of nodes
``resolution`` m apart (0.25 m by default, shared-notes slam.md 4.1) covering the area plus a margin.
Each node outside the area gets its Euclidean distance to the nearest inside node
(``scipy.ndimage.distance_transform_edt``) minus half a cell, the mean distance from the last inside
node to the boundary it stands behind; inside nodes get 0. Between nodes the field is the bilinear
interpolant

    d(x, y) = (1-u)(1-v) d00 + u(1-v) d10 + (1-u) v d01 + u v d11,   u, v in [0, 1) the cell fractions,

whose gradient is the interpolant's own derivative (dd/dx = [(1-v)(d10-d00) + v(d11-d01)] / h, likewise
in y): the exact Jacobian of what is evaluated, which is what a Gauss-Newton step needs. Beyond the
raster the distance grows linearly, d(p) = d(q) + |p - q| with q the nearest raster point (p clipped
to the raster's box), so far-off points are pulled back with a unit gradient instead of a flat zero.

The walkable log-likelihood of a position is the Gaussian of its distance outside, floored so a few
points off the plan (map errors, doors not drawn) do not veto a placement (slam.md 3.4):

    log L(p) = max(-1/2 (d(p) / sigma)^2, floor).

Wall crossing asks the floor's wall segments (for the competition's plans the walkable area's
boundary, shop fronts included; for simulated plans the walls with their doors open) through a
shapely STRtree: a move crosses a wall when the two segments cross at a point interior to both, the
same test as :func:`hybridloc.geo.wall_crossings`, without its N x M arrays.
"""

from __future__ import annotations

import numpy as np
import shapely
from scipy import ndimage

from ..types import Floor

#: Raster margin around the walkable area, m: enough for the distance to grow well beyond the
#: walkable likelihood's floor (sigma 1 m, floor -8: d = 4 m) before the linear extension takes over.
DEFAULT_MARGIN = 10.0


class WalkableField:
    """Distance outside one floor's walkable area and its gradient (implements ``ScalarField``).

    Parameters
    ----------
    inside : ndarray (ny, nx) bool
        Raster nodes in the walkable area; node (j, i) is at ``(x0 + i h, y0 + j h)``.
    x0, y0 : float
        Position of node (0, 0), m.
    resolution : float
        Node spacing h, m.
    walls : ndarray (M, 2, 2)
        Wall segments, m (for :meth:`crosses_wall`).
    walkable : shapely geometry or None
        The exact area (for :meth:`contains`); without it the raster answers.
    """

    def __init__(self, inside: np.ndarray, x0: float, y0: float, resolution: float, walls: np.ndarray | None = None, walkable=None) -> None:
        inside = np.asarray(inside, bool)
        if inside.ndim != 2 or min(inside.shape) < 2:
            raise ValueError("WalkableField: the raster needs at least 2 x 2 nodes")
        if not resolution > 0:
            raise ValueError("WalkableField: resolution must be positive")
        self.inside = inside
        self.x0, self.y0, self.resolution = float(x0), float(y0), float(resolution)
        h = self.resolution
        if inside.any():
            # distance from each outside node to the nearest inside node, less half a cell (the boundary
            # lies between the two nodes); inside nodes 0
            d = ndimage.distance_transform_edt(~inside) * h
            self.dist = np.where(inside, 0.0, np.maximum(d - 0.5 * h, 0.0))
        else:  # nothing walkable: every node is far outside (the field still has a gradient: none)
            self.dist = np.full(inside.shape, 1e6)
        ny, nx = inside.shape
        self.x1, self.y1 = self.x0 + (nx - 1) * h, self.y0 + (ny - 1) * h
        self.walls = np.zeros((0, 2, 2)) if walls is None else np.asarray(walls, float).reshape(-1, 2, 2)
        self.walkable = walkable
        self._wall_tree: shapely.STRtree | None = None

    @classmethod
    def from_floor(cls, floor: Floor, resolution: float = 0.25, margin: float = DEFAULT_MARGIN) -> WalkableField:
        """Rasterise ``floor.walkable`` at ``resolution`` m over its bounds plus ``margin`` m."""
        area = floor.walkable
        if area.is_empty:
            bx0, by0, bx1, by1 = floor.bounds()
        else:
            bx0, by0, bx1, by1 = area.bounds
        x0, y0 = bx0 - margin, by0 - margin
        nx = int(np.ceil((bx1 + margin - x0) / resolution)) + 1
        ny = int(np.ceil((by1 + margin - y0) / resolution)) + 1
        if nx * ny > 100_000_000:
            raise ValueError(f"floor {floor.name}: a {nx} x {ny} raster at {resolution} m is too large")
        gx, gy = x0 + resolution * np.arange(nx), y0 + resolution * np.arange(ny)
        X, Y = np.meshgrid(gx, gy)
        inside = shapely.contains_xy(area, X, Y) if not area.is_empty else np.zeros(X.shape, bool)
        return cls(inside, x0, y0, resolution, floor.walls, area)

    def __getstate__(self) -> dict:
        # caches stay behind should a field be pickled (today no path ships one: Dask workers and
        # forked copies build or inherit theirs): the remembered anchoring searches
        # (.anchoring.anchor_points) and log-likelihood rasters are made again where they are needed
        return {k: v for k, v in self.__dict__.items() if k not in ("_anchor_memo", "_raster_cache")}

    # ------------------------------------------------------------------------------------------
    def __call__(self, p) -> tuple[np.ndarray, np.ndarray]:
        """Distance outside the walkable area (0 inside), m, and its gradient, for points ``p`` (m, 2)."""
        p = np.asarray(p, float).reshape(-1, 2)
        h = self.resolution
        ny, nx = self.dist.shape
        q = np.column_stack([np.clip(p[:, 0], self.x0, self.x1), np.clip(p[:, 1], self.y0, self.y1)])
        fx, fy = (q[:, 0] - self.x0) / h, (q[:, 1] - self.y0) / h
        i = np.clip(np.floor(fx).astype(np.int64), 0, nx - 2)
        j = np.clip(np.floor(fy).astype(np.int64), 0, ny - 2)
        u, v = fx - i, fy - j
        D = self.dist
        d00, d10, d01, d11 = D[j, i], D[j, i + 1], D[j + 1, i], D[j + 1, i + 1]
        d = (1 - u) * (1 - v) * d00 + u * (1 - v) * d10 + (1 - u) * v * d01 + u * v * d11
        gx = ((1 - v) * (d10 - d00) + v * (d11 - d01)) / h
        gy = ((1 - u) * (d01 - d00) + u * (d11 - d10)) / h
        # beyond the raster: d(p) = d(q) + |p - q|; the clipped axes take the unit pull, the others keep
        # the raster's derivative (dq/dp is 0 along a clipped axis)
        off = p - q
        r = np.hypot(off[:, 0], off[:, 1])
        out = r > 0
        grad = np.column_stack([gx, gy])
        if out.any():
            d = d + r
            clipped = off != 0
            grad[clipped] = 0.0
            grad[out] += off[out] / r[out, None]
        return d, grad

    def contains(self, p) -> np.ndarray:
        """Which points ``p`` (m, 2) lie in the walkable area (the exact area when known, else the
        nearest raster node)."""
        p = np.asarray(p, float).reshape(-1, 2)
        if self.walkable is not None:
            return shapely.contains_xy(self.walkable, p[:, 0], p[:, 1])
        h = self.resolution
        ny, nx = self.inside.shape
        i = np.rint((p[:, 0] - self.x0) / h).astype(np.int64)
        j = np.rint((p[:, 1] - self.y0) / h).astype(np.int64)
        ok = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
        res = np.zeros(len(p), bool)
        res[ok] = self.inside[j[ok], i[ok]]
        return res

    def crosses_wall(self, p0, p1) -> np.ndarray:
        """Which moves ``p0[k] -> p1[k]`` ((m, 2) each) cross a wall segment (at a point interior to both)."""
        p0 = np.asarray(p0, float).reshape(-1, 2)
        p1 = np.asarray(p1, float).reshape(-1, 2)
        out = np.zeros(len(p0), bool)
        if len(p0) == 0 or len(self.walls) == 0:
            return out
        if self._wall_tree is None:
            self._wall_tree = shapely.STRtree(shapely.linestrings(self.walls))
        moves = shapely.linestrings(np.stack([p0, p1], axis=1))
        moving = (p0 != p1).any(axis=1)  # a zero-length move crosses nothing (and is not a valid line)
        idx = np.nonzero(moving)[0]
        if len(idx):
            hit = self._wall_tree.query(moves[idx], predicate="crosses")[0]
            out[idx[hit]] = True
        return out

    def log_likelihood(self, p, sigma: float = 1.0, floor: float = -8.0) -> np.ndarray:
        """Walkable log-likelihood ``max(-1/2 (d/sigma)^2, floor)`` of points ``p`` (m, 2) (slam.md 3.4)."""
        d, _ = self(p)
        return np.maximum(-0.5 * (d / sigma) ** 2, floor)

    def log_likelihood_raster(self, step: float, sigma: float = 1.0, floor: float = -8.0) -> tuple[np.ndarray, float, float]:
        """The log-likelihood on a coarser grid of nodes ``step`` m apart over the same box: (L (ny, nx),
        x0, y0), node (j, i) at ``(x0 + i step, y0 + j step)`` (what a correlation search slides over).
        Computed once per (step, sigma, floor) and kept; the array is read-only."""
        cache = self.__dict__.setdefault("_raster_cache", {})
        key = (float(step), float(sigma), float(floor))
        if key not in cache:
            cache[key] = self._log_likelihood_raster(step, sigma, floor)
        return cache[key]

    def _log_likelihood_raster(self, step: float, sigma: float, floor: float) -> tuple[np.ndarray, float, float]:
        nx = int(np.floor((self.x1 - self.x0) / step)) + 1
        ny = int(np.floor((self.y1 - self.y0) / step)) + 1
        X, Y = np.meshgrid(self.x0 + step * np.arange(nx), self.y0 + step * np.arange(ny))
        L = self.log_likelihood(np.column_stack([X.ravel(), Y.ravel()]), sigma, floor).reshape(ny, nx)
        L.flags.writeable = False
        return L, self.x0, self.y0

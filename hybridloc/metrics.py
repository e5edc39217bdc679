"""Evaluation metrics shared by every ``hybridloc eval`` command and benchmark.

* :func:`umeyama` / :func:`absolute_trajectory_error`: error after the best rigid (optionally
  similarity) alignment, Umeyama (1991), in 2-D or 3-D.
* :func:`return_to_start_error`: closed-loop error and percent of distance travelled, Ojeda &
  Borenstein (2007) eqs 7-9.
* :func:`error_at_points`: error at ground-truth points (e.g. waypoints) by interpolating the
  estimate in time.
* :func:`percentiles`, :func:`floor_hit_rate`, :func:`step_count_error`, :func:`summarize_errors`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares (R, t, s) minimising sum ||dst_i - (s R src_i + t)||^2 (Umeyama 1991).

    Parameters
    ----------
    src, dst : ndarray, shape (N, d)
        Corresponding points, d = 2 or 3, N >= d.

    Returns
    -------
    R : ndarray, shape (d, d)
        Proper rotation (det +1).
    t : ndarray, shape (d,)
    s : float
        1 unless ``with_scale``.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2:
        raise ValueError(f"umeyama: shapes {src.shape} and {dst.shape} must match and be (N, d)")
    n, d = src.shape
    if n < 2:
        raise ValueError("umeyama: need at least 2 points")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    # Cross-covariance Sigma = (1/n) sum xd xs^T; its SVD gives the rotation (Umeyama eqs 38-40).
    U, D, Vt = np.linalg.svd(xd.T @ xs / n)
    S = np.eye(d)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[-1, -1] = -1.0
    R = U @ S @ Vt
    var_s = (xs**2).sum() / n
    s = float(np.trace(np.diag(D) @ S) / var_s) if with_scale and var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


@dataclass(frozen=True)
class ErrorSummary:
    """Statistics of a set of position errors, metres."""

    n: int
    mean: float
    rmse: float
    median: float
    p75: float
    p90: float
    p95: float
    max: float

    def __str__(self) -> str:
        return (
            f"n={self.n} mean={self.mean:.3f} rmse={self.rmse:.3f} p50={self.median:.3f} "
            f"p75={self.p75:.3f} p90={self.p90:.3f} p95={self.p95:.3f} max={self.max:.3f}"
        )


def percentiles(errors: Sequence[float], qs: Sequence[float] = (50, 75, 95)) -> dict[float, float]:
    """Percentiles (linear interpolation) of the finite errors; NaN when there are none."""
    e = np.asarray(errors, dtype=float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {q: float("nan") for q in qs}
    return {q: float(v) for q, v in zip(qs, np.percentile(e, qs))}


def summarize_errors(errors: Sequence[float]) -> ErrorSummary:
    e = np.asarray(errors, dtype=float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        nan = float("nan")
        return ErrorSummary(0, nan, nan, nan, nan, nan, nan, nan)
    p = percentiles(e, (50, 75, 90, 95))
    return ErrorSummary(int(e.size), float(e.mean()), float(np.sqrt((e**2).mean())), p[50], p[75], p[90], p[95], float(e.max()))


@dataclass(frozen=True)
class AteResult:
    errors: np.ndarray  # (N,) per-sample position error after alignment, m
    R: np.ndarray
    t: np.ndarray
    s: float
    rmse: float
    mean: float
    aligned: np.ndarray  # (N, d) estimate after alignment


def absolute_trajectory_error(est: np.ndarray, gt: np.ndarray, dims: int = 2, with_scale: bool = False) -> AteResult:
    """Absolute trajectory error after the best rigid alignment of ``est`` onto ``gt``.

    Parameters
    ----------
    est, gt : ndarray, shape (N, >= dims)
        Time-synchronised positions, m.
    dims : 2 or 3
        Compare x, y only (2) or x, y, z (3).
    """
    if dims not in (2, 3):
        raise ValueError("dims must be 2 or 3")
    e = np.asarray(est, dtype=float)[:, :dims]
    g = np.asarray(gt, dtype=float)[:, :dims]
    R, t, s = umeyama(e, g, with_scale)
    al = (s * (R @ e.T)).T + t
    err = np.linalg.norm(al - g, axis=1)
    return AteResult(err, R, t, s, float(np.sqrt((err**2).mean())), float(err.mean()), al)


@dataclass(frozen=True)
class ReturnToStart:
    e_r: float  # ||end - start|| in the horizontal plane, m (Ojeda eq 7)
    distance: float  # total horizontal path length D, m
    e_p: float  # 100 e_r / D, percent (Ojeda eq 9)


def return_to_start_error(pos: np.ndarray) -> ReturnToStart:
    """Closed-loop error of one walk that ends where it started (Ojeda & Borenstein eqs 7, 9).

    e_r = sqrt(x_r^2 + y_r^2) with (x_r, y_r) the end point minus the start point; D is the
    horizontal distance travelled; E_p = 100 e_r / D. Average several walks' e_r for eq 8.
    """
    p = np.asarray(pos, dtype=float)[:, :2]
    if len(p) < 2:
        raise ValueError("need at least two positions")
    e_r = float(np.linalg.norm(p[-1] - p[0]))
    D = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    return ReturnToStart(e_r, D, 100.0 * e_r / D if D > 0 else float("nan"))


def interpolate_positions(t_est: np.ndarray, pos_est: np.ndarray, t_query: np.ndarray) -> np.ndarray:
    """Linear interpolation of positions (N, d) at query times; NaN outside the estimate's span."""
    t_est = np.asarray(t_est, dtype=float)
    pos_est = np.asarray(pos_est, dtype=float)
    tq = np.asarray(t_query, dtype=float)
    out = np.column_stack([np.interp(tq, t_est, pos_est[:, k]) for k in range(pos_est.shape[1])])
    outside = (tq < t_est[0]) | (tq > t_est[-1])
    out[outside] = np.nan
    return out


def error_at_points(t_est: np.ndarray, pos_est: np.ndarray, t_true: np.ndarray, pos_true: np.ndarray, dims: int = 2) -> np.ndarray:
    """Horizontal (dims=2) or 3-D error at each ground-truth point, the estimate interpolated in time.

    Points outside the estimate's time span get NaN (not counted by :func:`summarize_errors`).
    """
    est = interpolate_positions(t_est, np.asarray(pos_est)[:, :dims], t_true)
    return np.linalg.norm(est - np.asarray(pos_true, dtype=float)[:, :dims], axis=1)


def floor_hit_rate(est_floor: Sequence, true_floor: Sequence) -> float:
    """Fraction of entries where the estimated floor equals the truth (None counts as a miss)."""
    if len(est_floor) != len(true_floor):
        raise ValueError("floor sequences differ in length")
    if len(true_floor) == 0:
        return float("nan")
    return float(np.mean([e is not None and e == t for e, t in zip(est_floor, true_floor)]))


def step_count_error(n_detected: int, n_true: int) -> float:
    """Relative step-count error (n_detected - n_true) / n_true (signed; multiply by 100 for %)."""
    if n_true <= 0:
        raise ValueError("n_true must be positive")
    return (n_detected - n_true) / n_true


def pyshoe_align(est: np.ndarray, gt: np.ndarray, dist: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """PyShoe's alignment: shift both tracks to start at 0, then rotate the estimate about the vertical
    so that its position at the first sample at least ``dist`` m (horizontally) from the start points
    the same way as the truth's at that sample. Returns (estimate, truth), both (N, 3)."""
    e = np.asarray(est, dtype=float) - est[0]
    g = np.asarray(gt, dtype=float) - gt[0]
    d = np.hypot(e[:, 0], e[:, 1])
    far = np.flatnonzero(d >= dist)
    k = int(far[0]) if far.size else min(300, len(e) - 1)
    ang = np.arctan2(g[k, 1], g[k, 0]) - np.arctan2(e[k, 1], e[k, 0])
    c, s = np.cos(ang), np.sin(ang)
    out = e.copy()
    out[:, 0], out[:, 1] = c * e[:, 0] - s * e[:, 1], s * e[:, 0] + c * e[:, 1]
    return out, g


def pyshoe_armse(est: np.ndarray, gt: np.ndarray, dims: int = 2) -> float:
    """PyShoe's ARMSE: mean over samples of sqrt(mean over the ``dims`` axes of the squared error)."""
    diff = np.asarray(est, dtype=float)[:, :dims] - np.asarray(gt, dtype=float)[:, :dims]
    return float(np.mean(np.sqrt(np.mean(diff**2, axis=1))))


def first_leg_rotation(est_xy: np.ndarray, true_xy: np.ndarray) -> float:
    """Rotation (rad) turning an estimated track's first leg (points 0 -> 1) onto the true one; 0 when
    the estimate barely moved. With the first point, the "oracle start pose" of a dead-reckoned track."""
    de, dt_ = np.asarray(est_xy[1]) - np.asarray(est_xy[0]), np.asarray(true_xy[1]) - np.asarray(true_xy[0])
    if float(np.hypot(*de)) <= 0.1:
        return 0.0
    d = math.atan2(dt_[1], dt_[0]) - math.atan2(de[1], de[0])
    return math.atan2(math.sin(d), math.cos(d))


def oracle_start_errors(est_xy: np.ndarray, true_xy: np.ndarray) -> np.ndarray:
    """Errors at points 1.. of a dead-reckoned track started at the true first point and rotated so its
    first leg points the true way (how PDR alone is scored against waypoints)."""
    est_xy, true_xy = np.asarray(est_xy, float), np.asarray(true_xy, float)
    rot = first_leg_rotation(est_xy, true_xy)
    c, s = math.cos(rot), math.sin(rot)
    aligned = (est_xy - est_xy[0]) @ np.array([[c, s], [-s, c]]) + true_xy[0]
    return np.linalg.norm(aligned[1:] - true_xy[1:], axis=1)


# ------------------------------------------------------------------ causal scoring of live estimates
def held_rows(poses, wp_t) -> np.ndarray:
    """For each waypoint after the first, the index of the newest pose row with t <= its time (as a
    live client would show it; at equal t the later row), -1 before the first row."""
    if not poses:
        return np.full(max(len(wp_t) - 1, 0), -1)
    order = np.array(sorted(range(len(poses)), key=lambda i: (poses[i][0], i)))
    k = np.searchsorted(np.array([poses[i][0] for i in order]), np.asarray(wp_t[1:], float), side="right") - 1
    return np.where(k >= 0, order[np.maximum(k, 0)], -1)


def causal_errors(poses, wp_t, wp_xy) -> np.ndarray:
    """Causal scoring: at each waypoint (after the first) the newest estimate available then; NaN before the first."""
    out = np.full(max(len(wp_t) - 1, 0), np.nan)
    idx = held_rows(poses, wp_t)
    ok = idx >= 0
    if ok.any():
        xy = np.array([[poses[i][1], poses[i][2]] for i in idx[ok]])
        out[ok] = np.linalg.norm(xy - np.asarray(wp_xy[1:])[ok], axis=1)
    return out


# ------------------------------------------------------------------ radio-map coverage
def walkable_reach(walkable, xy, radius_m: float):
    """The part of a floor's walkable area within ``radius_m`` of any of the points ``xy`` (m, 2) (a
    radio map's labelled scans, say): walkable ∩ ∪ disc(p, r), a shapely geometry (empty without a
    finite point). The discs are buffered polygons (64 segments per circle: the area of each within
    0.2 % of pi r^2)."""
    import shapely

    if not (math.isfinite(radius_m) and radius_m > 0):
        raise ValueError(f"walkable_reach: radius must be positive, got {radius_m}")
    p = np.asarray(xy, float).reshape(-1, 2)
    p = p[np.isfinite(p).all(axis=1)]
    if walkable is None or walkable.is_empty or not len(p):
        return shapely.MultiPolygon()
    return walkable.intersection(shapely.union_all(shapely.buffer(shapely.points(p), radius_m, quad_segs=16)))


def walkable_coverage(walkable, xy, radius_m: float) -> float:
    """Share of a floor's walkable area within ``radius_m`` of any of the points ``xy`` (m, 2):
    area(:func:`walkable_reach`) / area(walkable), in [0, 1]; NaN when the walkable area is empty."""
    reach = walkable_reach(walkable, xy, radius_m)  # checks the radius first
    if walkable is None or walkable.is_empty or not walkable.area > 0:
        return float("nan")
    return float(min(1.0, reach.area / walkable.area))


# ------------------------------------------------------------------ convergence from a cold start
def time_to_within(poses, wp_t, wp_xy, radius_m: float, window_s: float, wp_floors=None) -> float:
    """Seconds from a walk's first waypoint until its track first comes within ``radius_m`` of the
    truth, looking ``window_s`` seconds on; inf when it does not in that time (or the walk has no
    waypoint after the first).

    ``poses``: rows (t, x, y, floor, ...) as a client writes them; the track at time t is the newest
    row at or before t (a live client's view), so it is scored at each row's time (where it changes)
    against the truth there: the waypoints interpolated linearly in time (the Indoor Location
    Competition's ground truth between marks). ``wp_floors`` (one per waypoint, or None): a row on
    another floor than the truth's is not within, however near. Rows after the last waypoint, or
    before the first, are not scored.
    """
    if not (radius_m > 0 and window_s > 0):
        raise ValueError("time_to_within: radius and window must be positive")
    wt, wxy = np.asarray(wp_t, float), np.asarray(wp_xy, float).reshape(-1, 2)
    if len(wt) < 2 or not poses:
        return math.inf
    t = np.array([p[0] for p in poses], float)
    xy = np.array([[p[1], p[2]] for p in poses], float)
    on = (t > wt[0]) & (t <= min(wt[0] + window_s, wt[-1]))
    if not on.any():
        return math.inf
    idx = np.flatnonzero(on)
    truth = np.column_stack([np.interp(t[idx], wt, wxy[:, 0]), np.interp(t[idx], wt, wxy[:, 1])])
    near = np.linalg.norm(xy[idx] - truth, axis=1) < radius_m
    if wp_floors is not None:
        k = np.clip(np.searchsorted(wt, t[idx], side="right") - 1, 0, len(wt) - 1)  # the mark at or before each time
        fl = [poses[i][3] if len(poses[i]) > 3 else None for i in idx]
        near &= np.array([f is None or wp_floors[j] is None or f == wp_floors[j] for f, j in zip(fl, k)], bool)
    hit = np.flatnonzero(near)
    return float(t[idx[hit[0]]] - wt[0]) if hit.size else math.inf

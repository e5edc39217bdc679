"""Floor-plan anchoring of walk groups on site1 (issue #20 point 4; shared-notes slam.md 3.4-3.5).

A group of walks with their true relative shape - each walk's waypoint polyline sampled every 1 m, the
group then rotated by U(-8, 8) deg, scaled by U(0.92, 1.08) and shifted by an unknown offset - is placed
on its floor's walkable area by :func:`hybridloc.slam.anchoring.anchor_points`. A group is what a
connected component of the crowd graph looks like: a random seed walk plus, one at a time, the walk
nearest to the group (so the group is spatially connected, not spread over the floor). Per floor
(F1, F2, F3) and group size it reports how often the anchoring claims a placement (not ambiguous), how
often the claim is right (points back within 3 m RMS of the truth), how often it claims a wrong one,
and, for choosing the ambiguity threshold, the best mode's correctness against the log-likelihood
margin over the runner-up. Seconds per call too. Needs ../shared/data/msft-ilc/site1.

    python -m benchmarks.bench_anchoring [--trials 20] [--sizes 1 5 15] [--seed 0]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from benchmarks import headline
from hybridloc.io.msft import find_ilc_traces, read_ilc_site, read_ilc_waypoints
from hybridloc.slam.anchoring import MIN_LOG_RATIO, MIN_MEAN_FIT, anchor_points
from hybridloc.slam.floorplan import WalkableField

SITE = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "msft-ilc" / "site1"
#: A placement is right when the group's points are back within this RMS distance of the truth, m.
RIGHT_M = 3.0


def polyline_points(xy: np.ndarray, spacing: float = 1.0) -> np.ndarray:
    """Points every ``spacing`` m along a polyline (its vertices' path), the first vertex included."""
    seg = np.diff(xy, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(seg[:, 0], seg[:, 1]))])
    if s[-1] <= 0:
        return xy[:1]
    q = np.arange(0.0, s[-1] + 1e-9, spacing)
    return np.column_stack([np.interp(q, s, xy[:, 0]), np.interp(q, s, xy[:, 1])])


def grow_group(walks: list[np.ndarray], size: int, rng: np.random.Generator) -> list[int]:
    """A random seed walk, then repeatedly the walk nearest to the group (min point distance)."""
    group = [int(rng.integers(len(walks)))]
    while len(group) < min(size, len(walks)):
        tree = cKDTree(np.vstack([walks[g] for g in group]))
        best, best_d = -1, math.inf
        for i, w in enumerate(walks):
            if i in group:
                continue
            d = float(tree.query(w, k=1)[0].min())
            if d < best_d:
                best, best_d = i, d
        group.append(best)
    return group


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20, help="groups per floor and size")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 5, 15])
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    if not SITE.is_dir():
        print(f"{SITE} is absent: nothing to measure")
        headline({"skipped": True})
        return 0
    rng = np.random.default_rng(a.seed)
    plan = read_ilc_site(SITE)
    rows = []  # (floor, size, margin, mean_fit, best_right, claimed, seconds, n_points)
    for fl in plan.floors:
        t0 = time.perf_counter()
        field = WalkableField.from_floor(fl)
        t_field = time.perf_counter() - t0
        walks = [polyline_points(read_ilc_waypoints(p).pos_enu) for p in find_ilc_traces(SITE / fl.name)]
        walks = [w for w in walks if len(w) >= 2]
        print(f"{fl.name}: {len(walks)} walks, walkable {fl.walkable.area:.0f} m^2 of {fl.outline.area:.0f}; field {t_field:.2f} s")
        for size in a.sizes:
            for _ in range(a.trials):
                g = grow_group(walks, size, rng)
                truth = np.vstack([walks[i] for i in g])
                th, s = math.radians(rng.uniform(-8.0, 8.0)), rng.uniform(0.92, 1.08)
                R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
                c = truth.mean(0)
                comp = ((truth - c) @ R) / s + rng.uniform(-100.0, 100.0, 2)  # truth = s R (comp - offset) + c
                t1 = time.perf_counter()
                res = anchor_points(comp, field)
                dt = time.perf_counter() - t1
                rms = float(np.sqrt(np.mean(np.sum((res.apply(comp) - truth) ** 2, axis=1))))
                rows.append((fl.name, size, res.score - res.runner_up, res.mean_fit, rms <= RIGHT_M, not res.ambiguous, dt, len(comp)))
    arr = np.array([(r[1], r[2], r[3], r[4], r[5], r[6], r[7]) for r in rows], float)
    floors = np.array([r[0] for r in rows])
    print(f"\nclaims (min_log_ratio {MIN_LOG_RATIO:g}, min_mean_fit {MIN_MEAN_FIT:g}); right = within {RIGHT_M:g} m RMS")
    print("floor  walks  groups  points  best right  claimed  claimed right  claimed wrong  s/call")
    figures: dict = {}
    for size in a.sizes:
        for f in [*sorted(set(floors)), "all"]:
            m = (arr[:, 0] == size) & ((floors == f) if f != "all" else True)
            if not m.any():
                continue
            best_right, claimed = arr[m, 3].astype(bool), arr[m, 4].astype(bool)
            print(
                f"{f:>5}  {size:5d}  {m.sum():6d}  {np.median(arr[m, 6]):6.0f}  {best_right.mean():10.0%}  {claimed.mean():7.0%}"
                f"  {(claimed & best_right).mean():13.0%}  {(claimed & ~best_right).mean():13.0%}  {np.median(arr[m, 5]):6.2f}"
            )
            if f == "all":
                figures[f"recovered_{size}"] = (claimed & best_right).mean()
                figures[f"wrong_claims_{size}"] = (claimed & ~best_right).mean()
    # the threshold's choice: the margin over the runner-up when the best mode is right vs wrong
    fit_ok = arr[:, 2] >= MIN_MEAN_FIT
    print("\nmargin over the runner-up (log-likelihood, weights = metres of path), fit ok:")
    for thr in (5.0, 10.0, 20.0, 40.0, 80.0):
        claim = fit_ok & (arr[:, 1] >= thr)
        right = arr[:, 3].astype(bool)
        parts = []
        for size in a.sizes:
            m = arr[:, 0] == size
            parts.append(f"size {size}: claimed right {(claim & right & m).sum() / m.sum():4.0%} wrong {(claim & ~right & m).sum() / m.sum():4.0%}")
        print(f"  >= {thr:5.0f}: " + "; ".join(parts))
    wrong_best = ~arr[:, 3].astype(bool) & fit_ok
    if wrong_best.any():
        print(
            f"  margins of wrong best modes: p50 {np.median(arr[wrong_best, 1]):.1f}, p90 {np.percentile(arr[wrong_best, 1], 90):.1f}, max {arr[wrong_best, 1].max():.1f}"
        )
    figures["seconds_per_call_median"] = float(np.median(arr[:, 5]))
    figures["seconds_per_call_max"] = float(np.max(arr[:, 5]))
    headline(figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Which labels place the badly placed crowd walks (issue #21, correction)? Runs ``hybridloc eval slam``'s
split of SITE_DIR (the same walks, survey draw and SLAM), then, for every crowd walk piece the final
solve placed by radio-map fixes (``anchored`` = ``map``), prints its error at its hidden waypoints, how
many of its fixes came from the survey map and from the crowd map (EM), and which labels its scans
match in the map EM locates it with: the labels of the other EM folds (every anchored walk's, the
survey walks' included; at their final positions), the ``knn_k`` nearest in fingerprint space, with
their truth error and their walks.

The truth only measures; nothing here feeds back into the SLAM.

Usage: python scripts/probe_em_sources.py SITE_DIR [--survey-fraction F] [--seed S] [--worst N]
Prints the N worst pieces, a table by survey-map fixes, and one summary JSON line."""

import argparse
import io
import json
from collections import Counter

import numpy as np

import hybridloc.slam.evaluate as ev
from hybridloc.io.msft import find_ilc_traces, read_ilc_waypoints
from hybridloc.radio.locate import KnnLocator
from hybridloc.slam import pipeline as pl

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("site_dir")
ap.add_argument("--survey-fraction", type=float, default=0.1)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--worst", type=int, default=20)
args = ap.parse_args()

# the run's result and its floors' final FloorSlam objects (the last anchors() of each floor: the final
# EM round's registrations and fixes), taken by wrapping the two calls
held: dict = {}
_run_slam, _solve = ev.run_slam, pl.FloorSlam.solve


def run_slam(*a, **kw):
    held["res"] = _run_slam(*a, **kw)
    return held["res"]


def solve(self):
    held.setdefault("slams", {})[self.floor] = self
    fs = _solve(self)
    # survey-map fixes among the fixes that placed each piece (map_fixes come first in anchors())
    self.survey_support = {k: sum(1 for f in fx if any(f is m for m in self.map_fixes.get(k, []))) for k, fx in self._anchors_fixes.items()}
    return fs


_anchors = pl.FloorSlam.anchors


def anchors(self, pieces_idx=None):
    a = _anchors(self, pieces_idx)
    self._anchors_fixes = dict(a.fixes)
    return a


ev.run_slam, pl.FloorSlam.solve, pl.FloorSlam.anchors = run_slam, solve, anchors
summary = ev.run_slam_eval(args.site_dir, args.survey_fraction, args.seed, out=io.StringIO())
res, slams = held["res"], held["slams"]
paths = {p.name.split(".")[0]: p for p in find_ilc_traces(args.site_dir)}
wps = {n: read_ilc_waypoints(p) for n, p in paths.items()}


def truth_err(name: str, t: float, pos) -> float:
    wp = wps.get(name)
    if wp is None or len(wp.t) < 2 or not wp.t[0] <= t <= wp.t[-1]:
        return float("nan")
    return float(np.linalg.norm(np.asarray(pos)[:2] - ev._truth_at(wp, np.array([t]))[0]))


cfg = pl.SlamConfig()
wifi = [i for i, ls in enumerate(res.labels) if ls.scan.technology.value == "wifi"]
labels = [res.labels[i] for i in wifi]
lab_src = np.array([ls.source for ls in labels])
lab_err = np.array([truth_err(ls.source, ls.scan.t, ls.pos_enu) for ls in labels])
# EM's folds (run_slam): walk index mod em_folds; a walk is located with the labels of the other folds
n_folds = max(cfg.em_folds, 2)
lab_fold = np.array([res.label_walk[i] % n_folds for i in wifi])
locs = {
    f: (KnnLocator([labels[i] for i in np.flatnonzero(lab_fold != f)], k=cfg.knn_k, max_age_s=cfg.knn_max_age_s), np.flatnonzero(lab_fold != f))
    for f in range(n_folds)
}
rows = []
for fname, fs in sorted(res.floors.items()):
    fsl = slams[fname]
    for k, pc in enumerate(fs.pieces):
        name = res.names[pc.walk]
        if res.walks[pc.walk].marks or fs.status[k] != pl.MAP:
            continue
        wp = wps[name]
        sel = (wp.t >= pc.t[0]) & (wp.t <= pc.t[-1])
        if not sel.any():
            continue
        err = float(np.linalg.norm(fs.track(k, wp.t[sel]) - wp.pos_enu[sel], axis=1).mean())
        n_fix = len(fsl._anchors_fixes.get(k, []))
        n_survey = fsl.survey_support.get(k, 0)
        scans = [pc.scans[int(pc.scan[i])] for i in np.flatnonzero(pc.scan >= 0)]
        scans = [s for s in scans if s.technology.value == "wifi"]
        nb_err, nb_src = [], []
        if scans:
            loc, at = locs[pc.walk % n_folds]
            for row in loc.nearest(scans)[1]:
                nb_err.extend(lab_err[at[row]].tolist())
                nb_src.extend(lab_src[at[row]].tolist())
        rows.append(dict(floor=fname, walk=name, err_m=err, fixes=n_fix, survey_fixes=n_survey, nb_err=nb_err, nb_src=nb_src))
# a matched label's walk: its piece on the same floor (error, survey-map fixes), or what placed it otherwise
walk_err = {(r["walk"], r["floor"]): r["err_m"] for r in rows}
survey_of = {(r["walk"], r["floor"]): r["survey_fixes"] for r in rows}
surveyed = {res.names[w] for w in range(len(res.walks)) if res.walks[w].marks}


def source_text(src: str, n: int, floor: str) -> str:
    if (src, floor) in walk_err:
        return f"{src[:8]} x{n} ({walk_err[(src, floor)]:.1f}, {survey_of[(src, floor)]})"
    return f"{src[:8]} x{n} ({'survey walk' if src in surveyed else 'not map-placed'})"


print(f"{len(rows)} crowd pieces placed by map fixes (eval slam split of {args.site_dir}, F = {args.survey_fraction:g}, seed {args.seed})")
print("worst: floor walk  error m  fixes (survey map)  matched labels: median error m, share > 15 m, their walks (error m, survey-map fixes)")
for r in sorted(rows, key=lambda r: -r["err_m"])[: args.worst]:
    e = np.asarray(r["nb_err"], float)
    top = Counter(r["nb_src"]).most_common(3)
    srcs = ", ".join(source_text(s, n, r["floor"]) for s, n in top)
    known = e[np.isfinite(e)]
    med = f"{np.median(known):5.1f}" if len(known) else "    -"
    share = f"{np.mean(known > 15):.2f}" if len(known) else "   -"
    print(f"  {r['floor']} {r['walk'][:8]} {r['err_m']:6.1f}  {r['fixes']:3d} ({r['survey_fixes']:2d})  {med} {share}  {srcs}")
bins = {}
print("by survey-map fixes among those that placed the piece:")
for lo, hi, key in ((0, 0, "0"), (1, 2, "1-2"), (3, 10**9, ">=3")):
    s = [r for r in rows if lo <= r["survey_fixes"] <= hi]
    if not s:
        continue
    mean = float(np.mean([r["err_m"] for r in s]))
    bad = sum(r["err_m"] > 20 for r in s)
    bins[key] = dict(pieces=len(s), mean_err_m=round(mean, 2), over_20m=bad)
    print(f"  {key:>4}: {len(s)} pieces, mean error {mean:.2f} m, {bad} over 20 m")
bad = [r for r in rows if r["err_m"] > 20]
own = [x for r in bad for x in r["nb_err"] if np.isfinite(x)]
own_em = [x for r in bad if r["survey_fixes"] == 0 for x in r["nb_err"] if np.isfinite(x)]
fig = dict(
    pieces_map=len(rows),
    over_20m=len(bad),
    over_20m_without_survey_fixes=sum(r["survey_fixes"] == 0 for r in bad),
    over_20m_matched_label_err_median_m=round(float(np.median(own)), 2) if own else None,
    over_20m_without_survey_fixes_matched_label_err_median_m=round(float(np.median(own_em)), 2) if own_em else None,
    by_survey_fixes=bins,
    crowd_mean_m=round(summary["crowd_mean_m"], 2),
    seed=args.seed,
)
print(json.dumps(fig))

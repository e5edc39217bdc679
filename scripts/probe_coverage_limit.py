"""How much of the crowd could any loop detector anchor (issue #21, coverage)? An oracle on the truth.

Usage: python scripts/probe_coverage_limit.py SERVER_DB SITE_DIR [--survey-fraction F] [--seed S]
(SERVER_DB: the server.db an ``hybridloc eval crowd --out DIR`` run leaves, with that run's F and S).

Every walk's true path is its waypoints joined by straight lines, sampled every metre. A fingerprint
loop can only join two walks where they pass near each other: single-scan similarity's best match from
another walk is a median 4.7-6.2 m away (shared-notes slam.md 0.2), so "near" is tried at 3 and 5 m.
Starting from the surveys (their marks are absolute) and the walks the server anchored, a walk is
*reachable* when at least ``--min-overlap`` metres of its true path lie within r of an anchored walk's
true path on its floor; reachable walks are added and the closure repeated (a perfect front end chains
walks). The oracle's coverage, scans of unmarked walks in anchored or reachable walks, is an upper bound
of what loop closures with a perfect front end could anchor (the floor-plan search, which places shapes
with no loop, is apart). Prints one JSON line per relative walk, then the summary JSON line."""

import argparse
import json

import numpy as np
from scipy.spatial import cKDTree

from hybridloc.crowd_eval import plan_crowd
from hybridloc.io.msft import read_ilc_trace
from hybridloc.server.store import Store

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("db")
ap.add_argument("site_dir")
ap.add_argument("--survey-fraction", type=float, default=0.1)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--min-overlap", type=float, default=5.0, help="metres of path near an anchored walk, default 5")
args = ap.parse_args()

store = Store(f"sqlite:///{args.db}")
plan = plan_crowd(args.site_dir, args.survey_fraction, args.seed)
site = plan.site
states = store.slam.walk_states(site)
dev_of = {w.walk_id: w.device for w in store.walks(site)}
status_of_dev = {dev_of[wid]: st for wid, st in states.items() if wid in dev_of}


def true_path(path):
    tr = read_ilc_trace(path)
    wp = np.asarray(tr.waypoints.pos_enu, float)[:, :2]
    if len(wp) < 2:
        return wp, tr
    seg = np.linalg.norm(np.diff(wp, axis=0), axis=1)
    s = np.r_[0.0, np.cumsum(seg)]
    q = np.arange(0.0, s[-1] + 1e-9, 1.0)
    return np.c_[np.interp(q, s, wp[:, 0]), np.interp(q, s, wp[:, 1])], tr


walks = {}
for w in plan.surveys:
    p, _ = true_path(w.path)
    walks[w.device] = dict(floor=w.floor, p=p, kind="survey", n_scan=0)
for w in plan.clients:
    p, tr = true_path(w.path)
    st = status_of_dev.get(w.device)
    kind = "none" if st is None else ("absolute" if st.status == "corrected" and st.anchored != "relative" else st.status)
    walks[w.device] = dict(floor=w.floor, p=p, kind=kind, n_scan=len(tr.scans))

n_total = sum(w["n_scan"] for w in walks.values() if w["kind"] != "survey")
summary = dict(
    clients=sum(w["kind"] != "survey" for w in walks.values()),
    kinds={k: sum(w["kind"] == k for w in walks.values()) for k in sorted({w["kind"] for w in walks.values()})},
    server_coverage=sum(w["n_scan"] for w in walks.values() if w["kind"] == "absolute") / n_total,
)
for r in (3.0, 5.0, 8.0):
    anchored = {d for d, w in walks.items() if w["kind"] in ("survey", "absolute")}
    rounds = 0
    while True:
        added = set()
        for fl in {w["floor"] for w in walks.values()}:
            A = [walks[d]["p"] for d in anchored if walks[d]["floor"] == fl and len(walks[d]["p"])]
            if not A:
                continue
            tree = cKDTree(np.vstack(A))
            for d, w in walks.items():
                if d in anchored or w["floor"] != fl or not len(w["p"]):
                    continue
                near = tree.query(w["p"], distance_upper_bound=r)[0] <= r
                if near.sum() >= args.min_overlap:  # samples are 1 m apart
                    added.add(d)
        if not added:
            break
        anchored |= added
        rounds += 1
        if rounds == 1:
            direct = set(added)
    rel = [d for d, w in walks.items() if w["kind"] == "relative"]
    summary[f"r{r:g}"] = dict(
        oracle_coverage=sum(walks[d]["n_scan"] for d in anchored if walks[d]["kind"] != "survey") / n_total,
        relative_reachable_direct=sum(d in direct for d in rel) if rounds else 0,
        relative_reachable_chained=sum(d in anchored for d in rel),
        relative_walks=len(rel),
        rounds=rounds,
    )
# per relative walk: its path length and the metres within 3 / 5 m of the server's anchored walks (no chaining)
for fl in sorted({w["floor"] for w in walks.values()}):
    A = [w["p"] for w in walks.values() if w["floor"] == fl and w["kind"] in ("survey", "absolute") and len(w["p"])]
    tree = cKDTree(np.vstack(A)) if A else None
    for d, w in sorted(walks.items()):
        if w["floor"] != fl or w["kind"] != "relative" or tree is None:
            continue
        dist = tree.query(w["p"])[0] if len(w["p"]) else np.array([])
        print(
            json.dumps(
                dict(
                    device=d,
                    floor=fl,
                    length_m=len(w["p"]),
                    scans=w["n_scan"],
                    near3_m=int((dist <= 3).sum()),
                    near5_m=int((dist <= 5).sum()),
                    dist_median_m=float(np.median(dist)) if len(dist) else None,
                )
            )
        )
print(json.dumps(summary))

"""Why are crowd walks left relative (issue #21, coverage)? Force-register every crowd walk piece against
the final map (its own labels excluded) and score the forced placement at the walk's hidden waypoints.

Usage: python scripts/probe_relative_walks.py SERVER_DB SITE_DIR [--survey-fraction F] [--seed S] [--no-gate]
(SERVER_DB: the server.db an ``hybridloc eval crowd --out DIR`` run leaves, with that run's F and S, so
that the same walks are the clients; --no-gate: the relative walks only, with the mapped-distance gate
of their fixes lifted). One JSON line per walk piece, then a summary JSON line."""

import argparse
import json

import numpy as np
from scipy.spatial import cKDTree

from hybridloc.crowd_eval import plan_crowd
from hybridloc.io.msft import read_ilc_trace
from hybridloc.server.slam_batch import load_site
from hybridloc.server.store import Store
from hybridloc.slam.register import register_walk

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("db")
ap.add_argument("site_dir")
ap.add_argument("--survey-fraction", type=float, default=0.1)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--no-gate", action="store_true")
args = ap.parse_args()

store = Store(f"sqlite:///{args.db}")
plan = plan_crowd(args.site_dir, args.survey_fraction, args.seed)
site = plan.site
by_dev = {w.device: w for w in plan.clients}
slam = load_site(store, site)
if args.no_gate:
    slam._gate = float("inf")
states = store.slam.walk_states(site)
infos = {w.walk_id: w for w in store.walks(site)}
refs = slam._map.references
ref_xy = np.array([r.pos_enu[:2] for r in refs], float)
ref_floor = np.array([r.floor for r in refs])
ref_src = np.array([r.source for r in refs])
rows = []
for wid, st in sorted(states.items()):
    info = infos.get(wid)
    cw = by_dev.get(info.device) if info else None
    if cw is None:
        continue  # a survey walk
    if args.no_gate and st.status != "relative":
        continue
    tr = read_ilc_trace(cw.path)
    wt, wxy = np.asarray(tr.waypoints.t, float), np.asarray(tr.waypoints.pos_enu, float)[:, :2]
    for j, pc in enumerate(slam._walk_pieces(store.read_walk(wid))):
        sel = (wt >= pc.t[0]) & (wt <= pc.t[-1])  # the piece's waypoints
        fx = slam._map_fixes([pc], exclude={str(wid)}).get(0, [])
        rec = dict(walk=wid, piece=j, floor=pc.floor, status=st.status, anchored=st.anchored, n_fix=len(fx), n_wp=0)
        if fx:
            qf = np.array([pc.q[i] for i, _, _ in fx])
            zf = np.array([z for _, z, _ in fx])
            sd = np.array([float(np.sqrt(np.linalg.eigvalsh(R).max())) for _, _, R in fx])
            reg = register_walk(qf, zf, sd, pc.step_q, slam._floor(pc.floor).field, slam.cfg.register)
            rec.update(placed=reg.placed, reason=reg.reason, support=reg.support, margin=float(reg.score - reg.runner_up))
            if np.isfinite(reg.score) and sel.any():
                p = pc.q @ reg.T.T + reg.t
                px = np.c_[np.interp(wt[sel], pc.t, p[:, 0]), np.interp(wt[sel], pc.t, p[:, 1])]
                e = np.linalg.norm(px - wxy[sel], axis=1)
                rec.update(n_wp=int(sel.sum()), err_median=float(np.median(e)), err_mean=float(e.mean()))
        other = ref_xy[(ref_floor == pc.floor) & (ref_src != str(wid))]
        if len(other) and sel.any():
            # each waypoint's distance to the nearest map label of other walks, m
            rec.update(wp_dist_to_map=[float(x) for x in cKDTree(other).query(wxy[sel])[0]])
        rows.append(rec)
        print(json.dumps(rec), flush=True)

summary = {}
for key in ("corrected", "relative"):
    S = [r for r in rows if r["status"] == key]
    E = np.array([r["err_median"] for r in S if r.get("placed") and "err_median" in r])
    D = np.array([x for r in S for x in r.get("wp_dist_to_map", [])])
    summary[key] = dict(
        wp_dist_to_map_median_m=float(np.median(D)) if len(D) else None,
        wp_share_over_8m=float(np.mean(D > 8)) if len(D) else None,
        pieces=len(S),
        no_fix=sum(r["n_fix"] == 0 for r in S),
        placed=int(sum(bool(r.get("placed")) for r in S)),
        placed_err_median_m=float(np.median(E)) if len(E) else None,
        placed_share_under_5m=float(np.mean(E < 5)) if len(E) else None,
    )
print(json.dumps(dict(no_gate=args.no_gate, **summary)))

"""Why are crowd walks left relative (issue #21, coverage)? Force-register every crowd walk piece against the final map (its
own labels excluded) and score the forced placement at the walk's hidden waypoints.

Usage: python scripts/probe_relative_walks.py SERVER_DB SITE_DIR [--no-gate]
(SERVER_DB: the server.db an ``hybridloc eval crowd --out DIR`` run leaves; --no-gate: the relative walks
only, with the mapped-distance gate of their fixes lifted). One JSON line per walk piece, then a summary
JSON line."""

import json
import sys

import numpy as np

from hybridloc.crowd_eval import plan_crowd
from hybridloc.io.msft import read_ilc_trace
from hybridloc.server.slam_batch import load_site
from hybridloc.server.store import Store
from hybridloc.slam.register import register_walk

db, site_dir = sys.argv[1], sys.argv[2]
no_gate = "--no-gate" in sys.argv[3:]
store = Store(f"sqlite:///{db}")
plan = plan_crowd(site_dir, 0.1, 0)
site = plan.site
by_dev = {w.device: w for w in plan.clients}
slam = load_site(store, site)
states = store.slam.walk_states(site)
infos = {w.walk_id: w for w in store.walks(site)}
rows = []
for wid, st in sorted(states.items()):
    info = infos.get(wid)
    cw = by_dev.get(info.device) if info else None
    if cw is None or (no_gate and st.status != "relative"):
        continue  # a survey walk
    walk = store.read_walk(wid)
    tr = read_ilc_trace(cw.path)
    wt, wxy = np.asarray(tr.waypoints.t, float), np.asarray(tr.waypoints.pos_enu, float)
    for j, pc in enumerate(slam._walk_pieces(walk)):
        fl = slam._floor(pc.floor)
        if no_gate:
            slam._gate = float("inf")
        fx = slam._map_fixes([pc], exclude={str(wid)}).get(0, [])
        rec = dict(walk=wid, piece=j, floor=pc.floor, status=st.status, anchored=st.anchored, n_fix=len(fx), n_wp=0)
        if len(fx) >= 1:
            qf = np.array([pc.q[i] for i, _, _ in fx])
            zf = np.array([z for _, z, _ in fx])
            sd = np.array([float(np.sqrt(np.linalg.eigvalsh(R).max())) for _, _, R in fx])
            reg = register_walk(qf, zf, sd, pc.step_q, fl.field, slam.cfg.register)
            rec.update(placed=reg.placed, reason=reg.reason, support=reg.support, margin=float(reg.score - reg.runner_up))
            if np.isfinite(reg.score):
                sel = (wt >= pc.t[0]) & (wt <= pc.t[-1])
                if sel.any():
                    p = pc.q @ reg.T.T + reg.t
                    px = np.c_[np.interp(wt[sel], pc.t, p[:, 0]), np.interp(wt[sel], pc.t, p[:, 1])]
                    e = np.linalg.norm(px - wxy[sel], axis=1)
                    rec.update(n_wp=int(sel.sum()), err_median=float(np.median(e)), err_mean=float(e.mean()))
        own = np.array([r.pos_enu[:2] for r in slam._map.references if r.floor == pc.floor and r.source != str(wid)])
        if len(own):
            from scipy.spatial import cKDTree

            sel = (wt >= pc.t[0]) & (wt <= pc.t[-1])
            d = cKDTree(own).query(wxy[sel][:, :2])[0] if sel.any() else np.zeros(0)
            rec.update(wp_dist_to_map=[float(x) for x in d])  # each waypoint's distance to the nearest map label of other walks, m
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
print(json.dumps(dict(no_gate=no_gate, **summary)))

"""Where do eval crowd's live outliers walk (issue #21, learning)? For each client of a run, how far
its hidden waypoints lie from the nearest reference of the radio map the server served when it
started (same floor), split into the clients whose mean live error exceeds --big (default 25 m) and
the others. Then the corrected side: the clients whose corrected track is more than --big-corrected
(default 20 m) off on average, their share of the summed corrected error and how their walks were
anchored, and the net change the final batches made against the walks as added (incremental).

Usage: python scripts/probe_live_outliers.py OUT_DIR [--big M] [--big-corrected M] [--fixes]
(OUT_DIR: the folder an ``hybridloc eval crowd --out OUT_DIR`` run leaves: server.db and clients.jsonl).
Prints a line per group and per third; the last line is one JSON object."""

import argparse
import atexit
import io
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from sqlalchemy import select
from sqlalchemy.orm import Session

from hybridloc.radio.radiomap import RadioMap
from hybridloc.server import db as m
from hybridloc.server.store import Store

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("out_dir")
ap.add_argument("--big", type=float, default=25.0, help="a client's mean live error above this, m, is an outlier")
ap.add_argument("--big-corrected", type=float, default=20.0, help="a corrected track's mean error above this, m, is badly placed")
ap.add_argument(
    "--fixes",
    action="store_true",
    help="also count each map-anchored corrected walk's fixes from the first survey map (the live SLAM child's) that pass its gate (loads the site's SLAM state: slower)",
)
args = ap.parse_args()
out = Path(args.out_dir)
clients = [json.loads(ln) for ln in (out / "clients.jsonl").read_text().splitlines()]
store = Store(f"sqlite:///{out / 'server.db'}", migrate=False)
atexit.register(store.close)
trees: dict = {}  # (map version, floor) -> KD-tree of its references
survey_version = None  # the first survey map: the one the live SLAM child takes its fixes from
with Session(store.engine) as s:
    for row in s.execute(select(m.RadioMapVersion).order_by(m.RadioMapVersion.version)).scalars():
        if survey_version is None and row.source == "survey":
            survey_version = row.version
        by_floor: dict = {}
        for r in RadioMap.load(io.BytesIO(row.data)).references:
            by_floor.setdefault(r.floor, []).append(r.pos_enu[:2])
        for f, pts in by_floor.items():
            trees[(row.version, f)] = cKDTree(np.asarray(pts, float))

rows = []
for c in clients:
    live = [w["live_m"] for w in c["waypoints"] if w["live_m"] is not None]
    tree = trees.get((c["map_version"], c["floor"]))
    if not live or tree is None:
        continue
    d, _ = tree.query([[w["x"], w["y"]] for w in c["waypoints"]])
    rows.append({"third": c["third"], "big": float(np.mean(live)) > args.big, "dist_m": float(np.median(d)), "live_sum": float(np.sum(live))})

head = {}
for name, sel in (("outliers", lambda r: r["big"]), ("others", lambda r: not r["big"])):
    d = np.array([r["dist_m"] for r in rows if sel(r)])
    if len(d):
        print(
            f"{name}: {len(d)} clients; their waypoints' median distance to the nearest reference of the map served (same floor): "
            f"median {np.median(d):.1f} m (p25 {np.percentile(d, 25):.1f}, p75 {np.percentile(d, 75):.1f}); over 5 m for {np.mean(d > 5):.0%}"
        )
        head[f"{name}_clients"] = len(d)
        head[f"{name}_median_dist_m"] = round(float(np.median(d)), 2)
for third in ("first", "middle", "last"):
    t = [r for r in rows if r["third"] == third]
    big = [r for r in t if r["big"]]
    share = sum(r["live_sum"] for r in big) / max(sum(r["live_sum"] for r in t), 1e-9)
    print(f"{third} third: {len(big)} of {len(t)} clients are outliers, holding {share:.0%} of the third's summed live error")
    head[f"{third}_outliers"] = len(big)
    head[f"{third}_outlier_error_share"] = round(share, 3)

# the corrected side: badly placed walks, and what the final batches changed
anchored: dict[int, str] = {}
with Session(store.engine) as s:
    for row in s.execute(select(m.WalkSlam)).scalars():
        anchored[row.walk_id] = row.anchored
per, delta, n_both = [], 0.0, 0
for c in clients:
    cor = [w["corrected_m"] for w in c["waypoints"] if w["corrected_m"] is not None]
    if cor:
        survey = trees.get((survey_version, c["floor"]))
        d1 = float(np.median(survey.query([[w["x"], w["y"]] for w in c["waypoints"]])[0])) if survey is not None else float("nan")
        per.append((float(np.mean(cor)), len(cor), "/".join(sorted({anchored.get(w, "?") for w in c["walk_ids"]})), d1))
    pairs = [(w["corrected_m"], w["incremental_m"]) for w in c["waypoints"] if w["corrected_m"] is not None and w["incremental_m"] is not None]
    delta += sum(a - b for a, b in pairs)
    n_both += len(pairs)
if per:
    total = sum(p[0] * p[1] for p in per)
    bad = [p for p in per if p[0] > args.big_corrected]
    kinds: dict[str, int] = {}
    for p in bad:
        kinds[p[2]] = kinds.get(p[2], 0) + 1
    rest = [p for p in per if p[0] <= args.big_corrected]
    rest_mean = sum(p[0] * p[1] for p in rest) / max(sum(p[1] for p in rest), 1)
    bad_d1 = float(np.median([p[3] for p in bad])) if bad else float("nan")
    rest_d1 = float(np.median([p[3] for p in rest])) if rest else float("nan")
    print(
        f"corrected: {len(bad)} of {len(per)} clients more than {args.big_corrected:g} m off on average, holding "
        f"{sum(p[0] * p[1] for p in bad) / total:.0%} of the summed corrected error (anchored: {kinds}); the others' mean {rest_mean:.2f} m; "
        f"their waypoints lie a median {bad_d1:.1f} m from the survey map's nearest reference (the others' {rest_d1:.1f} m); "
        f"the final batches changed the error by {delta / max(n_both, 1):+.2f} m per waypoint against the walks as added"
    )
    head.update(
        corrected_bad_clients=len(bad),
        corrected_bad_error_share=round(sum(p[0] * p[1] for p in bad) / total, 3),
        corrected_bad_survey_dist_m=round(bad_d1, 2),
        corrected_rest_survey_dist_m=round(rest_d1, 2),
        corrected_bad_anchored=kinds,
        corrected_rest_mean_m=round(rest_mean, 3),
        final_batches_change_m=round(delta / max(n_both, 1), 3),
    )
if args.fixes:
    # were the badly placed walks anchored by the survey map's fixes, or by EM's crowd-map fixes?
    from hybridloc.server.slam_batch import load_site

    with Session(store.engine) as s:
        site = s.execute(select(m.RadioMapVersion.site_id)).scalars().first()
        survey = s.execute(select(m.RadioMapVersion).where(m.RadioMapVersion.version == survey_version)).scalars().first()
    slam = load_site(store, site)
    slam.set_map(RadioMap.load(io.BytesIO(survey.data)))
    counts: dict[str, list[int]] = {"bad": [], "good": []}
    for c in clients:
        cor = [w["corrected_m"] for w in c["waypoints"] if w["corrected_m"] is not None]
        if not cor or not c["walk_ids"]:
            continue
        wid = c["walk_ids"][0]
        if anchored.get(wid) != "map" or wid not in slam.walks:
            continue
        n_fix = sum(len(v) for v in slam._map_fixes(slam._walk_pieces(slam.walks[wid])).values())
        counts["bad" if np.mean(cor) > args.big_corrected else "good"].append(n_fix)
    for name, v in counts.items():
        if v:
            a = np.asarray(v)
            print(
                f"map-anchored, {name}: {len(a)} walks; survey-map fixes passing the gate: median {np.median(a):.0f}, fewer than 3 for {np.mean(a < 3):.0%}"
            )
            head[f"{name}_survey_fixes_median"] = float(np.median(a))
            head[f"{name}_few_survey_fixes_share"] = round(float(np.mean(a < 3)), 3)
print(json.dumps(head))

"""Where do eval crowd's live outliers walk (issue #21, learning)? For each client of a run, how far
its hidden waypoints lie from the nearest reference of the radio map the server served when it
started (same floor), split into the clients whose mean live error exceeds --big (default 25 m) and
the others.

Usage: python scripts/probe_live_outliers.py OUT_DIR [--big M]
(OUT_DIR: the folder an ``hybridloc eval crowd --out OUT_DIR`` run leaves: server.db and clients.jsonl).
Prints a line per group and per third; the last line is one JSON object."""

import argparse
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
args = ap.parse_args()
out = Path(args.out_dir)
clients = [json.loads(ln) for ln in (out / "clients.jsonl").read_text().splitlines()]
store = Store(f"sqlite:///{out / 'server.db'}", migrate=False)
trees: dict = {}  # (map version, floor) -> KD-tree of its references
with Session(store.engine) as s:
    for row in s.execute(select(m.RadioMapVersion)).scalars():
        by_floor: dict = {}
        for r in RadioMap.load(io.BytesIO(row.data)).references:
            by_floor.setdefault(r.floor, []).append(r.pos_enu[:2])
        for f, pts in by_floor.items():
            trees[(row.version, f)] = cKDTree(np.asarray(pts, float))
store.close()

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
print(json.dumps(head))

"""Is a crowd walk on the floor it names (issue #21, coverage)? The truth is the recording's floor folder.

Usage: python scripts/probe_walk_floors.py SERVER_DB SITE_DIR [--survey-fraction F] [--seed S] [--resolve OUT_DB]
(SERVER_DB: the server.db an ``hybridloc eval crowd --out DIR`` run leaves, with that run's F and S).

A phone client names no floor itself: its walk names the floors of the server's fixes, in order of
first appearance, and a walk with no floor change between its steps is held, whole, on the first
(``walkgraph.walk_pieces``). An Indoor Location Competition trace never leaves its floor, so the
recording's folder is the walk's true floor. For every unmarked walk this prints which floor each
no-truth rule would give it, and how often that is the true one:

* ``named``: the first floor its fixes named (what the server holds it on);
* ``fix majority``: the floor most of its fixes named;
* ``strongest AP``: each scan votes the floor where the survey heard its 5 strongest known transmitters
  loudest; the walk takes the majority;
* ``vote (survey map)`` / ``vote (newest map)``: ``CrowdSlam.vote_floor`` (``SlamConfig.floor_vote``)
  against the survey map and against the newest stored map less the labels of a fifth of the walks,
  the walk's among them (a smaller map than the server votes on); silent
  ("none") without a clear majority; ``vote else named``: the vote where it speaks, else the floor
  named (what ``floor_vote`` does).

Site1, F = 0.1, seed 0 (the e16a292 run): named 75.3 % of the 275 walks (75.9 % of their scans), fix
majority 75.3 %, strongest AP 79.6 %; label propagation over a site-wide fingerprint-match graph
(scratch, not here) reached 80.0 %, and placing each walk on whichever floor's fixes register it moved
13 walks to the right floor and 23 to a wrong one. The floors of this mall are one atrium apart: a
sparse survey does not tell them apart.

``--resolve OUT_DB`` measures what the wrong floors cost: the database is copied to OUT_DB and every
floor re-solved (``server.slam_batch.run_batch``, the floor vote off) twice, as stored and with each unmarked walk moved to
its recording's floor (an oracle: the truth only measures the limit, never sets anything); coverage and
the corrected mean at the waypoints are printed for both. Site1 (e16a292 run): 69.7 % and 7.10 m as
stored; 78.8 % and 7.00 m on the true floors. Last line: one JSON object of the figures."""

import argparse
import collections
import dataclasses
import io
import json
import shutil
import sqlite3

import numpy as np

from hybridloc.crowd_eval import plan_crowd, track_errors, usable_track
from hybridloc.io.msft import read_ilc_trace
from hybridloc.radio.radiomap import RadioMap
from hybridloc.server.store import Store
from hybridloc.slam import online
from hybridloc.slam.pipeline import SlamConfig
from hybridloc.slam.walkgraph import walk_pieces

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("db")
ap.add_argument("site_dir")
ap.add_argument("--survey-fraction", type=float, default=0.1)
ap.add_argument("--seed", type=int, default=0)
ap.add_argument("--resolve", metavar="OUT_DB", help="copy the database here and re-solve it as stored and on the true floors")
args = ap.parse_args()

plan = plan_crowd(args.site_dir, args.survey_fraction, args.seed)
site = plan.site
truth = {c.device: c.floor for c in plan.clients}
store = Store(f"sqlite:///{args.db}")
versions = {v: data for v, _, data in store.map_versions(site)}
survey_map = RadioMap.load(io.BytesIO(versions[min(versions)]))
newest_map = RadioMap.load(io.BytesIO(versions[max(versions)]))
cfg = SlamConfig(floor_vote=True)

# the floor of each transmitter: where the survey heard it loudest
loudest: dict[str, dict[str, float]] = collections.defaultdict(dict)
for r in survey_map.references:
    for tx, v in r.scan.rssi_dbm.items():
        loudest[tx][r.floor] = max(loudest[tx].get(r.floor, -200.0), v)
tx_floor = {tx: max(d, key=d.get) for tx, d in loudest.items()}


def strongest_ap(walk) -> str | None:
    votes: collections.Counter = collections.Counter()
    for s in walk.scans:
        known = sorted(((v, tx) for tx, v in s.rssi_dbm.items() if tx in tx_floor), reverse=True)[:5]
        if known:
            votes[collections.Counter(tx_floor[tx] for _, tx in known).most_common(1)[0][0]] += 1
    return votes.most_common(1)[0][0] if votes else None


def voter(rmap, leave_out: set[str]) -> online.CrowdSlam:
    sl = online.CrowdSlam(site, None, cfg)
    sl.set_map(dataclasses.replace(rmap, references=[r for r in rmap.references if r.source not in leave_out]))
    return sl


crowd_ids = {str(w.walk_id) for w in store.walks(site) if not w.n_marks}
survey_voter = voter(survey_map, crowd_ids)
# the newest map less the walk's own labels: five folds of the walks, each voted on the map without its fold's
FOLDS = 5
fold_voters = [voter(newest_map, {w for w in crowd_ids if int(w) % FOLDS == k}) for k in range(FOLDS)]
con = sqlite3.connect(args.db)
rules = [
    "named",
    "fix majority",
    "strongest AP",
    "vote (survey map)",
    "vote (newest map)",
    "vote else named (survey map)",
    "vote else named (newest map)",
]
hits = {r: collections.Counter() for r in rules}
n_walks = n_scans = 0
for w in store.walks(site):
    if w.n_marks or w.device not in truth:
        continue
    walk = store.read_walk(w.walk_id)
    pcs = walk_pieces(walk, w.walk_id, cfg.walk, name=str(w.walk_id))
    fix_floors = [
        f
        for (f,) in con.execute(
            "SELECT floor FROM fix WHERE device_id = ? AND t >= ? AND t <= ? AND floor IS NOT NULL", (w.device, w.t_start, w.t_end)
        )
    ]
    got = {
        "named": walk.floors[0] if walk.floors else None,
        "fix majority": collections.Counter(fix_floors).most_common(1)[0][0] if fix_floors else None,
        "strongest AP": strongest_ap(walk),
        "vote (survey map)": survey_voter.vote_floor(pcs[0]) if len(pcs) == 1 else None,
        "vote (newest map)": fold_voters[int(w.walk_id) % FOLDS].vote_floor(pcs[0]) if len(pcs) == 1 else None,
    }
    # SlamConfig.floor_vote as the server applies it: the vote where it speaks, else the floor named
    for m in ("survey map", "newest map"):
        got[f"vote else named ({m})"] = got[f"vote ({m})"] or got["named"]
    n_walks += 1
    n_scans += w.n_scans
    for r, f in got.items():
        key = "none" if f is None else ("right" if f == truth[w.device] else "wrong")
        hits[r][key] += 1
        hits[r][key + " scans"] += w.n_scans
print(f"{n_walks} unmarked walks, {n_scans} scans; the floor each rule gives them against the recording's floor:")
out: dict = {"walks": n_walks, "scans": n_scans}
for r in rules:
    h = hits[r]
    print(
        f"  {r:28s} right {h['right']:4d} ({h['right'] / n_walks:.1%}; scans {h['right scans'] / n_scans:.1%}), wrong {h['wrong']:4d}, none {h['none']:4d}"
    )
    out[r.replace(" ", "_").replace("(", "").replace(")", "") + "_right"] = round(h["right"] / n_walks, 4)


def score(st: Store) -> dict:
    """The server's coverage (``hybridloc status``'s, as eval crowd reports it) and the corrected mean at
    the waypoints (crowd_eval's scoring of the final tracks)."""
    states, tracks = st.slam.walk_states(site), st.slam.tracks(site)
    by_dev: dict = collections.defaultdict(list)
    for w in st.walks(site):
        by_dev[w.device].append(w.walk_id)
    errs = []
    for c in plan.clients:
        usable = [tracks[wid] for wid in by_dev.get(c.device, []) if usable_track(tracks.get(wid), states.get(wid))]
        wps = read_ilc_trace(c.path).waypoints
        if usable and len(wps.t):
            errs.append(track_errors(usable, np.asarray(wps.t, float), np.asarray(wps.pos_enu, float)[:, :2]))
    e = np.concatenate(errs) if errs else np.zeros(0)
    return {"coverage": round(st.slam.summary(site)["coverage"], 4), "corrected_mean_m": round(float(np.nanmean(e)), 3) if len(e) else None}


if args.resolve:
    from hybridloc.server.slam_batch import run_batch
    from hybridloc.slam import pipeline

    # the floors as the walks name them (the vote off, as the e16a292 run held them); the oracle moves them
    vote_default = pipeline.SlamConfig.__init__

    def vote_off(self, *a, **k):
        k.setdefault("floor_vote", False)
        vote_default(self, *a, **k)

    pipeline.SlamConfig.__init__ = vote_off  # type: ignore[method-assign]

    for name, oracle in (("as stored", False), ("true floors", True)):
        shutil.copy(args.db, args.resolve)
        st = Store(f"sqlite:///{args.resolve}")
        original = online.CrowdSlam._walk_pieces

        def on_true_floor(self, walk, track=None, _orig=original):
            pcs = _orig(self, walk, track)
            if len(pcs) == 1 and not walk.marks and walk.device in truth and pcs[0].floor != truth[walk.device]:
                return [dataclasses.replace(pcs[0], floor=truth[walk.device])]
            return pcs

        online.CrowdSlam._walk_pieces = on_true_floor if oracle else original
        try:
            run_batch(st, site)
        finally:
            online.CrowdSlam._walk_pieces = original
        s = score(st)
        print(f"re-solved {name}: coverage {s['coverage']:.1%}, corrected mean {s['corrected_mean_m']} m")
        out["resolve_" + name.replace(" ", "_")] = s
print(json.dumps(out))

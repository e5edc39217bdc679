"""What limits eval crowd's learning figure (issue #21)? Each client of a run replayed offline
(:func:`hybridloc.crowd_eval.replay_offline`: the client's phone PDR and Kalman filter, the server's kNN
answers) against variants of the maps it could have been served, per third of the clients:

- ``served``: the map version the server served it (the check: this is the live run);
- ``survey``: the survey map only (the plain method: no crowd SLAM at all);
- ``oracle``: the served map with every crowd label moved to its walk's true position and floor (the
  hidden waypoints, interpolated in time): a perfect SLAM of the same walks, the ceiling of labelling;
- ``clean10``: the served map without the crowd labels more than 10 m (or on another floor) from the truth;
- ``next``: the next map version (the client's own walk's labels removed): a map one batch fresher;
- ``ended``: the last map version's labels of the survey walks and of the walks that ended (recording
  clock) before the client started - what the server had added by then (eval crowd's pacing) - at their
  final positions: a map refreshed at every added walk (optimistic: final labels, not as added);
- ``fresh``: the served version plus the final labels of the walks that ended before the client started
  and that the version does not hold: the freshness of ``ended`` without its hindsight on the older
  walks (``serve --slam-grow-map`` serves those walks as added, not at their final positions);
- ``fresh-grown``: ``fresh`` with only the walks an ``eval crowd --grow-map`` run served as added
  (``map_grown`` in clients.jsonl): the same walks as the live run's, at their final positions.

Usage: python scripts/probe_learning.py OUT_DIR SITE_DIR [--variants served,survey,oracle,clean10,next,ended,fresh,fresh-grown]
(OUT_DIR: an ``hybridloc eval crowd --out OUT_DIR`` run: server.db and clients.jsonl). A line per
variant; the last line is one JSON object."""

import argparse
import dataclasses
import io
import json
import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from hybridloc import geo
from hybridloc.crowd_eval import plan_crowd, replay_offline, thirds
from hybridloc.io.msft import read_ilc_site
from hybridloc.radio.radiomap import RadioMap
from hybridloc.server.locate_pool import KnnOne, make_locator
from hybridloc.server.store import Store

VARIANTS = ("served", "survey", "oracle", "clean10", "next", "ended", "fresh", "fresh-grown")
_STATE: dict = {}


def _truth(clients) -> dict[str, tuple]:
    """walk id (a crowd label's source) -> (waypoint times, positions, floor)."""
    out = {}
    for c in clients:
        t = np.array([w["t"] for w in c["waypoints"]], float)
        xy = np.array([[w["x"], w["y"]] for w in c["waypoints"]], float)
        for w in c["walk_ids"]:
            out[str(w)] = (t, xy, c["floor"])
    return out


def _map(version: int, variant: str, own: set[str]):
    """The locator of a variant of map ``version`` (the worker keeps the last few)."""
    key = (version, variant, tuple(sorted(own)) if variant in ("next", "ended") else ())
    cache = _STATE.setdefault("locators", {})
    if key in cache:
        return cache[key]
    raw = _STATE.setdefault("maps", {})
    if version not in raw:
        store = Store(_STATE["db"], migrate=False)
        try:
            data = store.map_version(_STATE["site"], version)
        finally:
            store.close()
        if len(raw) >= 2:
            raw.pop(next(iter(raw)))
        raw[version] = data
    if raw[version] is None:
        return None
    rm = RadioMap.load(io.BytesIO(raw[version]))
    truth = _STATE["truth"]
    if variant in ("oracle", "clean10"):
        refs = []
        for r in rm.references:
            if r.source not in truth:  # a survey label
                refs.append(r)
                continue
            t, xy, floor = truth[r.source]
            tt = float(np.clip(r.scan.t, t[0], t[-1]))
            where = np.array([np.interp(tt, t, xy[:, 0]), np.interp(tt, t, xy[:, 1])])
            if variant == "oracle":
                pos = np.array(r.pos_enu, float)
                pos[:2] = where
                refs.append(dataclasses.replace(r, pos_enu=pos, floor=floor))
            elif r.floor == floor and float(np.hypot(*(np.asarray(r.pos_enu, float)[:2] - where))) <= 10.0:
                refs.append(r)
        rm.references = refs
    elif variant == "next":
        rm.references = [r for r in rm.references if r.source not in own]
    elif variant == "ended":  # own: the walks that had ended
        rm.references = [r for r in rm.references if r.source not in truth or r.source in own]
    loc = make_locator(rm, "knn") if rm.references else None
    if len(cache) >= 3:
        cache.pop(next(iter(cache)))
    cache[key] = loc
    return loc


def _fresh(version: int, last: int, ended: set[str]):
    """``fresh``: map ``version`` as served, plus the last version's labels of the walks in ``ended`` that
    it does not hold (at their final positions): what a map grown at every added walk serves, with
    hindsight positions for the walks added since ``version`` only."""
    served = _map(version, "served", set())
    if served is None:
        return None
    held = {r.source for r in served.knn.refs}
    if _STATE.get("last_refs", (None,))[0] != last:
        store = Store(_STATE["db"], migrate=False)
        try:
            data = store.map_version(_STATE["site"], last)
        finally:
            store.close()
        _STATE["last_refs"] = (last, RadioMap.load(io.BytesIO(data)).references if data is not None else [])
    extra = [r for r in _STATE["last_refs"][1] if r.source in ended and r.source not in held]
    key = ("fresh", version, tuple(sorted(r.source for r in extra)))
    cache = _STATE.setdefault("fresh", {})
    if key not in cache:
        if len(cache) >= 3:
            cache.pop(next(iter(cache)))
        cache[key] = KnnOne(served.knn.extended(extra)) if extra else served
    return cache[key]


def _init(db: str, site: str, clients: list, axes: dict) -> None:
    _STATE.update(db=db, site=site, truth=_truth(clients), axes=axes, clients=clients)


def _one(job) -> list:
    c, path, variant, survey_v, last_v = job
    v = c["map_version"]
    if v is None:
        return []
    own = {str(w) for w in c["walk_ids"]}
    if variant == "survey":
        loc = _map(survey_v, "served", own)
    elif variant == "next":
        loc = _map(min(v + 1, last_v), "next", own)
    elif variant in ("ended", "fresh", "fresh-grown"):
        t0 = c["waypoints"][0]["t"]
        mine = [d for d in _STATE["clients"] if d["waypoints"] and d["waypoints"][-1]["t"] < t0]
        if variant == "fresh-grown":  # only the walks a --grow-map run served as added
            mine = [d for d in mine if d.get("map_grown")]
        ended = {str(w) for d in mine for w in d["walk_ids"]}
        loc = _map(last_v, "ended", ended) if variant == "ended" else _fresh(v, last_v, ended)
    else:
        loc = _map(v, variant, own)
    wp = c["waypoints"]
    return replay_offline(path, [w["t"] for w in wp], [[w["x"], w["y"]] for w in wp], _STATE["axes"], [loc])[0].tolist()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir")
    ap.add_argument("site_dir")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--survey-fraction", type=float, default=0.1, help="the run's (to find its recordings)")
    ap.add_argument("--seed", type=int, default=0, help="the run's")
    args = ap.parse_args()
    out = Path(args.out_dir)
    clients = [json.loads(ln) for ln in (out / "clients.jsonl").read_text().splitlines()]
    plan = plan_crowd(args.site_dir, args.survey_fraction, args.seed)
    path_of = {w.path.name: str(w.path) for w in plan.clients}
    db = f"sqlite:///{out / 'server.db'}"
    store = Store(db, migrate=False)
    try:
        versions = [(v, src) for v, src, _ in store.map_versions(plan.site)]
    finally:
        store.close()
    survey_v = next(v for v, src in versions if src == "survey")
    last_v = versions[-1][0]
    axes = geo.corridor_axes(read_ilc_site(args.site_dir))
    cuts = thirds(len(clients))
    head: dict = {"run": str(out)}
    live = [np.array([np.nan if w["live_m"] is None else w["live_m"] for i in part for w in clients[i]["waypoints"]], float) for part in cuts]
    print(
        "live run:", " / ".join(f"{np.nanmean(x):.2f}" for x in live), "m; learning", f"{100 * (1 - np.nanmean(live[2]) / np.nanmean(live[0])):.0f} %"
    )
    with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn"), initializer=_init, initargs=(db, plan.site, clients, axes)) as ex:
        for variant in args.variants.split(","):
            jobs = [(c, path_of[c["recording"]], variant, survey_v, last_v) for c in clients]
            res = list(ex.map(_one, jobs, chunksize=8))
            m = [float(np.nanmean(np.concatenate([np.asarray(res[i], float) for i in part if res[i]]))) for part in cuts]
            gain = 1 - m[2] / m[0]
            print(f"{variant:8s} first {m[0]:.2f} m, middle {m[1]:.2f}, last {m[2]:.2f}: learning {100 * gain:.0f} %")
            head[variant] = {"first_m": round(m[0], 3), "middle_m": round(m[1], 3), "last_m": round(m[2], 3), "learning": round(gain, 4)}
    print(json.dumps(head))


if __name__ == "__main__":
    main()

"""Do eval crowd's live clients suffer from fixes on the wrong floor (issue #21)? Two measurements on
an ``hybridloc eval crowd --out OUT_DIR`` run:

1. the fixes the server sent each client (its database's ``fix`` table), per third: the share naming
   another floor than the client walked, and the mean error of those and of the others against the
   truth (the hidden waypoints, interpolated at the fix's time);
2. every client replayed offline with the map it was served (:func:`hybridloc.crowd_eval.replay_offline`,
   the client's PDR and Kalman filter; ``base`` is the eval's own "replay with the maps served") and
   with a floor-aware client: the filter's floor is the lead of a causal vote over its fixes' floors
   (each fix adding its kNN floor share), and a fix naming another floor is either not fused
   (``reject``) or fused with its covariance multiplied by 4 (``inflate4``); and a client whose fixes
   all come from its true floor's references of the same map (``true-floor``: a perfect floor
   decision, each scan located on that floor only).

Usage: python scripts/probe_live_floor.py OUT_DIR SITE_DIR [--variants base,reject,inflate4,true-floor]
A line per third and per variant; the last line is one JSON object."""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import sqlite3
from multiprocessing import Pool
from pathlib import Path

import numpy as np

VARIANTS = ("base", "reject", "inflate4", "true-floor")
THIRDS = ("first", "middle", "last")


def _floor_aware(variant: str) -> None:
    """Patch the client's Kalman filter (this worker process only) for ``variant``."""
    import hybridloc.fusion.kalman as kalman

    orig = getattr(kalman.LocalFusion, "_probe_orig", kalman.LocalFusion._correct_position)
    kalman.LocalFusion._probe_orig = orig
    if variant == "base":
        kalman.LocalFusion._correct_position = orig
        return

    def correct(self, fix):
        if not self.initialised or fix.floor is None:
            return orig(self, fix)
        votes = self.__dict__.setdefault("_probe_votes", collections.Counter())
        votes[fix.floor] += fix.floor_prob
        self.floor = max(votes, key=votes.get)
        if fix.floor == self.floor:
            return orig(self, fix)
        if variant == "reject":
            self.n_rejected += 1
            return False, self.estimate("fix-other-floor")
        return orig(self, dataclasses.replace(fix, cov=np.asarray(fix.cov, float) * 4.0))

    kalman.LocalFusion._correct_position = correct


def _replay(job):
    variant, client, path, db_url, site, axes = job
    _floor_aware(variant)
    from hybridloc.crowd_eval import _baseline_locator, replay_offline

    wp = client["waypoints"]
    t = np.array([w["t"] for w in wp], float)
    xy = np.array([[w["x"], w["y"]] for w in wp], float)
    if variant == "true-floor":
        loc = _floor_locator(db_url, site, client["map_version"], client["floor"])
        if loc is None:  # the map holds no reference on that floor: the served map, as the client had
            loc = _baseline_locator(db_url, site, client["map_version"], "served")
    else:
        loc = _baseline_locator(db_url, site, client["map_version"], "served")
    err = replay_offline(path, t, xy, axes, [loc])[0]
    return variant, client["third"], err[np.isfinite(err)].tolist()


_FLOOR_LOCATORS: dict = {}


def _floor_locator(db_url: str, site: str, version: int, floor: str):
    """The server's kNN locator over the references of one floor of map ``version`` (None: none there)."""
    key = (version, floor)
    if key not in _FLOOR_LOCATORS:
        import io

        from hybridloc.radio.radiomap import RadioMap
        from hybridloc.server.locate_pool import make_locator
        from hybridloc.server.store import Store

        store = Store(db_url, migrate=False)
        try:
            data = store.map_version(site, version)
        finally:
            store.close()
        rmap = RadioMap.load(io.BytesIO(data)) if data else None
        refs = [r for r in rmap.references if r.floor == floor] if rmap else []
        if len(_FLOOR_LOCATORS) >= 6:
            _FLOOR_LOCATORS.pop(next(iter(_FLOOR_LOCATORS)))
        # the server's locator (make_locator: kNN) on that floor's references alone
        _FLOOR_LOCATORS[key] = make_locator(dataclasses.replace(rmap, references=refs), "knn") if refs else None
    return _FLOOR_LOCATORS[key]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir")
    ap.add_argument("site_dir")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    a = ap.parse_args()
    out, site_dir = Path(a.out_dir), Path(a.site_dir)
    variants = [v for v in a.variants.split(",") if v]
    if bad := [v for v in variants if v not in VARIANTS]:
        ap.error(f"unknown variants {bad} (of {', '.join(VARIANTS)})")
    clients = [json.loads(line) for line in open(out / "clients.jsonl")]
    db = sqlite3.connect(out / "server.db")
    site = db.execute("select id from site").fetchone()[0]
    fixes = collections.defaultdict(list)
    for dev, t, x, y, floor in db.execute("select device_id, t, x, y, floor from fix"):
        fixes[dev].append((t, x, y, floor))
    db.close()
    summary: dict = {}
    for third in THIRDS:
        right, wrong = [], []
        for c in clients:
            if c["third"] != third:
                continue
            wp = c["waypoints"]
            T = np.array([w["t"] for w in wp], float)
            X = np.array([w["x"] for w in wp], float)
            Y = np.array([w["y"] for w in wp], float)
            for t, x, y, floor in fixes.get(c["device"], []):
                if T[0] <= t <= T[-1]:
                    (right if floor == c["floor"] else wrong).append(float(np.hypot(np.interp(t, T, X) - x, np.interp(t, T, Y) - y)))
        n = len(right) + len(wrong)
        share = len(wrong) / n if n else float("nan")
        print(
            f"{third} third: {len(wrong)} of {n} fixes within the walks name another floor ({100 * share:.0f} %); "
            f"their mean error {np.mean(wrong) if wrong else float('nan'):.1f} m, the others' {np.mean(right) if right else float('nan'):.1f} m"
        )
        summary[f"other_floor_share_{third}"] = round(share, 4)
    from hybridloc import geo
    from hybridloc.io.msft import find_ilc_traces, read_ilc_site

    axes = geo.corridor_axes(read_ilc_site(site_dir))
    paths = {p.name: p for p in find_ilc_traces(site_dir)}
    db_url = f"sqlite:///{(out / 'server.db').resolve()}"
    ordered = sorted(clients, key=lambda c: c["map_version"] or 0)  # a worker keeps its last map's locator
    jobs = [(v, c, paths[c["recording"]], db_url, site, axes) for v in variants for c in ordered if c["map_version"] is not None]
    errs: dict = collections.defaultdict(lambda: collections.defaultdict(list))
    with Pool(2, maxtasksperchild=50) as pool:
        for v, third, e in pool.imap_unordered(_replay, jobs, chunksize=4):
            errs[v][third].extend(e)
    for v in variants:
        m = [float(np.mean(errs[v][th])) if errs[v][th] else float("nan") for th in THIRDS]
        every = float(np.mean([x for th in THIRDS for x in errs[v][th]]))
        print(f"replay {v:<9} thirds {m[0]:.2f} / {m[1]:.2f} / {m[2]:.2f} m, learning {100 * (1 - m[2] / m[0]):.0f} %, all clients {every:.2f} m")
        summary[f"replay_{v}_thirds_m"] = [round(x, 3) for x in m]
        summary[f"replay_{v}_mean_m"] = round(every, 3)
    print(json.dumps(summary))


if __name__ == "__main__":
    main()

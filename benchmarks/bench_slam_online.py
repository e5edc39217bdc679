"""Crowd SLAM live (issue #21, hybridloc.slam.online): adding one walk to a floor holding ~100 walks, a
batch re-solve per floor next to run_slam on the same walks, and how far the incremental tracks are
from the batch's.

Data: Indoor Location Competition site1 (``../shared/data/msft-ilc/site1``), every recording of the
chosen floors. Per floor a seeded share (``--survey-fraction``) keeps its waypoints as survey marks;
those walks also label the survey map the server would serve (PDR bridged between marks, source
``survey-<walk id>``); the other walks lose their marks before anything reads them. Then, per floor:

1. **replay**: every walk added one by one in a seeded order (:meth:`CrowdSlam.add_walk`), the survey
   map served; the time of each add, and the walks held when it ran;
2. **batch**: :meth:`CrowdSlam.rebuild_floor` over the held walks (timed), and for the ``--compare``
   floors :func:`run_slam` on the same walks and map (timed: the batch must not cost more);
3. **incremental vs batch**: per walk absolute in both, the median distance between its replayed and
   its batch track (the joint solve and EM against each walk solved alone with the walks before it);
4. on the first floor, **re-add** (``--readd`` seeded walks): the server's steady state - the map served
   is the survey plus the crowd labels of the batch, without the re-added walks' own labels; each walk
   is removed and added again against all the others held at their batch solution (timed; its new
   track against its batch track).

Also printed: the largest corrected step and the share of points > 2 m outside the walkable area of
every walk, the figures the quarantine bounds (``MAX_STEP_M``, ``MAX_OUTSIDE_SHARE``) must clear.

    python -m benchmarks.bench_slam_online [--floors F1 F2 F3] [--compare F1 F2 F3] [--survey-fraction 0.1] [--readd 20] [--seed 0]

The last line is one JSON object (benchmarks.headline).

Measured (2-core machine, seed 0, F = 0.1, 305 walks): add_walk with >= 80 walks held on the floor
median 0.11 s, p95 0.22 s, max 0.39 s; re-added with 104 held: median 0.14 s, p95 0.25 s.
rebuild_floor against run_slam on the same walks: F1 31.9 / 33.8 s, F2 22.6 / 23.1 s, F3 52.6 / 43.1 s
(F3's batch dropped failing walks: one more loop detection and solve, and their incremental re-adds).
Incremental vs batch, walks absolute in both: median 1.0 m, p90 11 m (the joint solve and EM re-place
some walks the replay had put by the survey map alone); re-added vs batch: median 0.64 m. Coverage of
the crowd scans 0.56 after the replay, 0.90 after the batches. Quarantined: 2 of 305 in the replay, 2
in the batches (after re-adding the walks the joint solve could not fit), none among the re-adds.
Held tracks: largest corrected step per walk p95 1.01 m, max 1.55 m (bound 2 m); share of points
> 2 m outside the walkable area p95 0.046, max 0.227 (bound 0.25).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks import headline

SITE = Path(__file__).resolve().parents[2] / "shared" / "data" / "msft-ilc" / "site1"


def _survey_refs(walks):
    from hybridloc.radio.survey import label_scans
    from hybridloc.types import Waypoints

    refs = []
    for w in walks:
        if w.marks:
            wp = Waypoints(np.array([m.t for m in w.marks]), np.array([[m.x, m.y] for m in w.marks]), w.marks[0].floor)
            refs += label_scans([s for s in w.scans if s.technology.value == "wifi"], list(w.steps), wp, w.t_start, source=f"survey-{w.walk_id}")
    return refs


def _distance(a, b) -> float | None:
    """Median distance between two tracks of one walk (the same points), or None unless both are absolute."""
    if a is None or b is None or a.anchored == "relative" or b.anchored == "relative" or len(a) != len(b):
        return None
    return float(np.median(np.linalg.norm(a.pos_enu - b.pos_enu, axis=1)))


def _pct(x, q) -> float:
    return float(np.percentile(x, q)) if len(x) else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench_slam_online", description=__doc__.split("\n\n")[0])
    ap.add_argument("--site", default=str(SITE))
    ap.add_argument("--floors", nargs="+", default=["F1", "F2", "F3"])
    ap.add_argument("--compare", nargs="*", default=["F1", "F2", "F3"], help="floors where run_slam is timed beside rebuild_floor")
    ap.add_argument("--survey-fraction", type=float, default=0.1)
    ap.add_argument("--readd", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    a = ap.parse_args(argv)

    import logging

    from hybridloc.io.msft import read_ilc_site
    from hybridloc.radio.radiomap import BuildParams, build_radio_map
    from hybridloc.slam.floorplan import WalkableField
    from hybridloc.slam.online import CrowdSlam
    from hybridloc.slam.pipeline import run_slam
    from hybridloc.slam.walkgraph import walks_from_files

    logging.getLogger("hybridloc").setLevel(logging.ERROR)
    site = Path(a.site)
    if not site.is_dir():
        print(f"bench_slam_online: {site} is absent (the ILC site1 recordings)", file=sys.stderr)
        return 2
    plan = read_ilc_site(site)
    rng = np.random.default_rng(a.seed)
    t0 = time.monotonic()
    floors: dict[str, list] = {}
    next_id = 1
    for fl in a.floors:
        paths = sorted((site / fl / "path_data_files").glob("*.txt*"))
        loaded = walks_from_files(paths, marks=True, workers=a.workers)
        keep = set(rng.choice(len(loaded), size=round(a.survey_fraction * len(loaded)), replace=False).tolist())
        floors[fl] = [dataclasses.replace(w, walk_id=next_id + i, marks=w.marks if i in keep else ()) for i, (w, _) in enumerate(loaded)]
        next_id += len(loaded) + 1000
    print(f"read {sum(len(v) for v in floors.values())} walks of {', '.join(a.floors)} in {time.monotonic() - t0:.0f} s", flush=True)
    survey = _survey_refs([w for ws in floors.values() for w in ws])
    smap = build_radio_map(survey, site="site1", plan=plan)
    cs = CrowdSlam("site1", plan)
    cs.set_map(smap)
    adds, inc, figures = [], {}, {}
    q_inc = 0
    for fl, ws in floors.items():
        for k in rng.permutation(len(ws)):
            n_held = len(cs._floors[fl].held) if fl in cs._floors else 0
            o = cs.add_walk(ws[k])
            adds.append((fl, n_held, o.seconds))
            q_inc += bool(o.quarantined)
            inc[o.walk_id] = o.track if not o.quarantined else None
        sec = np.array([s for f, n, s in adds if f == fl])
        print(
            f"floor {fl}: {len(ws)} walks added one by one: median {np.median(sec):.3f} s, p95 {_pct(sec, 95):.3f} s, max {sec.max():.3f} s",
            flush=True,
        )
    cov_inc = cs.coverage()
    batch_s, run_s, diffs, q_bat = {}, {}, [], 0
    for fl, ws in floors.items():
        t = time.monotonic()
        out = cs.rebuild_floor(fl)
        batch_s[fl] = time.monotonic() - t
        q_bat += out.stats["quarantined"]
        d = [x for wid, o in out.walks.items() if (x := _distance(inc.get(wid), o.track if not o.quarantined else None)) is not None]
        diffs += d
        print(
            f"floor {fl}: rebuild_floor {batch_s[fl]:.1f} s ({out.stats['em_rounds']} EM rounds, anchored {out.stats['anchored']}, "
            f"{out.stats['quarantined']} quarantined); incremental vs batch, {len(d)} walks absolute in both: median {np.median(d):.2f} m, p90 {_pct(d, 90):.2f} m",
            flush=True,
        )
        if fl in a.compare:
            held = [w for w in ws if w.walk_id in out.walks]  # what the batch solved
            t = time.monotonic()
            run_slam(held, plan, smap)
            run_s[fl] = time.monotonic() - t
            print(f"floor {fl}: run_slam on the same {len(held)} walks {run_s[fl]:.1f} s", flush=True)
    cov_bat = cs.coverage()
    # the quarantine bounds against every real track
    steps, outside = [], []
    fields = {fl: WalkableField.from_floor(plan.floor(fl)) for fl in floors}
    for tr in cs.tracks.values():
        if tr is None:
            continue
        st = np.array(tr.kind) == "step"
        if st.sum() > 1:
            steps.append(float(np.linalg.norm(np.diff(tr.pos_enu[st], axis=0), axis=1).max()))
        if tr.anchored != "relative":
            dd, _ = fields[tr.floor[0]](tr.pos_enu)
            outside.append(float((dd > 2.0).mean()))
    print(
        f"held tracks: largest corrected step per walk p95 {_pct(steps, 95):.2f} m, max {max(steps):.2f} m; "
        f"share of points > 2 m outside the walkable area p95 {_pct(outside, 95):.3f}, max {max(outside):.3f}",
        flush=True,
    )
    # re-add at steady state on the first floor
    fl = a.floors[0]
    held_ids = sorted(w.walk_id for w in floors[fl] if w.walk_id in cs.walks and not w.marks)
    readd = sorted(rng.choice(held_ids, size=min(a.readd, len(held_ids)), replace=False).tolist())
    refs = survey + [ls for ls in cs.labels() if int(ls.source) not in set(readd)]
    cs.set_map(build_radio_map(refs, site="site1", plan=plan, params=BuildParams(label_weight=True)))
    re_s, re_d, re_held, q_re = [], [], [], 0
    for wid in readd:
        before = cs.tracks[wid]
        walk = cs.walks[wid]
        cs.remove_walk(wid)
        re_held.append(len(cs._floors[fl].held))
        o = cs.add_walk(walk)
        re_s.append(o.seconds)
        q_re += bool(o.quarantined)
        if (x := _distance(before, o.track if not o.quarantined else None)) is not None:
            re_d.append(x)
    print(
        f"floor {fl}: {len(readd)} walks re-added with {int(np.median(re_held))} held: median {np.median(re_s):.3f} s, p95 {_pct(re_s, 95):.3f} s; "
        f"against their batch track ({len(re_d)} absolute in both): median {np.median(re_d) if re_d else float('nan'):.2f} m",
        flush=True,
    )
    late = [s for _, n, s in adds if n >= 80]
    figures = {
        "add_walk_median_s": float(np.median(late)) if late else float("nan"),
        "add_walk_p95_s": _pct(late, 95),
        "add_walk_max_s": max(late) if late else float("nan"),
        "add_walk_held_min": 80,
        "readd_median_s": float(np.median(re_s)),
        "readd_p95_s": _pct(re_s, 95),
        "readd_held_walks": int(np.median(re_held)),
        **{f"rebuild_floor_s_{f}": v for f, v in batch_s.items()},
        **{f"run_slam_s_{f}": v for f, v in run_s.items()},
        "inc_vs_batch_median_m": float(np.median(diffs)) if diffs else float("nan"),
        "inc_vs_batch_p90_m": _pct(diffs, 90),
        "readd_vs_batch_median_m": float(np.median(re_d)) if re_d else float("nan"),
        "coverage_incremental": cov_inc,
        "coverage_batch": cov_bat,
        "quarantined_incremental": q_inc,
        "quarantined_batch": q_bat,
        "quarantined_readd": q_re,
        "walks": sum(len(v) for v in floors.values()),
        "seed": a.seed,
        "seconds": time.monotonic() - t0,
    }
    headline(figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""``hybridloc eval slam``: crowd SLAM on Indoor Location Competition recordings, scored at waypoints.

Protocol (issue #20, slam.md 5). Per floor, the walks sorted by file name: even positions are the
crowd, odd positions the test walks. A seeded fraction F of the crowd keep their survey marks; the
rest lose them before anything reads them (:func:`~hybridloc.slam.walkgraph.walk_from_ilc` with
``marks=False``: their waypoints are returned to this module only, which uses them to score). No
waypoint reaches the graph, a step-length model, the similarity model or any setting. A seeded share
P of the unmarked crowd walks is used (the data-amount curve).

Figures, per floor and overall:

* corrected crowd walks (those that lost their marks) at their hidden waypoints: mean, median, p90;
  coverage = the share of their scans that got an absolute label;
* loops: precision (both ends within 5 m by waypoint interpolation) of the accepted loops, and
  accepted loops per WiFi scan;
* the test walks as live clients (phone PDR + the server's kNN fixes through the Kalman filter, cold,
  causal: a fix is used from the first step after its scan) with three maps: the F survey walks only,
  survey plus corrected crowd, and every crowd walk labelled by its true waypoints (the upper anchor);
* wall time and peak memory.
"""

from __future__ import annotations

import math
import resource
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import MissingData
from ..metrics import causal_errors, summarize_errors
from ..radio.survey import LabelledScan, label_scans
from ..types import Waypoints
from .pipeline import RELATIVE, SlamConfig, SlamResult, mapped_distance_gate, run_slam

#: test clients take every fix (as the server answers today); the coverage-gated variant is printed beside
GATED = False
#: a loop is true when its two places are within this distance (issue #20)
LOOP_TRUE_M = 5.0


@dataclass
class _Walk:
    path: Path
    floor: str
    role: str  # "survey" (keeps marks), "crowd" (marks stripped), "test"
    walk: object
    wp: Waypoints


def _truth_at(wp: Waypoints, t: np.ndarray) -> np.ndarray:
    """Waypoint interpolation (the data set's truth; metre-level itself), holding at the ends."""
    return np.column_stack([np.interp(t, wp.t, wp.pos_enu[:, 0]), np.interp(t, wp.t, wp.pos_enu[:, 1])])


def _waypoints_of_marks(walk) -> Waypoints:
    m = walk.marks
    return Waypoints(np.array([x.t for x in m]), np.array([[x.x, x.y] for x in m]).reshape(-1, 2), m[0].floor if m else None)


def _survey_labels(w: _Walk, wp: Waypoints) -> list[LabelledScan]:
    if len(wp.t) < 2 or len(w.walk.steps) < 2:
        return []
    wifi = [s for s in w.walk.scans if s.technology.value == "wifi"]
    return label_scans(wifi, list(w.walk.steps), wp, float(w.walk.t_start), source=w.path.name)


def _fused(test: list[_Walk], refs: list[LabelledScan], axes: dict, k: int = 5, max_age_s: float = 8.0, gated: bool = GATED) -> np.ndarray:
    """Errors at waypoints (after the first) of the test walks as live clients of a map of ``refs``."""
    from ..fusion import LocalFusion, run_fusion
    from ..radio.locate import KnnLocator

    if not refs:
        return np.concatenate([np.full(max(len(w.wp.t) - 1, 0), np.nan) for w in test]) if test else np.zeros(0)
    # memo: each walk's scans are searched once for its fixes and its gate (the fixes without regions)
    loc = KnnLocator(refs, k=k, max_age_s=max_age_s, memo=True)
    gate = mapped_distance_gate(refs, SlamConfig()) if gated else math.inf
    out = []
    for w in test:
        steps = list(w.walk.steps)
        scans = [s for s in w.walk.scans if s.technology.value == "wifi"]
        answers = loc.locate_many(scans, regions=False) if scans else []
        near = loc.nearest(scans)[0][:, 0] <= gate if scans and math.isfinite(gate) else np.ones(len(answers), bool)
        fixes = [r.fix for r, ok in zip(answers, near) if r.fix is not None and ok]
        est = run_fusion(LocalFusion(corridor_axes=axes), steps, fixes) if steps else []
        poses = [(e.t, float(e.pos[0]), float(e.pos[1]), e.floor) for e in est]
        out.append(causal_errors(poses, w.wp.t, w.wp.pos_enu))
    return np.concatenate(out) if out else np.zeros(0)


def _summ(e: np.ndarray) -> dict:
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"n": 0, "mean": float("nan"), "median": float("nan"), "p75": float("nan"), "p90": float("nan")}
    return {
        "n": int(e.size),
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "p75": float(np.percentile(e, 75)),
        "p90": float(np.percentile(e, 90)),
    }


def _peak_mb() -> float:
    self_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    child_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return max(self_kb, child_kb) / 1024.0


def _load_walks(paths: list[Path], marks: list[bool], workers: int, progress) -> list:
    from .walkgraph import walks_from_files

    return walks_from_files(paths, marks=marks, workers=workers, progress=progress)


def run_slam_eval(
    site_dir: str,
    survey_fraction: float = 0.1,
    seed: int = 0,
    data_fraction: float = 1.0,
    workers: int = 2,
    config: SlamConfig | None = None,
    out=None,
) -> dict:
    from .. import geo
    from ..io.msft import find_ilc_traces, read_ilc_site, read_ilc_waypoints
    from ..progress import Progress

    out = out if out is not None else sys.stdout  # looked up per call (a captured stdout may be replaced)
    if not 0.0 <= survey_fraction <= 1.0 or not 0.0 < data_fraction <= 1.0:
        raise ValueError("--survey-fraction must be in [0, 1] and --data-fraction in (0, 1]")
    t0 = time.monotonic()
    site = Path(site_dir)
    if not site.is_dir():
        raise MissingData(f"{site}: {'not a folder' if site.exists() else 'no such folder'} (an Indoor Location Competition site folder)")
    paths = find_ilc_traces(site)
    if len(paths) < 4:
        raise MissingData(f"too few Indoor Location Competition recordings under {site_dir}")
    plan = read_ilc_site(site)
    # two generators: which walks keep their marks does not depend on how many crowd walks are used,
    # so the data-amount curve (P) varies only the crowd
    rng_survey = np.random.default_rng(seed)
    rng_data = np.random.default_rng([seed, 1])
    # roles per floor: the floor of each file is its folder's (no file is read for this)
    by_floor: dict[str, list[Path]] = {}
    for p in sorted(paths, key=lambda p: p.name):
        by_floor.setdefault(p.parent.parent.name, []).append(p)
    roles: dict[Path, str] = {}
    for _fl, ps in sorted(by_floor.items()):
        crowd = ps[0::2]
        for p in ps[1::2]:
            roles[p] = "test"
        n_keep = int(round(survey_fraction * len(crowd)))
        keep = set(rng_survey.choice(len(crowd), size=n_keep, replace=False).tolist()) if n_keep else set()
        rest = [i for i in range(len(crowd)) if i not in keep]
        n_use = int(math.ceil(data_fraction * len(rest)))
        use = set(rng_data.choice(rest, size=n_use, replace=False).tolist()) if rest and n_use else set()
        for i, p in enumerate(crowd):
            if i in keep:
                roles[p] = "survey"
            elif i in use:
                roles[p] = "crowd"
    order = [p for p in sorted(roles, key=lambda p: p.name)]
    bar = Progress("[eval slam] reading walks (phone PDR)", len(order))
    loaded = _load_walks(order, [roles[p] == "survey" for p in order], workers, lambda i, n: bar.update(i))
    bar.close()
    W = []
    for p, (walk, wp) in zip(order, loaded):
        if roles[p] != "survey":
            assert not walk.marks  # stripped before anything reads them
        W.append(_Walk(p, walk.floors[0] if walk.floors else "", roles[p], walk, wp if roles[p] != "survey" else read_ilc_waypoints(p)))
    crowd_side = [w for w in W if w.role in ("survey", "crowd")]
    tests = [w for w in W if w.role == "test"]
    t_read = time.monotonic() - t0
    # the survey-only map: the kept marks label their walks' scans (passive survey)
    survey_refs = [ls for w in crowd_side if w.role == "survey" for ls in _survey_labels(w, _waypoints_of_marks(w.walk))]
    survey_map = None
    if survey_refs:
        from ..radio.radiomap import build_radio_map

        survey_map = build_radio_map(survey_refs, site=W[0].walk.site, plan=plan)
    t1 = time.monotonic()
    res: SlamResult = run_slam([w.walk for w in crowd_side], plan, survey_map, config, names=[w.path.name.split(".")[0] for w in crowd_side])
    t_slam = time.monotonic() - t1
    # ---------------------------------------------------------------------------- crowd accuracy
    per_floor: dict[str, dict] = {}
    crowd_err: dict[str, list] = {}
    cover: dict[str, list[int]] = {}
    for fname, fs in res.floors.items():
        for k, pc in enumerate(fs.pieces):
            w = crowd_side[pc.walk]
            if w.role != "crowd":
                continue
            n_sc = len(pc.scans)
            c = cover.setdefault(fname, [0, 0])
            c[1] += n_sc
            if fs.status[k] == RELATIVE:
                continue
            c[0] += n_sc
            wt = w.wp.t[(w.wp.t >= pc.t[0]) & (w.wp.t <= pc.t[-1])]
            if len(wt):
                e = np.linalg.norm(fs.track(k, wt) - _truth_at(w.wp, wt), axis=1)
                crowd_err.setdefault(fname, []).extend(e.tolist())
    # ---------------------------------------------------------------------------- loops
    name_to = {w.path.name.split(".")[0]: w for w in crowd_side}
    loop_ok: dict[str, list[bool]] = {}
    loop_kind: dict[str, list[str]] = {}
    n_wifi: dict[str, int] = {}
    for fname, fs in res.floors.items():
        n_wifi[fname] = sum(1 for pc in fs.pieces for i in np.flatnonzero(pc.scan >= 0) if pc.scans[int(pc.scan[i])].technology.value == "wifi")
        for lp in fs.loops:
            if not lp.accepted:
                continue
            a, b = name_to[lp.walk_a], name_to[lp.walk_b]
            d = float(np.linalg.norm(_truth_at(a.wp, np.array([lp.t_a]))[0] - _truth_at(b.wp, np.array([lp.t_b]))[0]))
            loop_ok.setdefault(fname, []).append(d <= LOOP_TRUE_M)
            loop_kind.setdefault(fname, []).append(lp.kind)
    # ---------------------------------------------------------------------------- fused test clients
    axes = geo.corridor_axes(plan)
    crowd_refs = [ls for ls in res.labels if ls.scan.technology.value == "wifi"]
    all_marks_refs = [ls for w in crowd_side for ls in _survey_labels(w, w.wp)]
    t2 = time.monotonic()
    maps = {"survey_only": survey_refs, "crowd": crowd_refs, "all_marks": all_marks_refs}
    fused = {k: _fused(tests, v, axes) for k, v in maps.items()}
    # the same clients when the locator answers only scans the map covers (mapped_distance_gate):
    # a partial map then leaves clients without fixes instead of sending them to its nearest place
    fused_gated = {k: _fused(tests, v, axes, gated=True) for k, v in maps.items()}
    test_floor = np.concatenate([np.full(max(len(w.wp.t) - 1, 0), w.floor, dtype=object) for w in tests]) if tests else np.zeros(0, object)
    t_fused = time.monotonic() - t2
    seconds = time.monotonic() - t0
    # ---------------------------------------------------------------------------- report
    n_roles = {r: sum(w.role == r for w in W) for r in ("survey", "crowd", "test")}
    print(
        f"crowd SLAM on {site}: {n_roles['survey']} survey walks (F = {survey_fraction:g}, seed {seed}), {n_roles['crowd']} crowd walks "
        f"without marks (P = {data_fraction:g}), {n_roles['test']} test walks; read {t_read:.0f} s, SLAM {t_slam:.0f} s, clients {t_fused:.0f} s",
        file=out,
    )
    floors = sorted(set(res.floors) | set(test_floor.tolist()))
    for fname in [*floors, "all"]:
        if fname == "all":
            ce = _summ(np.concatenate([np.asarray(v, float) for v in crowd_err.values()]) if crowd_err else np.zeros(0))
            cv = [sum(c[0] for c in cover.values()), sum(c[1] for c in cover.values())]
            lk = [x for v in loop_ok.values() for x in v]
            kinds = [x for v in loop_kind.values() for x in v]
            nw = sum(n_wifi.values())
            sel = np.ones(len(test_floor), bool)
        else:
            ce = _summ(np.asarray(crowd_err.get(fname, []), float))
            cv = cover.get(fname, [0, 0])
            lk = loop_ok.get(fname, [])
            kinds = loop_kind.get(fname, [])
            nw = n_wifi.get(fname, 0)
            sel = test_floor == fname
        cov_share = cv[0] / cv[1] if cv[1] else float("nan")
        prec = float(np.mean(lk)) if lk else float("nan")
        fs = {k: _summ(v[sel]) for k, v in fused.items()}
        per_floor[fname] = {
            "crowd": ce,
            "coverage": cov_share,
            "loop_precision_5m": prec,
            "loops_accepted": len(lk),
            "loops_per_scan": len(lk) / nw if nw else float("nan"),
            "fused": fs,
        }
        print(f"  {'floor ' + fname if fname != 'all' else 'overall':<9}", file=out)
        print(
            f"    corrected crowd walks at hidden waypoints: mean {ce['mean']:.2f} m, median {ce['median']:.2f}, p90 {ce['p90']:.2f} (n={ce['n']}); "
            f"coverage {100 * cov_share:.1f} % of crowd scans labelled",
            file=out,
        )
        by_kind = ", ".join(
            f"{kd} {sum(1 for x in kinds if x == kd)} at {np.mean([ok for ok, x in zip(lk, kinds) if x == kd]):.3f}" for kd in sorted(set(kinds))
        )
        print(
            f"    loops: {len(lk)} accepted ({len(lk) / nw if nw else float('nan'):.3f} per WiFi scan), precision at 5 m {prec:.3f} ({by_kind})",
            file=out,
        )
        for k, label in (("survey_only", "survey only"), ("crowd", "survey + crowd"), ("all_marks", "all marks (upper anchor)")):
            s = fs[k]
            print(
                f"    test clients, fused, map {label:<26}: mean {s['mean']:.2f} m, median {s['median']:.2f}, p75 {s['p75']:.2f} (n={s['n']})",
                file=out,
            )
        gs = {k: v[sel] for k, v in fused_gated.items()}
        print(
            "    the same, fixes only where the map covers the scan: "
            + ", ".join(f"{k} {_summ(v)['mean']:.2f} m on {100 * np.isfinite(v).mean() if v.size else 0:.0f} % of waypoints" for k, v in gs.items()),
            file=out,
        )
        a, c, m = fs["survey_only"]["mean"], fs["crowd"]["mean"], fs["all_marks"]["mean"]
        print(f"    ratios: crowd / all marks {c / m:.2f} (goal <= 1.15), crowd / survey only {c / a:.2f} (goal <= 0.7)", file=out)
    peak = _peak_mb()
    print(f"  wall time {seconds:.0f} s, peak memory {peak:.0f} MB", file=out)
    allf = per_floor["all"]
    return {
        "crowd_median_m": allf["crowd"]["median"],
        "crowd_mean_m": allf["crowd"]["mean"],
        "crowd_p90_m": allf["crowd"]["p90"],
        "coverage": allf["coverage"],
        "loop_precision_5m": allf["loop_precision_5m"],
        "loops_per_scan": allf["loops_per_scan"],
        "fused_mean_survey_only_m": allf["fused"]["survey_only"]["mean"],
        "fused_mean_crowd_m": allf["fused"]["crowd"]["mean"],
        "fused_mean_all_marks_m": allf["fused"]["all_marks"]["mean"],
        "fused_median_crowd_m": allf["fused"]["crowd"]["median"],
        "fused_p75_crowd_m": allf["fused"]["crowd"]["p75"],
        "survey_fraction": survey_fraction,
        "data_fraction": data_fraction,
        "seed": seed,
        "walks_survey": n_roles["survey"],
        "walks_crowd": n_roles["crowd"],
        "walks_test": n_roles["test"],
        "seconds": seconds,
        "peak_memory_mb": peak,
    }


__all__ = ["LOOP_TRUE_M", "run_slam_eval", "summarize_errors"]

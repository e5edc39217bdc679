"""Loop signal of the crowd-SLAM front end on ILC site1: which similarity measure, chosen without truth.

For each floor and each similarity measure (``hybridloc.slam.frontend.MEASURES``, with and without
the per-walk RSS offset removal) it runs the front end on every walk of the floor (fresh readings,
inverted index, mutual top-k, the within-walk distance model, PCM) and prints:

* **no-truth criterion** (what the choice uses): at matched candidate rates (the similarity
  threshold ``s_r`` above which the mutual top-k candidates number ``r`` per scan, r = 0.05, 0.1, 0.2),
  the mixture of eq. 1 fitted by EM on the *within-walk* pairs with S >= s_r: inlier share ``pi``,
  inlier spread ``sigma`` and the probability it implies of d < 5 m,
  ``P_model = pi (1 - exp(-25 / (2 sigma^2))) + (1 - pi) G(5 m)``. The sharper measure has the larger
  ``P_model`` at the same rate.
* **truth figures** (printed for the report; never used to choose or fit anything): P(d < 5 m) of the
  candidates at each rate and of the loops PCM accepted, with d the distance between the two scans'
  waypoint-interpolated positions; accepted loops per scan; the share of accepted loops within the
  99 % radius ``3.03 sigma_in`` of their own model; and the error of each linked walk pair's clique-mean
  translation (``pair_translations``) against the translation the waypoints imply over the clique's scans.

The choice: the highest no-truth score; the per-walk offset removal only if it adds >= 0.01 to it.
Figures and the choice are written in the docstring of :mod:`hybridloc.slam.frontend`.

Positions in each walk's own frame: phone PDR (``PhonePdr(rate, make_model("height"), heading0=None)``,
absolute heading) and :class:`hybridloc.pdr.deadreckoning.DeadReckoning` (positions and covariance) at
each scan's time (median last-seen time of its fresh readings). g(d) of eq. 1 from points on a 1 m grid
of the floor outline minus its shops (slam.md 3.1: 97.7-99.7 % of waypoints lie there).

    python -m benchmarks.bench_loop_signal [--site DIR] [--cache FILE.pkl]

Last line: one JSON object (per floor and measure: the figures above; and the chosen measure).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import time
from pathlib import Path

import numpy as np
import shapely

from hybridloc.io.msft import find_ilc_traces, read_ilc_floor, read_ilc_trace
from hybridloc.pdr.deadreckoning import DeadReckoning
from hybridloc.pdr.phone import PhonePdr
from hybridloc.pdr.steplength import make_model
from hybridloc.slam.frontend import (
    CHI2_2_99,
    MEASURES,
    FrontendConfig,
    LoopDetector,
    WalkScans,
    fit_mixture,
    index_pairs,
    pair_similarity,
    pair_translations,
    scan_time,
    top_k,
)

SITE = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "msft-ilc" / "site1"
RATES = (0.05, 0.1, 0.2)
#: The per-walk offset removal is chosen only if it raises the no-truth score by at least this much.
OFFSET_MARGIN = 0.01


def load_site(site: Path, cache: str | None) -> list[dict]:
    """Per trace: floor, WiFi scans, PDR steps and waypoints (waypoints only for scoring)."""
    if cache and os.path.exists(cache):
        with open(cache, "rb") as f:
            return pickle.load(f)
    out = []
    for p in find_ilc_traces(site):
        tr = read_ilc_trace(p)
        if tr.imu is None:
            continue
        steps = PhonePdr(tr.imu.rate_hz, make_model("height"), heading0=None).process(tr.imu)
        out.append(
            dict(
                path=str(p),
                floor=p.parent.parent.name,
                scans=list(tr.wifi_scans),
                steps=steps,
                wp_t=np.asarray(tr.waypoints.t),
                wp_p=np.asarray(tr.waypoints.pos_enu),
            )
        )
    if cache:
        with open(cache, "wb") as f:
            pickle.dump(out, f)
    return out


def walkable_points(site: Path, floor: str, grid: float = 1.0) -> np.ndarray:
    fl, _ = read_ilc_floor(site / floor)
    area = fl.outline
    shops = [g for _, g in fl.rooms]
    if shops:
        area = shapely.difference(area, shapely.union_all(shops))
    x0, y0, x1, y1 = area.bounds
    xx, yy = np.meshgrid(np.arange(x0, x1, grid), np.arange(y0, y1, grid))
    inside = shapely.contains_xy(area, xx.ravel(), yy.ravel())
    return np.column_stack([xx.ravel()[inside], yy.ravel()[inside]])


def build_walks(traces: list[dict], max_age_s: float) -> tuple[list[WalkScans], dict[int, np.ndarray]]:
    """WalkScans per trace with at least 2 scans and steps, and the truth position of each scan (scoring only)."""
    walks, truth, node = [], {}, 0
    for w, tr in enumerate(traces):
        scans, steps = tr["scans"], tr["steps"]
        if len(scans) < 2 or len(steps) < 2 or len(tr["wp_t"]) < 2:
            continue
        t = np.array([scan_time(s, max_age_s) for s in scans])
        dr = DeadReckoning.from_steps(steps, t0=min(float(t.min()), steps[0].t) - 1e-3)
        q, C = dr.position_at(t), dr.covariance_at(t)
        walks.append(WalkScans(w, tr["floor"], np.arange(node, node + len(scans)), t, q, C, scans))
        node += len(scans)
        truth[w] = np.column_stack([np.interp(t, tr["wp_t"], tr["wp_p"][:, 0]), np.interp(t, tr["wp_t"], tr["wp_p"][:, 1])])
    return walks, truth


def p_model_5m(pi: float, sigma: float, G5: float) -> float:
    return pi * (1.0 - math.exp(-25.0 / (2 * sigma**2))) + (1.0 - pi) * G5


def evaluate(walks: list[WalkScans], truth: dict[int, np.ndarray], cfg: FrontendConfig, g_points: np.ndarray) -> dict:
    det = LoopDetector(cfg, walkable={walks[0].floor: g_points})
    t0 = time.perf_counter()
    det.fit(walks)
    loops = det.detect(walks)
    seconds = time.perf_counter() - t0
    n_scans = sum(len(w.scans) for w in walks)
    g = det.density(walks[0].floor)
    G5 = float(np.mean(g(np.linspace(0, 5, 501))) * 5.0)  # integral of g over [0, 5 m]
    # no-truth criterion: within-walk mixture above the threshold giving r mutual candidates per scan
    S_in, d_in, g_in, v_in = det.within_walk_data(walks)
    V = det._floor_vectors(walks, walks[0].floor)
    I, J = index_pairs(V, cfg)
    S = pair_similarity(V.R, I, J, cfg.measure)
    sel = top_k(I, J, S, V.walk_row, cfg.k, cfg.one_per_walk)
    directed = dict(zip(zip(I[sel].tolist(), J[sel].tolist()), S[sel].tolist()))
    mutual = sorted({(min(i, j), max(i, j)): s for (i, j), s in directed.items() if (j, i) in directed}.items(), key=lambda kv: -kv[1])
    msim = np.array([s for _, s in mutual])

    def true_d(wa, ia, wb, jb):
        return float(np.linalg.norm(truth[walks[wa].walk][ia] - truth[walks[wb].walk][jb]))

    rates = {}
    for r in RATES:
        m = int(round(r * n_scans))
        if m < 1 or len(msim) < m:
            continue
        s_r = float(msim[m - 1])
        keep = S_in >= s_r
        if keep.sum() < 20:
            rates[str(r)] = dict(s=s_r, n_within=int(keep.sum()))
            continue
        pi, sg = fit_mixture(d_in[keep], g_in[keep], v_in[keep])
        d_true = [true_d(V.walk_row[i], V.scan_row[i], V.walk_row[j], V.scan_row[j]) for (i, j), _ in mutual[:m]]
        rates[str(r)] = dict(
            s=s_r, n_within=int(keep.sum()), pi=pi, sigma=sg, p_model_5m=p_model_5m(pi, sg, G5), p_true_5m=float(np.mean(np.array(d_true) < 5.0))
        )
    by_walk = {w.walk: w for w in walks}
    node_row = {}
    for w in walks:
        for i, n in enumerate(w.node):
            node_row[int(n)] = (w.walk, i)
    acc = [lp for lp in loops if lp.accepted]

    def node_row_of(lp):
        return node_row[lp.node_a][1], node_row[lp.node_b][1]

    d_acc = np.array([np.linalg.norm(truth[lp.walk_a][node_row[lp.node_a][1]] - truth[lp.walk_b][node_row[lp.node_b][1]]) for lp in acc])
    reasons: dict[str, int] = {}
    for lp in loops:
        reasons[lp.reason or "accepted"] = reasons.get(lp.reason or "accepted", 0) + 1
    linked = len({lp.walk_a for lp in acc} | {lp.walk_b for lp in acc})
    # walk-pair translations (clique means) against the truth: with each walk's frame taken as a shift of
    # the site frame over the clique's scans, t_true = mean_j (p_B - q_B) - mean_i (p_A - q_A)
    t_err = []
    for pt in pair_translations(loops, walks):
        mem = [node_row_of(lp) for lp in acc if (lp.walk_a, lp.walk_b) == (pt.walk_a, pt.walk_b)]
        A, B = by_walk[pt.walk_a], by_walk[pt.walk_b]
        ia = np.unique([m[0] for m in mem])
        jb = np.unique([m[1] for m in mem])
        t_true = (truth[B.walk][jb] - B.q[jb]).mean(axis=0) - (truth[A.walk][ia] - A.q[ia]).mean(axis=0)
        t_err.append(float(np.linalg.norm(pt.t - t_true)))
    return dict(
        scans=n_scans,
        walks=len(walks),
        candidates=len(loops),
        reasons=reasons,
        accepted=len(acc),
        accepted_per_scan=len(acc) / n_scans,
        accepted_p5m=float(np.mean(d_acc < 5.0)) if len(acc) else float("nan"),
        accepted_d50=float(np.median(d_acc)) if len(acc) else float("nan"),
        # share of accepted loops within the 99 % radius of the Rayleigh the model gives each (sigma_in sqrt(9.21))
        accepted_in_model=float(np.mean(d_acc <= np.array([lp.sigma_in for lp in acc]) * math.sqrt(CHI2_2_99))) if len(acc) else float("nan"),
        walks_linked=linked,
        walk_pairs=len(t_err),
        pair_translation_err_median=float(np.median(t_err)) if t_err else float("nan"),
        pair_translation_err_p90=float(np.percentile(t_err, 90)) if t_err else float("nan"),
        rates=rates,
        seconds=seconds,
        model=det.model.table() if det.model is not None else "",
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--site", default=str(SITE))
    ap.add_argument("--cache", default=None, help="pickle of the read traces and PDR steps (written if absent)")
    ap.add_argument("--measures", default=",".join(MEASURES))
    ap.add_argument("--model", action="store_true", help="print each fitted distance model")
    args = ap.parse_args(argv)
    site = Path(args.site)
    traces = load_site(site, args.cache)
    base = FrontendConfig()
    walks, truth = build_walks(traces, base.max_age_s)
    floors = sorted({w.floor for w in walks})
    variants = [(m, off) for m in args.measures.split(",") for off in (False, True)]
    result: dict = {}
    for fl in floors:
        fw = [w for w in walks if w.floor == fl]
        pts = walkable_points(site, fl)
        print(f"\n== {fl}: {len(fw)} walks, {sum(len(w.scans) for w in fw)} scans, {len(pts)} walkable 1 m cells")
        print(
            "measure     offset | no truth: r=0.05 pi sigma P_model | r=0.1 pi sigma P_model | r=0.2 pi sigma P_model || "
            "truth P(d<5) r=.05 .1 .2 | accepted/scan P(d<5) d50 P(d<3.03 sigma_in) walks linked | walk pairs, translation error median p90 | s"
        )
        for m, off in variants:
            cfg = FrontendConfig(measure=m, remove_offset=off)
            res = evaluate(fw, truth, cfg, pts)
            result.setdefault(fl, {})[f"{m}{'+offset' if off else ''}"] = {k: v for k, v in res.items() if k != "model"}
            cells, tcells = [], []
            for r in RATES:
                x = res["rates"].get(str(r), {})
                cells.append(f"{x.get('pi', float('nan')):.2f} {x.get('sigma', float('nan')):5.2f} {x.get('p_model_5m', float('nan')):.3f}")
                tcells.append(f"{x.get('p_true_5m', float('nan')):.2f}")
            print(
                f"{m:10s} {str(off):6s} | {' | '.join(cells)} || {' '.join(tcells)} | {res['accepted_per_scan']:.3f} "
                f"{res['accepted_p5m']:.2f} {res['accepted_d50']:4.1f} m {res['accepted_in_model']:.2f} {res['walks_linked']:3d}/{res['walks']} | "
                f"{res['walk_pairs']:3d} {res['pair_translation_err_median']:4.1f} {res['pair_translation_err_p90']:4.1f} m | {res['seconds']:.1f}"
            )
            if args.model:
                print(res["model"])
                print("reasons:", res["reasons"])
    # the choice: mean over floors and rates of P_model (no truth)
    score = {}
    for key in result[floors[0]]:
        vals = [
            result[fl][key]["rates"][str(r)].get("p_model_5m", float("nan")) for fl in floors for r in RATES if str(r) in result[fl][key]["rates"]
        ]
        score[key] = float(np.nanmean(vals)) if vals else float("nan")
    best = max(score, key=lambda k: -1 if math.isnan(score[k]) else score[k])
    if best.endswith("+offset") and score[best] - score[best.removesuffix("+offset")] < OFFSET_MARGIN:
        best = best.removesuffix("+offset")  # the offset removal must earn its keep
    print("\nno-truth score (mean P_model(d<5) over floors and rates):", ", ".join(f"{k} {v:.3f}" for k, v in score.items()), f"-> {best}")
    print(json.dumps({"floors": result, "score": score, "chosen": best}))


if __name__ == "__main__":
    main()

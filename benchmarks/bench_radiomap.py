"""Radio map speed: build from 100,000 labelled scans (goal <= 30 s) and one locate query on a floor of
5,000 cells and 1,000 transmitters (goal <= 2 ms median).

A synthetic floor 106 m x 106 m (1.5 m cells -> ~5,000 cells) with 1,000 access points; RSSI by
log-distance path loss (-45 dBm at 1 m, exponent 3.5, 4 dB shadowing), heard above -90 dBm: about
100 access points per scan, as in a shopping mall (the Indoor Location Competition site1 median is 147). Measured in the
same run: our Sorensen kNN and the plain method, scikit-learn's Euclidean weighted kNN, over the same labelled scans.

    python -m benchmarks.bench_radiomap [--scans 100000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks import headline
from hybridloc.radio.locate import KnnLocator, ProbabilisticLocator
from hybridloc.radio.radiomap import BuildParams, build_radio_map
from hybridloc.radio.survey import LabelledScan
from hybridloc.types import RfScan


def world(n_scans: int, rng: np.random.Generator, side: float = 106.0, n_ap: int = 1000):
    aps = rng.uniform(0, side, (n_ap, 2))
    names = [f"ap{i:04d}" for i in range(n_ap)]

    def scan(p, t):
        d = np.maximum(1.0, np.linalg.norm(aps - p, axis=1))
        r = -45.0 - 35.0 * np.log10(d) + 4.0 * rng.standard_normal(n_ap)
        heard = np.flatnonzero(r > -90.0)
        return RfScan(t, "wifi", {names[j]: float(r[j]) for j in heard})

    pts = rng.uniform(0, side, (n_scans, 2))
    labelled = [LabelledScan(scan(p, float(i)), p, 0.5, "F1") for i, p in enumerate(pts)]
    q_pts = rng.uniform(5, side - 5, (300, 2))
    queries = [scan(p, 1e6 + i) for i, p in enumerate(q_pts)]
    return labelled, queries, q_pts


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scans", type=int, default=100_000)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(5)
    t0 = time.perf_counter()
    labelled, queries, q_pts = world(args.scans, rng)
    gen = time.perf_counter() - t0
    t0 = time.perf_counter()
    rmap = build_radio_map(labelled, params=BuildParams(cell=1.5, min_samples=3))
    build = time.perf_counter() - t0
    f = rmap.floors["F1"]
    print(
        f"radio map: {len(labelled)} labelled scans (generated in {gen:.1f} s) built in {build:.1f} s "
        f"(goal <= 30 s): {len(f.cells)} cells x {len(f.tx)} transmitters"
    )
    for region in (False, True):
        loc = ProbabilisticLocator(rmap, region=region)
        ts, errs = [], []
        for q, p in zip(queries, q_pts):
            t0 = time.perf_counter()
            r = loc.locate(q)
            ts.append(time.perf_counter() - t0)
            errs.append(np.linalg.norm(r.fix.pos_enu - p))
        ts = np.array(ts) * 1e3
        print(
            f"locate (cell likelihood{', with 95% region polygons' if region else ''}): median {np.median(ts):.2f} ms, p99 {np.percentile(ts, 99):.2f} ms "
            f"(goal median <= 2 ms); median error {np.median(errs):.2f} m"
        )
    per_q = {}
    for metric, label in (
        ("sorensen", "our weighted kNN (Sorensen, sparse references)"),
        ("euclidean", "plain weighted kNN (scikit-learn, Euclidean)"),
    ):
        t0 = time.perf_counter()
        knn = KnnLocator(labelled[:20000], k=5, metric=metric)
        fit = time.perf_counter() - t0
        t0 = time.perf_counter()
        res = knn.locate_many(queries)
        per_q[metric] = (time.perf_counter() - t0) / len(queries) * 1e3
        e = [np.linalg.norm(r.fix.pos_enu - p) for r, p in zip(res, q_pts)]
        print(f"{label}, 20,000 references (fit {fit:.1f} s): {per_q[metric]:.2f} ms per query in a batch; median error {np.median(e):.2f} m")
    print(
        f"ratios: Sorensen/scikit-learn kNN time {per_q['sorensen'] / per_q['euclidean']:.2f}; cell-likelihood/Sorensen kNN time {np.median(ts) / per_q['sorensen']:.2f}"
    )
    headline(
        {
            "build_s": build,
            "locate_region_median_ms": np.median(ts),
            "knn_sorensen_ms_per_query": per_q["sorensen"],
            "knn_euclidean_ms_per_query": per_q["euclidean"],
        }
    )


if __name__ == "__main__":
    main()

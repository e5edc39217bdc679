"""``hybridloc locate``: fingerprint positioning of recordings against a radio map file."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import MissingData


def _cmd_locate(args: argparse.Namespace) -> int:
    import csv
    import math

    from ..io.common import stem_of
    from ..io.writers import region_feature, write_geojson
    from ..radio.locate import KnnLocator, ProbabilisticLocator
    from ..radio.radiomap import RadioMap
    from ..radio.sources import scans_to_locate

    rmap = RadioMap.load(args.map)
    if args.method == "knn":
        if not rmap.references:
            raise MissingData(f"{args.map} holds no reference scans for kNN; use --method prob")
        knn = KnnLocator(rmap.references, k=args.k, max_age_s=args.max_age, metric=args.metric)
    else:
        prob = ProbabilisticLocator(rmap, max_age_s=args.max_age)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for p in args.inputs:
        scans, site = scans_to_locate(args.format, p)
        if site and rmap.site and site != rmap.site:
            from ..radio.locate import LocateResult

            results = [LocateResult(None, None, reason=f"the map is of site {rmap.site!r}, this input of {site!r}") for _ in scans]
        else:
            results = knn.locate_many(scans) if args.method == "knn" else [prob.locate(s) for s in scans]
        stem = stem_of(p)
        feats = []
        with open(out / f"{stem}.csv", "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            extra_cols = ["building"] if args.format == "ujiindoorloc" else []
            w.writerow(["t", "x", "y", "floor", "sigma_x", "sigma_y", "floor_prob", *extra_cols, "reason"])
            n_fix = 0
            for s, res in zip(scans, results):
                if res.fix is None:
                    w.writerow([f"{s.t:.3f}", "", "", "", "", "", "", *([""] * len(extra_cols)), res.reason])
                    continue
                n_fix += 1
                fl = res.fix.floor or ""
                extra = []
                if args.format == "ujiindoorloc" and fl.startswith("b"):
                    b, f_ = fl[1:].split("_f")
                    fl, extra = f_, [b]
                sx, sy = (math.sqrt(v) for v in (res.fix.cov[0, 0], res.fix.cov[1, 1]))
                w.writerow(
                    [
                        f"{s.t:.3f}",
                        f"{res.fix.pos_enu[0]:.3f}",
                        f"{res.fix.pos_enu[1]:.3f}",
                        fl,
                        f"{sx:.3f}",
                        f"{sy:.3f}",
                        f"{res.fix.floor_prob:.4f}",
                        *extra,
                        "",
                    ]
                )
                if res.region is not None:
                    feats.append(region_feature(res.region))
        write_geojson(out / f"{stem}.geojson", feats)
        print(f"{p}: {len(scans)} scans, {n_fix} fixes -> {out / (stem + '.csv')}")
    return 0


def register(sub) -> None:
    lo = sub.add_parser("locate", help="fingerprint positioning: a CSV of fixes and a GeoJSON of regions per input")
    lo.add_argument("inputs", nargs="+", metavar="INPUT")
    lo.add_argument("--map", required=True, metavar="MAP")
    lo.add_argument("--format", choices=("msft", "ujiindoorloc", "csv"), required=True)
    lo.add_argument("--out", required=True, metavar="DIR")
    lo.add_argument("--method", choices=("knn", "prob"), default="knn", help="weighted kNN (default) or the probabilistic cell likelihood")
    lo.add_argument("--k", type=int, default=5)
    lo.add_argument(
        "--metric",
        choices=("sorensen", "euclidean"),
        default="sorensen",
        help="kNN distance on powed fingerprints: Sorensen / Bray-Curtis (default) or Euclidean",
    )
    lo.add_argument("--max-age", type=float, default=8.0, help="ignore readings older than this at scan time, s (default 8)")
    lo.set_defaults(func=_cmd_locate)

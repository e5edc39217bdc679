"""Is the foot INS's zero-angular-rate update what lets the gait-driven walks' heading drift (issue #24
point 2)? On the 3DM-GX5-25 the stance is never still (``probe_foot_heading.py``: least |omega| per
stance 7-33 deg/s), and the chi-square gate turns away 59-96 % of the ZARUs there (PyShoe's GX3, its first four trials: 30-41 %):
the ones it keeps are the stance samples whose rate happens to sit near the current bias estimate, a
selection that could bias the estimate itself.

    python scripts/probe_foot_zaru.py [GAIT_DIR]

Runs ``eval pdr-foot``'s gait-driven scoring (``--detector robust``) with the ZARU's noise and its
treatment of large residuals varied: the gate (the filter's: sigma 0.5 deg/s), no gate, Huber's and
Cauchy's kernels instead of the gate. Prints, per way, the return error (% of the path) of the walks
whose truth closes, the final-point error of all walks and the footprint error; the last line is one
JSON object. Only the ZARU changes (its model class is wrapped); nothing is shipped from here.

Measured 2026-12-07 (return median / max, %): gated 0.5 deg/s 2.45 / 6.09 (the filter's); ungated 0.5
16.55 / 34.88, 2 3.95 / 26.47, 3 2.43 / 12.44, 4 2.21 / 4.82, 5 2.44 / 3.21, 7 2.97 / 4.70, 10 3.04 /
5.55; gated 5 2.42 / 4.40; Huber 0.5 2.66 / 15.01, 1 2.13 / 6.44; Cauchy 0.5 2.41 / 3.89, 2 2.78 /
5.04. Some ways cut the worst walk (40: 6.09 -> 0.70 % at ungated 5 deg/s) and cost others (36: 1.11
-> 2.71 %); no way brings the median near the 1.0 % goal, and the footprint error is no better than the
filter's 0.555 m anywhere but ungated 5 deg/s (0.540 m). That one, checked further (a scratch run, not
this script): PyShoe VICON mean ARMSE 0.0526 m against 0.0529 m, but 20 simulated closed loops
(``hybridloc.ins.evaluate.simulated_loop_errors(20)``) 5.76 % median, 39.4 % max against the filter's
0.48 / 1.40 %. The ZARU's weighting is not the lever.
"""

from __future__ import annotations

import argparse
import json
import math

import hybridloc.ins.eskf as eskf
import hybridloc.ins.foot as foot
from hybridloc.estimation import Cauchy, Huber
from hybridloc.ins.evaluate import evaluate_gait_walk, gait_walks, summarize_gait
from hybridloc.ins.measurements import ZeroAngularRate

WAYS = [("gated", 0.5), ("ungated", 0.5), ("ungated", 2.0), ("ungated", 3.0), ("ungated", 4.0), ("ungated", 5.0), ("ungated", 7.0)]
WAYS += [("ungated", 10.0), ("gated", 5.0), ("huber", 0.5), ("huber", 1.0), ("cauchy", 0.5), ("cauchy", 2.0)]

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("gait_dir", nargs="?", default="../shared/data/gait-driven-own")
args = ap.parse_args()
walks = gait_walks(args.gait_dir)
if not walks:
    raise SystemExit(f"{args.gait_dir}: no gait-driven walks (SensorConnect CSV + footprint .mat)")

filter_correct = eskf.ErrorStateEkf.correct
out = {}
for treatment, sigma_deg in WAYS:

    class Zaru(ZeroAngularRate):
        def __init__(self, omega_body, treatment=treatment, sigma_deg=sigma_deg):
            super().__init__(omega_body, sigma=sigma_deg * math.pi / 180)
            if treatment in ("huber", "cauchy"):
                self.kernel = Huber() if treatment == "huber" else Cauchy()

    def correct(self, model, z, gate=True, treatment=treatment):
        # the kernels replace the gate: a large residual is down-weighted instead of turned away
        return filter_correct(self, model, z, gate and not (model.kind == "zaru" and treatment != "gated"))

    foot.ZeroAngularRate = Zaru
    eskf.ErrorStateEkf.correct = correct
    try:
        rs = [evaluate_gait_walk(p, foot.FootInsConfig(detector="robust")) for p in walks]
    finally:
        foot.ZeroAngularRate = ZeroAngularRate
        eskf.ErrorStateEkf.correct = filter_correct
    s = summarize_gait(rs)
    key = f"{treatment} {sigma_deg:g} deg/s"
    out[key] = {
        "return_median_pct": s.return_median_pct,
        "return_max_pct": s.return_max_pct,
        "final_median_pct": s.final_median_pct,
        "footprint_median_m": s.footprint_median_m,
    }
    print(
        f"ZARU {key:>18}: return median {s.return_median_pct:5.2f} % max {s.return_max_pct:5.2f} % ({s.closing} closing walks); "
        f"final median {s.final_median_pct:5.2f} %; footprint median {s.footprint_median_m:.3f} m",
        flush=True,
    )
print(json.dumps(out))

"""Does the gait-driven set's gyro clipping limit its return error (issue #24 point 2)?

The 3DM-GX5-25 of the gait-driven walks clips its rate near 500 deg/s (497-511 deg/s by axis and sign),
and a running foot's pitch rate goes past that. Its readings wander about the ceiling instead of
repeating (505.8, 507.3, 507.5, 507.3 deg/s), so the exact-repeat test of ``ImuBlock.saturated`` missed
them until the ceiling test (``hybridloc.types.CEILING_SHARE``) was added.

    python scripts/probe_foot_clipping.py [GAIT_DIR]

Prints, per walk, the samples at the ceiling (share of the walk) and the final-point error (% of the
path) with the filter as ``eval pdr-foot`` runs it (``--detector robust``) and with the vertical ZARU
at 5 deg/s and the demoted runs' ZUPTs gated (the setting its last section chooses in every fold
since the robust detector's shortest stance, 2026-12-07; 0.5 deg/s before).
Then the cause tested directly: the walks with no sample at a ceiling, their gyro clipped on purpose
at 450, 400 and 350 deg/s, run again. Then two remedies (not shipped): (a) each clipped run filled
with a cubic through the two readings either side of it, and (b) the attitude's covariance grown,
along the clipped body axis only, by 30 % of the reading's rate per clipped sample (the filter then
lets the next ZUPT set the tilt). The last line is one JSON object. Nothing is shipped from here.

Measured 2026-12-07 with the shortest stance (``stance.MIN_STANCE_S``), the final-point error, robust
/ vertical ZARU at 5 deg/s + gated demoted runs (%), and the share of samples the ceiling test flags:
walks that reach the ceiling 31 (0.20 %) 2.16 / 2.15, 33 (0.13 %) 2.51 / 2.15, 34 (0.92 %) 2.30 /
1.84, 35 (3.77 %) 2.59 / 3.25, 38 (0.27 %) 3.66 / 2.88, 43 (0.36 %) 5.46 / 1.84, 44 (0.13 %) 3.71 /
1.48; walks that never do: 32 0.56 / 0.67, 36 1.11 / 0.31, 39 2.47 / 0.38, 40 6.09 / 0.32, 42 4.44 /
0.96, 45 4.47 / 0.64. With the vertical ZARU the medians are 2.15 % (reaching the ceiling) against
0.51 % (never), and the closing walks' return median is 0.65 %. Those that reach the ceiling are the
fast ones (34, 35, 38, 43, 44 peak at 8.8-17 g against 3.9-5.9 g), so speed and clipping go together
here. Clipping the six clean walks on purpose separates them: at 450 deg/s (0.2 % of samples) their
median is 0.61 %, at 400 (1.3 %) 1.36 %, at 350 (3.9 %) 6.01 %. A few tenths of a percent of the
samples clipped cost little, a few percent cost a few percent of the path: walk 35 (3.8 % flagged;
7.6 % of its samples at 495 deg/s or more) is within what its clipping explains. Neither remedy moves
the closing walks' median (0.65 %): (a) 0.65 % (35: 3.25 -> 4.43 %), (b) 0.65 % (38: 2.88 -> 1.44,
43: 1.84 -> 0.20, 44: 1.48 -> 1.14, 34: 1.84 -> 1.56, but 35: 3.25 -> 10.72 %). Before the shortest
stance (0.5 deg/s, the robust detector cutting strides at mid-swing dips): 2.58 % against 0.77 %,
return 1.37 %; clipped on purpose 0.85 / 0.82 / 3.96 %; remedies 1.35 / 1.32 %.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

import hybridloc.ins.eskf as eskf
import hybridloc.io.imu_files as imu_files
from hybridloc.ins.evaluate import evaluate_gait_walk, gait_walks
from hybridloc.ins.foot import PLATEAU_ACCEL, PLATEAU_GYRO, FootInsConfig
from hybridloc.ins.stance import stance_runs

ROBUST = FootInsConfig(detector="robust")
ZARU_UP = replace(ROBUST, zaru_up_sigma=5.0 * math.pi / 180, vet_demoted=True)
CONFIGS = {"robust": ROBUST, "zaru-up": ZARU_UP}
CLIP_DEG_S = (450.0, 400.0, 350.0)
INFLATE = 0.3  # remedy (b): attitude sd added per clipped sample, as a share of the reading's rate x dt

_read = imu_files.read_sensorconnect_csv
_predict = eskf.ErrorStateEkf.predict


def _clipped(imu):
    return imu.saturated(PLATEAU_ACCEL, PLATEAU_GYRO)[1]


def _cubic_fill(imu):
    """Remedy (a): each clipped run of an axis replaced, where larger, by a cubic through the two
    readings either side of it."""
    from scipy.interpolate import CubicSpline

    g = imu.gyro_body.copy()
    n = len(g)
    for k, level in enumerate(_axis_levels(imu)):
        for a, b in zip(*stance_runs(np.abs(g[:, k]) >= level)):
            idx = np.r_[max(0, a - 2) : a, b : min(n, b + 2)]
            if len(idx) < 4:
                continue
            s = np.sign(g[a, k])
            fit = CubicSpline(idx, s * g[idx, k])(np.arange(a, b))
            g[a:b, k] = s * np.maximum(s * g[a:b, k], fit)
    return g


def _axis_levels(imu) -> np.ndarray:
    """Per body axis, the rate (rad/s) from which its readings sit at a ceiling (inf: none): 99 % of
    the axis's largest reading when the saturated samples hold it."""
    g = np.abs(imu.gyro_body)
    near = _clipped(imu)
    out = np.full(3, np.inf)
    for k in range(3):
        top = 0.99 * g[:, k].max()
        if np.any(near & (g[:, k] >= top)):
            out[k] = top
    return out


def _job(job):
    path, cfg_name, mode, level = job
    state = {}

    def read(p, *a, **k):
        rec = _read(p, *a, **k)
        imu = rec.imu
        if mode == "clip":
            c = math.radians(level)
            imu = dataclasses.replace(imu, gyro_body=np.clip(imu.gyro_body, -c, c))
        elif mode == "cubic":
            imu = dataclasses.replace(imu, gyro_body=_cubic_fill(imu))
        elif mode == "inflate":
            state["level"] = _axis_levels(imu)
        return dataclasses.replace(rec, imu=imu)

    def predict(self, f, w, dt):
        _predict(self, f, w, dt)
        on = np.abs(w) >= state.get("level", np.full(3, np.inf))
        if on.any():
            R = self.x.R
            self.P[6:9, 6:9] += R @ np.diag(np.where(on, (INFLATE * np.abs(w) * dt) ** 2, 0.0)) @ R.T

    imu_files.read_sensorconnect_csv = read
    eskf.ErrorStateEkf.predict = predict
    try:
        r = evaluate_gait_walk(path, CONFIGS[cfg_name])
        imu = read(path).imu
    finally:
        imu_files.read_sensorconnect_csv = _read
        eskf.ErrorStateEkf.predict = _predict
    share = (
        100.0 * float(_clipped(imu).mean())
        if mode != "clip"
        else 100.0 * float((np.abs(imu.gyro_body) >= math.radians(level) * 0.999).any(axis=1).mean())
    )
    return r.name, r.final_pct, r.closes, share


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("gait_dir", nargs="?", default="../shared/data/gait-driven-own")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    walks = gait_walks(args.gait_dir)
    if not walks:
        raise SystemExit(f"{args.gait_dir}: no gait-driven walks (SensorConnect CSV + footprint .mat)")
    out: dict = {}
    with ProcessPoolExecutor(args.workers) as ex:

        def run(paths, mode, level=0.0):
            res = {}
            for name in CONFIGS:
                res[name] = list(ex.map(_job, [(p, name, mode, level) for p in paths]))
            return res

        base = run(walks, "as-read")
        shares = {n: s for n, _, _, s in base["robust"]}
        clipped = [n for n, s in shares.items() if s > 0]
        print("walk                   at the ceiling   final: robust  zaru-up   closes")
        for (n, f0, cl, s), (_, f1, _, _) in zip(base["robust"], base["zaru-up"]):
            print(f"{n:<22} {s:9.2f} %        {f0:7.2f} %  {f1:6.2f} %   {'yes' if cl else ''}")
        for name in CONFIGS:
            fin = {n: f for n, f, _, _ in base[name]}
            mc = float(np.median([fin[n] for n in clipped])) if clipped else float("nan")
            mu = float(np.median([f for n, f in fin.items() if n not in clipped]))
            ret = float(np.median([f for _, f, c, _ in base[name] if c]))
            print(f"{name}: final-point median, walks with samples at the ceiling {mc:.2f} %, without {mu:.2f} %; return (closing walks) {ret:.2f} %")
            out[f"{name}_final_median_clipped_pct"], out[f"{name}_final_median_unclipped_pct"] = mc, mu
            out[f"{name}_return_median_pct"] = ret
        out["samples_at_ceiling_pct"] = shares
        clean = [p for p in walks if shares[p.name.split(".")[0]] == 0]
        print(f"\nthe {len(clean)} walks with no sample at a ceiling, clipped on purpose:")
        for level in CLIP_DEG_S:
            res = run(clean, "clip", level)
            for name in CONFIGS:
                fin = [f for _, f, _, _ in res[name]]
                share = float(np.mean([s for _, _, _, s in res[name]]))
                print(
                    f"  at {level:.0f} deg/s ({share:.1f} % of samples) {name:>8}: final-point median {np.median(fin):.2f} % "
                    f"({' '.join(f'{n[-2:]}:{f:.2f}' for n, f, _, _ in res[name])})"
                )
                out[f"clip{level:.0f}_{name}_final_median_pct"] = float(np.median(fin))
        print("\nremedies on every walk (not shipped):")
        for mode, label in (
            ("cubic", "(a) cubic fill of the clipped runs"),
            ("inflate", f"(b) attitude covariance grown along the clipped axis ({INFLATE:g})"),
        ):
            res = run(walks, mode)
            for name in CONFIGS:
                rs = res[name]
                ret = float(np.median([f for _, f, c, _ in rs if c]))
                print(f"  {label} {name:>8}: return median {ret:.2f} % ({' '.join(f'{n[-2:]}:{f:.2f}' for n, f, _, _ in rs)})")
                out[f"{mode}_{name}_return_median_pct"] = ret
    print(json.dumps(out))


if __name__ == "__main__":
    main()

"""Why the foot INS's heading drifts on the gait-driven walks (3DM-GX5-25): the measurements behind
``hybridloc.ins.hde``.

    python scripts/probe_foot_heading.py [../shared/data/gait-driven-own] [--preset gait-driven]

Per walk (default filter, ``--detector robust``; with ``--preset``, that preset of ``pdr foot``), one
line each:

* stance: how still the foot is where the detector calls stance: |omega| median over stance samples
  and the median of each stance run's least |omega| (a still foot reads ~1 deg/s: PyShoe's GX3, below);
* gyro at the start: the mean rate along gravity over the still prefix (a bias, plus the sway of a
  standing walker), against the vertical bias the filter ends with;
* heading: where the strides were counted exactly, the INS's stride heading minus the truth's, at the
  end and as a slope over time (deg/s): least squares, and Theil-Sen's median of pairwise slopes (the
  few strides through a turn, tens of degrees off, pull the least-squares slope; not the median); and
  the same error fitted with a gyro scale-factor term as well (a share of the angle turned), and the
  strides' summed length against the footprints';
* magnetometer (when logged): |B| and dip at each footprint (INS attitude), and how far the field's
  azimuth, turned into the truth's frame by the INS's own heading error there, wanders (a usable
  compass would hold it still), over all footprints and over those passing a 5 % |B| / 5 deg dip gate.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

import hybridloc.ins.foot as foot
from hybridloc.ins import stance as sm
from hybridloc.ins.eskf import ErrorStateEkf
from hybridloc.ins.evaluate import gait_walks
from hybridloc.ins.strapdown import quat_to_dcm
from hybridloc.io.imu_files import footprints_beside, read_pyshoe_mat, read_sensorconnect_csv

D = math.pi / 180


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


class _Recorder(ErrorStateEkf):
    last: _Recorder | None = None

    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        _Recorder.last = self


def main(folder: str, preset: str | None = None) -> None:
    from scipy.stats import theilslopes

    foot.ErrorStateEkf = _Recorder  # type: ignore[misc]  # to read the filter's final bias
    cfg = foot.FootInsConfig(**foot.FOOT_PRESETS[preset]) if preset else foot.FootInsConfig(detector="robust")
    for p in gait_walks(folder):
        imu = read_sensorconnect_csv(p).imu
        fp = footprints_beside(p)
        assert fp is not None
        res = foot.run_foot_ins(imu, cfg)
        kf = _Recorder.last
        assert kf is not None and res.step_stance is not None
        w = np.linalg.norm(imu.gyro_body, axis=1) / D
        s, e = sm.stance_runs(res.step_stance)
        mins = [w[a:b].min() for a, b in zip(s, e)]
        n0 = foot.still_prefix(imu, 5.0)
        up = imu.accel_body[:n0].mean(0)
        up /= np.linalg.norm(up)
        b_start = float(imu.gyro_body[:n0].mean(0) @ up) / D
        b_filter = float((quat_to_dcm(kf.x.q) @ kf.x.b_g)[2]) / D
        line = (
            f"{p.name.split('.')[0]:<22} stance |w| median {np.median(w[res.stance]):5.1f} deg/s, least per stance {np.median(mins):5.1f}; "
            f"vertical gyro: start mean {b_start:+.2f} deg/s, filter's bias {b_filter:+.2f}"
        )
        pts = np.array(foot.stance_points(res))
        if len(pts) - 1 == fp.n_strides:
            t = res.t[pts[fp.stride[1:]]]
            de = np.diff(res.pos_enu[pts, :2][fp.stride], axis=0)
            dg = np.diff(fp.pos_xy, axis=0)
            err = np.unwrap(wrap(np.arctan2(de[:, 1], de[:, 0]) - np.arctan2(dg[:, 1], dg[:, 0])))
            err -= err[:3].mean()
            line += (
                f"; heading error at the end {np.mean(err[-3:]) / D:+.1f} deg, slope {np.polyfit(t, err, 1)[0] / D:+.3f} deg/s "
                f"(Theil-Sen {theilslopes(err, t)[0] / D:+.3f})"
            )
            # a gyro scale-factor error turns the heading by a share of the angle turned, not by time:
            # err = a + b t + c turned (turned: the truth's unwrapped bearing change), Huber-weighted
            turned = np.unwrap(np.arctan2(dg[:, 1], dg[:, 0]))
            A = np.c_[np.ones_like(t), t - t[0], turned - turned[0]]
            w = np.ones_like(t)
            for _ in range(20):
                c = np.linalg.lstsq(A * w[:, None], err * w, rcond=None)[0]
                r = err - A @ c
                w = 1.0 / np.maximum(1.0, np.abs(r) / (1.5 * 1.4826 * np.median(np.abs(r)) + 1e-12))
            ratio = np.linalg.norm(de, axis=1).sum() / np.linalg.norm(dg, axis=1).sum()
            line += f"; with a scale term: {c[1] / D:+.3f} deg/s and {100 * c[2]:+.2f} % of the {(turned[-1] - turned[0]) / D:+.0f} deg turned; stride lengths summed x{ratio:.4f} the truth's"
            if imu.mag_body is not None:
                idx = pts[fp.stride[1:]]
                mn = np.array([quat_to_dcm(res.quat_wxyz[i]) @ imu.mag_body[i] for i in idx]) * 1e6
                F = np.linalg.norm(mn, axis=1)
                dip = np.arctan2(-mn[:, 2], np.hypot(mn[:, 0], mn[:, 1])) / D
                az = wrap(np.arctan2(mn[:, 1], mn[:, 0]) - err)
                az = wrap(az - math.atan2(np.sin(az).mean(), np.cos(az).mean())) / D
                ok = (np.abs(F - np.median(F)) < 0.05 * np.median(F)) & (np.abs(dip - np.median(dip)) < 5)
                line += (
                    f"; |B| {F.min():.0f}-{F.max():.0f} uT, dip {dip.min():.0f}-{dip.max():.0f} deg; field azimuth wanders "
                    f"{np.median(np.abs(az)):.1f} deg (median |dev|), gated {int(ok.sum())} of {len(ok)}: "
                    f"{np.median(np.abs(az[ok])) if ok.any() else float('nan'):.1f} deg"
                )
            else:
                line += "; no magnetometer logged"
        print(line, flush=True)
    pyshoe = Path(folder).parent / "pyshoe-vicon"
    for f in sorted(pyshoe.glob("*.mat"))[:3]:
        imu = read_pyshoe_mat(f).imu
        res = foot.run_foot_ins(imu)
        w = np.linalg.norm(imu.gyro_body, axis=1) / D
        print(f"PyShoe {f.stem:<15} stance |w| median {np.median(w[res.stance]):5.1f} deg/s (the GX3: a still stance)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", nargs="?", default="../shared/data/gait-driven-own")
    ap.add_argument("--preset", choices=list(foot.FOOT_PRESETS), help="a pdr foot preset (default: --detector robust)")
    a = ap.parse_args()
    main(a.folder, a.preset)

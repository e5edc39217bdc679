"""Foot INS evaluation on PyShoe VICON trials (``hybridloc eval pdr-foot``).

Per trial: PyShoe's 2-D and 3-D ARMSE (:func:`hybridloc.metrics.pyshoe_armse` after
:func:`~hybridloc.metrics.pyshoe_align`) of our default filter and detector, one setting for all
trials, beside the authors' own ``trial_error`` (their ZUPT-EKF with the SHOE detector at the
threshold tuned per trial on the ground truth); for trials whose truth returns to its start (a loop:
end within ``LOOP_CLOSE_M`` of the start), the return-to-start error in % of distance travelled
(Ojeda & Borenstein eqs 7-9). A plain method runs beside ours in the same pass: DEDRIFT-I
(Ojeda's velocity reset + acceleration de-drifting at gyro minima).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..io.imu_files import read_pyshoe_mat
from ..metrics import pyshoe_align, pyshoe_armse, return_to_start_error
from .foot import FootInsConfig, dedrift_i, run_foot_ins
from .stance import gyro_minimum

#: A trial is a loop when its true end is within this distance of its true start, m.
LOOP_CLOSE_M = 0.3


@dataclass
class TrialResult:
    name: str
    armse_2d: float
    armse_3d: float
    authors_2d: float
    dedrift_2d: float
    distance_m: float
    loop_pct: float | None  # return-to-start error, % of distance (loops only)
    duration_s: float
    stance_fraction: float
    opt_labels_2d: float = float("nan")  # our forward filter on the authors' per-trial-optimal SHOE stance labels
    forward_2d: float = float("nan")  # the forward filter alone (no stride smoothing), like the authors' figure


def evaluate_trial(path: str | Path, config: FootInsConfig | None = None) -> TrialResult:
    rec = read_pyshoe_mat(path)
    if rec.truth is None:
        raise ValueError(f"{path}: no ground truth")
    res = run_foot_ins(rec.imu, config)
    est, gt = pyshoe_align(res.pos_enu, rec.truth.pos_enu)
    fwd = float("nan")
    if res.pos_enu_forward is not None:
        fwd = pyshoe_armse(*pyshoe_align(res.pos_enu_forward, rec.truth.pos_enu), 2)
    dd = dedrift_i(rec.imu, gyro_minimum(rec.imu.gyro_body, n=max(1, int(0.5 * rec.imu.rate_hz)))[1])
    dd_a, gt_a = pyshoe_align(dd, rec.truth.pos_enu)
    loop = None
    if np.linalg.norm(gt[-1, :2] - gt[0, :2]) <= LOOP_CLOSE_M:
        loop = return_to_start_error(res.pos_enu).e_p
    dist = float(np.linalg.norm(np.diff(gt[:, :2], axis=0), axis=1).sum())
    te = rec.extras.get("trial_error")
    opt = float("nan")
    labels = rec.extras.get("zv_shoe_opt")
    if labels is not None and len(labels) == len(rec.imu.t):
        # the same filter on the stance the authors' SHOE gives at its per-trial best threshold: splits
        # the gap to their figure into what the detector costs and what the filter does. Their labels
        # are taken as they are (no vetting: deciding which stances to doubt is part of our detection)
        # and, like the authors' figure, the forward filter's track
        cfg_opt = replace(config or FootInsConfig(), vet=False, smooth=False)
        e_opt, g_opt = pyshoe_align(run_foot_ins(rec.imu, cfg_opt, stance=labels).pos_enu, rec.truth.pos_enu)
        opt = pyshoe_armse(e_opt, g_opt, 2)
    return TrialResult(
        Path(path).stem,
        pyshoe_armse(est, gt, 2),
        pyshoe_armse(est, gt, 3),
        float(te[0]) if te is not None else float("nan"),
        pyshoe_armse(dd_a, gt_a, 2),
        dist,
        loop,
        rec.imu.duration,
        float(res.stance.mean()),
        opt,
        fwd,
    )

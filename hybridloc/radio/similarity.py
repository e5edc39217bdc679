"""Fingerprint similarity (the ingredient of loop closure): plain measures and a learned probability.

* :func:`cosine_shifted`: cosine of the two readings vectors over the union of transmitters, each
  reading shifted by -MISSING_DBM so that "not heard" is 0 and stronger is larger.
* :func:`jaccard`: |A & B| / |A | B| of the transmitter sets.
* :func:`mean_abs_diff`: mean |r_a - r_b| over common transmitters, dB (inf with none in common).
* :class:`ProximityModel`: logistic regression (scikit-learn) from those features to the probability
  that two scans were taken within ``radius`` metres of each other, fitted on labelled pairs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from sklearn.linear_model import LogisticRegression

from ..types import RfScan
from .locate import MISSING_DBM
from .survey import LabelledScan


def cosine_shifted(a: RfScan, b: RfScan) -> float:
    keys = set(a.rssi_dbm) | set(b.rssi_dbm)
    if not keys:
        return 0.0
    va = np.array([a.rssi_dbm.get(k, MISSING_DBM) - MISSING_DBM for k in keys])
    vb = np.array([b.rssi_dbm.get(k, MISSING_DBM) - MISSING_DBM for k in keys])
    den = float(np.linalg.norm(va) * np.linalg.norm(vb))
    return float(va @ vb) / den if den > 0 else 0.0


def jaccard(a: RfScan, b: RfScan) -> float:
    A, B = set(a.rssi_dbm), set(b.rssi_dbm)
    u = len(A | B)
    return len(A & B) / u if u else 0.0


def mean_abs_diff(a: RfScan, b: RfScan) -> float:
    common = set(a.rssi_dbm) & set(b.rssi_dbm)
    if not common:
        return math.inf
    return float(np.mean([abs(a.rssi_dbm[k] - b.rssi_dbm[k]) for k in common]))


def pair_features(a: RfScan, b: RfScan) -> np.ndarray:
    mad = mean_abs_diff(a, b)
    n_common = len(set(a.rssi_dbm) & set(b.rssi_dbm))
    return np.array([cosine_shifted(a, b), jaccard(a, b), min(mad, 40.0) / 40.0, math.log1p(n_common)])


@dataclass
class ProximityModel:
    """P(distance between two scans' positions < radius | their fingerprints)."""

    radius: float
    clf: LogisticRegression

    @classmethod
    def fit(cls, labelled: list[LabelledScan], radius: float = 5.0, n_pairs: int = 20000, rng: np.random.Generator | None = None) -> ProximityModel:
        """Fit on random pairs of labelled scans on the same floor, half of them drawn near each other."""
        rng = rng or np.random.default_rng(0)
        if len(labelled) < 10:
            raise ValueError("need at least 10 labelled scans to learn a proximity model")
        pos = np.array([ls.pos_enu for ls in labelled])
        floors = np.array([ls.floor or "" for ls in labelled])
        X, y = [], []
        n = len(labelled)
        from scipy.spatial import cKDTree

        tree = cKDTree(pos)
        for _ in range(n_pairs):
            i = int(rng.integers(n))
            if rng.random() < 0.5:
                near = tree.query_ball_point(pos[i], 2 * radius)
                j = int(near[int(rng.integers(len(near)))])
            else:
                j = int(rng.integers(n))
            if i == j or floors[i] != floors[j]:
                continue
            X.append(pair_features(labelled[i].scan, labelled[j].scan))
            y.append(float(np.linalg.norm(pos[i] - pos[j])) < radius)
        if len(set(y)) < 2:
            raise ValueError("labelled pairs are all near or all far: cannot learn")
        clf = LogisticRegression(max_iter=1000).fit(np.array(X), np.array(y))
        return cls(radius, clf)

    def probability(self, a: RfScan, b: RfScan) -> float:
        return float(self.clf.predict_proba(pair_features(a, b)[None, :])[0, 1])

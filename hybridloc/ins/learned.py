"""A learned zero-velocity (stance) detector: a small random forest over rate- and mounting-free features.

Why a learned detector. The SHOE statistic alone cannot tell a foot at rest from a foot at the turn of
its swing: at the top of a swing the angular rate passes through zero and the specific force through
1 g for a few tens of milliseconds, and over SHOE's 25 ms window that looks as still as a rolling
stance (the gait-driven set's walks at 250 Hz: stances called mid-swing at 1.8 m/s, the INS losing
0.3 m of height and most of a stride). What separates them is context: the rest lasts, and around
it the signals stay quiet; the swing's pause is a notch in loud surroundings. The adaptive threshold
(:func:`.stance.adaptive_shoe`) encodes one such context by hand, with numbers picked by looking at
the PyShoe trials. Here the context features (the same statistics over windows from 25 ms to 0.4 s,
and the gait's own stance and swing levels) are handed to a classifier, which learns from labelled
trials where the boundary lies (Wagstaff et al. 2020 learned theirs with an LSTM on the same kind of
labels).

Labels. For each PyShoe VICON trial, the stance labels of the best of the authors' detectors at its
per-trial optimal threshold (``zv_<best>_opt``, of SHOE, ARED, AMVD and VICON; MBGTD's one instant
per stance is no stance label): the labelling that gave that trial its least ARMSE.

Features (:func:`stance_features`) use only magnitudes (|a|, |omega|, the SHOE terms), so they do not
depend on how the unit is mounted, and windows in seconds, so they do not depend on the rate.

The shipped model (``hybridloc/data/stance_forest.npz``) is a plain array file: every tree's
``feature``, ``threshold``, ``left``, ``right`` and leaf ``value`` (stance probability), evaluated here in
numpy (:class:`TreeEnsemble`): no pickle, no scikit-learn needed to use it, and the same answer on any
scikit-learn version. scikit-learn trains it (:func:`train_forest`, ``python -m scripts.train_stance_forest``).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.ndimage import maximum_filter1d, median_filter, minimum_filter1d, uniform_filter1d

from ..errors import DataFormatError
from ..units import G0

#: Feature windows, s (25 ms is SHOE's W = 5 samples at 200 Hz).
WINDOWS_S = (0.025, 0.05, 0.1, 0.2, 0.4)
#: The gait context windows, s: the stance level (least SHOE over a stride) and the swing level (most).
GAIT_WINDOW_S = 1.2
#: Noise scales of the SHOE terms (PyShoe's), so log T is comparable with :mod:`.stance`'s.
SIGMA_A = 0.00098
SIGMA_W = 8.7266463e-5

FEATURE_NAMES = tuple(
    [f"logT_{w * 1e3:.0f}ms" for w in WINDOWS_S]
    + [f"logW_{w * 1e3:.0f}ms" for w in WINDOWS_S]
    + [f"logWmax_{w * 1e3:.0f}ms" for w in WINDOWS_S[1:]]
    + [f"logAdev_{w * 1e3:.0f}ms" for w in WINDOWS_S]
    + [f"logAstd_{w * 1e3:.0f}ms" for w in WINDOWS_S[1:]]
    + ["logT_above_stance_level", "logT_below_swing_level", "stance_to_swing_decades", "logT_above_gait_median"]
)

DEFAULT_MODEL = Path(__file__).resolve().parents[1] / "data" / "stance_forest.npz"


def _win(rate_hz: float, seconds: float) -> int:
    return max(1, int(round(seconds * rate_hz)))


def stance_features(acc: np.ndarray, gyr: np.ndarray, rate_hz: float, g: float = G0) -> np.ndarray:
    """Per-sample features (N, len(FEATURE_NAMES)), float32; NaN samples give finite (loud) values."""
    acc = np.asarray(acc, dtype=float)
    gyr = np.asarray(gyr, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        an = np.linalg.norm(acc, axis=1)
        wn2 = np.sum(gyr**2, axis=1)
        w5 = _win(rate_hz, WINDOWS_S[0])
        a_bar = uniform_filter1d(acc, size=w5, axis=0, mode="nearest")
        u = a_bar / np.linalg.norm(a_bar, axis=1, keepdims=True)
        ta = np.sum((acc - g * u) ** 2, axis=1) / SIGMA_A**2
        tw = wn2 / SIGMA_W**2
        inst = np.nan_to_num(ta + tw, nan=1e14, posinf=1e14)
        wn2 = np.nan_to_num(wn2, nan=1e3, posinf=1e3)
        adev = np.nan_to_num(np.abs(an - g), nan=1e2, posinf=1e2)
        an = np.nan_to_num(an, nan=1e2, posinf=1e2)
    cols = []
    lt = {}
    for w in WINDOWS_S:
        k = _win(rate_hz, w)
        lt[w] = np.log10(np.maximum(uniform_filter1d(inst, size=k, mode="nearest"), 1e-3))
        cols.append(lt[w])
    for w in WINDOWS_S:
        cols.append(0.5 * np.log10(np.maximum(uniform_filter1d(wn2, size=_win(rate_hz, w), mode="nearest"), 1e-12)))
    for w in WINDOWS_S[1:]:
        cols.append(0.5 * np.log10(np.maximum(maximum_filter1d(wn2, size=_win(rate_hz, w), mode="nearest"), 1e-12)))
    for w in WINDOWS_S:
        cols.append(np.log10(np.maximum(uniform_filter1d(adev, size=_win(rate_hz, w), mode="nearest"), 1e-6)))
    for w in WINDOWS_S[1:]:
        k = _win(rate_hz, w)
        m = uniform_filter1d(an, size=k, mode="nearest")
        v = uniform_filter1d(an * an, size=k, mode="nearest") - m * m
        cols.append(0.5 * np.log10(np.maximum(v, 1e-12)))
    base = lt[WINDOWS_S[0]]
    n = _win(rate_hz, GAIT_WINDOW_S) | 1
    lo = minimum_filter1d(base, size=n, mode="nearest")
    hi = maximum_filter1d(base, size=n, mode="nearest")
    step = max(1, _win(rate_hz, 0.05))
    k = max(1, int(round(4.0 / 0.05)) | 1)
    med = np.repeat(median_filter(base[::step], size=k, mode="nearest"), step)[: len(base)]
    cols += [base - lo, hi - base, hi - lo, base - med]
    return np.column_stack(cols).astype(np.float32)


@dataclass(frozen=True, eq=False)
class TreeEnsemble:
    """Binary decision trees stored flat: node arrays of all trees back to back, ``roots`` their first
    nodes. A leaf has ``left == -1``; its ``value`` is the stance probability. Prediction = the mean
    leaf value over the trees."""

    feature: np.ndarray  # (M,) int32, the feature tested at each node
    threshold: np.ndarray  # (M,) float32: go left when x[feature] <= threshold
    left: np.ndarray  # (M,) int32 absolute node index, -1 at a leaf
    right: np.ndarray  # (M,) int32
    value: np.ndarray  # (M,) float32: stance probability at a leaf
    roots: np.ndarray  # (T,) int32
    feature_names: tuple[str, ...]
    meta: dict

    def predict_proba(self, X: np.ndarray) -> np.ndarray:
        X = np.asarray(X, dtype=np.float32)
        if X.ndim != 2 or X.shape[1] != len(self.feature_names):
            raise ValueError(f"features {X.shape}, the model wants (N, {len(self.feature_names)})")
        rows = np.arange(len(X))
        out = np.zeros(len(X))
        for r in self.roots:
            node = np.full(len(X), r, dtype=np.int64)
            while True:
                inner = self.left[node] >= 0
                if not inner.any():
                    break
                ni = node[inner]
                go_left = X[rows[inner], self.feature[ni]] <= self.threshold[ni]
                node[inner] = np.where(go_left, self.left[ni], self.right[ni])
            out += self.value[node]
        return out / len(self.roots)

    def save(self, path: str | os.PathLike) -> None:
        np.savez_compressed(
            path,
            feature=self.feature,
            threshold=self.threshold,
            left=self.left,
            right=self.right,
            value=self.value,
            roots=self.roots,
            feature_names=np.array(self.feature_names),
            meta_keys=np.array(list(self.meta.keys())),
            meta_values=np.array([str(v) for v in self.meta.values()]),
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> TreeEnsemble:
        path = str(path)
        try:
            z = np.load(path, allow_pickle=False)
            names = tuple(str(s) for s in z["feature_names"])
            meta = dict(zip((str(k) for k in z["meta_keys"]), (str(v) for v in z["meta_values"])))
            m = cls(
                z["feature"].astype(np.int32),
                z["threshold"].astype(np.float32),
                z["left"].astype(np.int32),
                z["right"].astype(np.int32),
                z["value"].astype(np.float32),
                z["roots"].astype(np.int32),
                names,
                meta,
            )
        except (OSError, KeyError, ValueError) as exc:
            raise DataFormatError(path, None, f"not a stance model file: {exc}") from exc
        if names != FEATURE_NAMES:
            raise DataFormatError(path, None, "the model's features are not this version's (retrain it: python -m scripts.train_stance_forest)")
        return m

    @classmethod
    def from_sklearn(cls, forest, feature_names: tuple[str, ...], meta: dict) -> TreeEnsemble:
        feats, thr, left, right, val, roots = [], [], [], [], [], []
        off = 0
        for est in forest.estimators_:
            t = est.tree_
            n = t.node_count
            leaf = t.children_left < 0
            p = t.value[:, 0, :]
            p = p / p.sum(axis=1, keepdims=True)
            k1 = list(forest.classes_).index(1) if 1 in list(forest.classes_) else list(forest.classes_).index(True)
            feats.append(np.where(leaf, 0, t.feature).astype(np.int32))
            thr.append(np.where(leaf, 0.0, t.threshold).astype(np.float32))
            left.append(np.where(leaf, -1, t.children_left + off).astype(np.int32))
            right.append(np.where(leaf, -1, t.children_right + off).astype(np.int32))
            val.append(p[:, k1].astype(np.float32))
            roots.append(off)
            off += n
        return cls(
            np.concatenate(feats),
            np.concatenate(thr),
            np.concatenate(left),
            np.concatenate(right),
            np.concatenate(val),
            np.array(roots, np.int32),
            feature_names,
            meta,
        )


@lru_cache(maxsize=4)
def load_model(path: str | None = None) -> TreeEnsemble:
    p = Path(path) if path else DEFAULT_MODEL
    if not p.is_file():
        raise DataFormatError(str(p), None, "stance model file missing (python -m scripts.train_stance_forest writes it)")
    return TreeEnsemble.load(p)


#: Stance where the forest's probability is at least this.
PROBABILITY = 0.5


def learned_stance(
    acc: np.ndarray, gyr: np.ndarray, rate_hz: float, g: float = G0, model: TreeEnsemble | None = None, probability: float = PROBABILITY
) -> tuple[np.ndarray, np.ndarray]:
    """(stance probability, stance mask) per sample from the forest (default: the shipped model)."""
    m = model or load_model()
    p = m.predict_proba(stance_features(acc, gyr, rate_hz, g))
    return p, p >= probability


# ------------------------------------------------------------------ training (needs scikit-learn)
#: Detectors whose per-trial optimal labels can teach stance (MBGTD marks one instant per stance).
LABEL_DETECTORS = ("shoe", "ared", "amvd", "vicon")


def trial_labels(extras: dict) -> np.ndarray | None:
    """The stance labels of a PyShoe trial's best detector at its optimal threshold (module docstring)."""
    te = extras.get("trial_error")
    names = extras.get("trial_error_detectors")
    if te is None or names is None:
        return None
    best = min((d for d in LABEL_DETECTORS if d in names), key=lambda d: te[list(names).index(d)])
    return extras.get(f"zv_{best}_opt")


@dataclass
class ForestSettings:
    n_trees: int = 24
    max_depth: int = 12
    min_samples_leaf: int = 20
    subsample: int = 4  # every n-th sample of each trial enters training (neighbours are near copies)
    seed: int = 24


def train_forest(trials: list[tuple[np.ndarray, np.ndarray]], settings: ForestSettings | None = None, meta: dict | None = None) -> TreeEnsemble:
    """A forest from (features (N, F), labels (N,)) pairs, one per trial; each trial weighs the same."""
    from sklearn.ensemble import RandomForestClassifier

    s = settings or ForestSettings()
    X = np.concatenate([f[:: s.subsample] for f, _ in trials])
    y = np.concatenate([lab[:: s.subsample] for _, lab in trials]).astype(np.int8)
    w = np.concatenate([np.full(len(lab[:: s.subsample]), 1.0 / max(1, len(lab[:: s.subsample]))) for _, lab in trials])
    rf = RandomForestClassifier(
        n_estimators=s.n_trees, max_depth=s.max_depth, min_samples_leaf=s.min_samples_leaf, random_state=s.seed, n_jobs=1, class_weight=None
    )
    rf.fit(X, y, sample_weight=w * len(trials))
    info = {"n_trees": s.n_trees, "max_depth": s.max_depth, "min_samples_leaf": s.min_samples_leaf, "subsample": s.subsample, "seed": s.seed}
    info.update(meta or {})
    return TreeEnsemble.from_sklearn(rf, FEATURE_NAMES, info)


def _check_probability(p: float) -> float:
    if not (0.0 < p < 1.0 and math.isfinite(p)):
        raise ValueError("probability must lie in (0, 1)")
    return p

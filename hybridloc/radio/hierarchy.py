"""Building, then floor, then position from one fingerprint neighbour list, with settings chosen by
cross-validation grouped by device (UJIIndoorLoc's validation file was recorded by other phones).

Everything here works on dense fingerprint matrices (n, m) in dBm with :data:`~.locate.MISSING_DBM`
for "not heard", so that a neighbour search done once per representation serves every k:

* :func:`offset_free`: each scan shifted so the mean of its ``top_n`` strongest readings is
  ``target_dbm`` (removes a phone's unknown RSSI offset).
* :func:`represent`: the non-negative ("positive data") representations compared with Sorensen's
  distance: ``powed`` (Torres-Sospedra et al.'s ((x - min) / -min)^beta) or ``exponential``
  (exp((x - min) / alpha) / exp(-min / alpha)), on raw or offset-free readings.
* :func:`hierarchical_vote`: building = the inverse-distance weighted vote of the ``k_building``
  nearest; floor = the vote of the first ``k_floor`` neighbours in that building; position = the
  weighted mean of the first ``k`` neighbours on that floor.
* :func:`grouped_search`: pick the settings of a grid by leave-one-group-out over the references
  (the groups are phones), scored by the penalised UJIIndoorLoc score.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy import sparse

from .locate import MISSING_DBM, REL_TARGET_DBM, REL_TOP_N, powed, sorensen_neighbours

#: The usual UJIIndoorLoc penalties added to the position error, m (EvAAL / IPIN competitions).
BUILDING_PENALTY_M = 50.0
FLOOR_PENALTY_M = 4.0


def offset_free(X: np.ndarray, top_n: int = REL_TOP_N, target_dbm: float = REL_TARGET_DBM) -> np.ndarray:
    """Readings shifted per scan so that the mean of the ``top_n`` strongest is ``target_dbm``
    (capped at 0 dBm); "not heard" stays :data:`MISSING_DBM`. Same transform as KnnLocator's
    "powed-rel" before the power."""
    heard = X > MISSING_DBM
    top = -np.sort(-np.where(heard, X, -np.inf), axis=1)[:, :top_n]
    ref = np.where(np.isfinite(top), top, np.nan)
    with np.errstate(all="ignore"):
        level = np.nanmean(ref, axis=1) if ref.shape[1] else np.full(len(X), np.nan)
    shift = target_dbm - np.nan_to_num(level, nan=target_dbm)
    return np.where(heard, np.minimum(X + shift[:, None], 0.0), MISSING_DBM)


def exponential(X: np.ndarray, alpha: float = 24.0) -> np.ndarray:
    """exp((x - min) / alpha) / exp(-min / alpha): 1 at 0 dBm, 0 for "not heard" (Torres-Sospedra
    et al.'s exponential representation)."""
    lo = MISSING_DBM
    return np.where(X > lo, np.exp((X - lo) / alpha - (-lo) / alpha), 0.0)


@dataclass(frozen=True)
class Representation:
    """How readings become non-negative fingerprints: ``kind`` "powed" (parameter beta) or
    "exponential" (parameter alpha, dB), on offset-free readings when ``offset_free``."""

    kind: str = "powed"
    param: float = math.e
    offset_free: bool = True

    def __call__(self, X: np.ndarray) -> np.ndarray:
        Y = offset_free(X) if self.offset_free else X
        if self.kind == "powed":
            return powed(Y, self.param)
        if self.kind == "exponential":
            return exponential(Y, self.param)
        raise ValueError(f"unknown representation {self.kind!r}")

    def label(self) -> str:
        p = "e" if self.kind == "powed" and abs(self.param - math.e) < 1e-9 else f"{self.param:g}"
        return f"{self.kind}({p}){'-rel' if self.offset_free else ''}"


@dataclass(frozen=True)
class VoteSettings:
    k: int = 5  # neighbours averaged for the position (on the chosen floor)
    k_floor: int = 5  # neighbours voting for the floor (in the chosen building)
    k_building: int = 5  # neighbours voting for the building
    weight_power: float = 1.0  # votes and averages weighted by distance^-weight_power


def sorensen_knn(R: np.ndarray, Q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(distances, indices) of the k nearest rows of the fingerprints ``R`` for each row of ``Q``
    (Sorensen distance, :func:`~.locate.sorensen_neighbours`)."""
    Rs = sparse.csc_array(R.astype(np.float32))
    return sorensen_neighbours(Rs, R.sum(axis=1, dtype=np.float64), Q.astype(np.float32), k)


def _weighted_vote(codes: np.ndarray, w: np.ndarray, use: np.ndarray, n_codes: int) -> np.ndarray:
    """Per row, the code with the largest sum of ``w`` over the entries with ``use`` (ties: lowest code)."""
    votes = np.zeros((codes.shape[0], n_codes))
    rows = np.broadcast_to(np.arange(codes.shape[0])[:, None], codes.shape)
    np.add.at(votes, (rows[use], codes[use]), w[use])
    return votes.argmax(axis=1)


def hierarchical_vote(
    D: np.ndarray, I: np.ndarray, building: np.ndarray, floor: np.ndarray, pos: np.ndarray, s: VoteSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Building, floor and position of each query from its neighbour list.

    Parameters
    ----------
    D, I : ndarray, shape (n, K)
        Distances and reference indices of each query's K nearest references, nearest first.
    building, floor : ndarray of int, shape (N,)
        The references' building and floor.
    pos : ndarray, shape (N, 2)
        The references' positions, m.
    s : VoteSettings
        k, k_floor, k_building should not exceed K.

    Returns (building (n,), floor (n,), position (n, 2)). The first neighbour is always in the chosen
    building's and floor's candidate set only when it won the vote; a query whose chosen floor holds no
    neighbour within the first K falls back to its nearest neighbour's position.
    """
    n, K = I.shape
    w = 1.0 / np.maximum(D, 1e-9) ** s.weight_power
    rank = np.broadcast_to(np.arange(K), (n, K))
    b_codes, b_inv = np.unique(building, return_inverse=True)
    nb = b_inv[I]
    bb = _weighted_vote(nb, w, rank < s.k_building, len(b_codes))
    in_b = nb == bb[:, None]
    f_codes, f_inv = np.unique(floor, return_inverse=True)
    nf = f_inv[I]
    use_f = in_b & (np.cumsum(in_b, axis=1) <= s.k_floor)
    # a building no neighbour votes for cannot happen: the building vote's winner holds a neighbour
    ff = _weighted_vote(nf, w, use_f, len(f_codes))
    on = in_b & (nf == ff[:, None])
    use_p = on & (np.cumsum(on, axis=1) <= s.k)
    wp = np.where(use_p, w, 0.0)
    tot = wp.sum(axis=1)
    P = np.einsum("nk,nkd->nd", wp, pos[I]) / np.maximum(tot, 1e-300)[:, None]
    none = tot <= 0
    P[none] = pos[I[none, 0]]
    return b_codes[bb], f_codes[ff], P


@dataclass
class Scores:
    """Per-query results against the truth."""

    error_m: np.ndarray  # 2-D position error, m (whatever the floor)
    building_hit: np.ndarray
    floor_hit: np.ndarray  # building and floor right

    @property
    def penalised_m(self) -> np.ndarray:
        return self.error_m + BUILDING_PENALTY_M * ~self.building_hit + FLOOR_PENALTY_M * ~self.floor_hit

    def summary(self, mask: np.ndarray | None = None) -> dict:
        m = np.ones(len(self.error_m), bool) if mask is None else mask
        on = m & self.floor_hit
        return {
            "mean_m": float(self.error_m[on].mean()) if on.any() else float("nan"),  # on the right floor
            "building_hit_pct": 100 * float(self.building_hit[m].mean()),
            "floor_hit_pct": 100 * float(self.floor_hit[m].mean()),
            "penalised_m": float(self.penalised_m[m].mean()),
            "n": int(m.sum()),
        }


def score(bb, ff, P, building, floor, pos) -> Scores:
    bh = bb == building
    return Scores(np.linalg.norm(P - pos, axis=1), bh, bh & (ff == floor))


def vote_grid(ks=(1, 2, 3, 4, 5, 7, 10), k_floors=(3, 5, 10, 20), k_buildings=(3, 5, 10, 20), weight_powers=(1.0, 2.0)) -> list[VoteSettings]:
    return [VoteSettings(*c) for c in itertools.product(ks, k_floors, k_buildings, weight_powers)]


@dataclass
class SearchResult:
    rep: Representation
    vote: VoteSettings
    fitted: float  # the winner's penalised score over the inner held-out queries, m
    table: dict  # (rep label, vote) -> penalised score


def grouped_search(
    X: np.ndarray,
    building: np.ndarray,
    floor: np.ndarray,
    pos: np.ndarray,
    groups: np.ndarray,
    reps: list[Representation],
    votes: list[VoteSettings],
) -> SearchResult:
    """The representation and vote settings with the lowest penalised score when every group's rows
    are located with the other groups' rows as references (leave-one-group-out)."""
    K = max(max(v.k, v.k_floor, v.k_building) for v in votes)
    table: dict = {}
    best = None
    for rep in reps:
        R = rep(X)
        D = np.empty((len(X), K))
        I = np.empty((len(X), K), dtype=np.int64)
        for g in np.unique(groups):
            te, tr = np.flatnonzero(groups == g), np.flatnonzero(groups != g)
            d, i = sorensen_knn(R[tr], R[te], K)
            if d.shape[1] < K:  # fewer references than K: pad with the last one
                d = np.pad(d, ((0, 0), (0, K - d.shape[1])), mode="edge")
                i = np.pad(i, ((0, 0), (0, K - i.shape[1])), mode="edge")
            D[te], I[te] = d, tr[i]
        for v in votes:
            pen = float(score(*hierarchical_vote(D, I, building, floor, pos, v), building, floor, pos).penalised_m.mean())
            table[(rep.label(), v)] = pen
            if best is None or pen < best[0]:
                best = (pen, rep, v)
    assert best is not None
    return SearchResult(best[1], best[2], best[0], table)

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


# --- Nested leave-one-group-out from neighbour lists computed once -------------------------------------
#
# grouped_search recomputes every neighbour search for every held-out group. When the outer loop also
# leaves groups out (the phone-grouped cross-validation), the searches can be done once: each row's
# nearest rows among the *other* groups (:func:`other_group_neighbours`), from which every nested split's
# list is the same list with the outer split's groups removed (:func:`restricted_neighbours`; rows left
# with too short a list are searched again, so the lists are exact). Building and floor are then voted
# from one representation's list and the position averaged from another's, restricted to the chosen
# floor (:func:`position_on_floor`); :func:`split_search` chooses both by leave-one-group-out.


def other_group_neighbours(R: np.ndarray, groups: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray]:
    """(distances, indices), each (n, K), of every row's K nearest rows of ``R`` in other groups
    (Sorensen); short lists (fewer than K rows in the other groups) are padded with index -1, distance inf."""
    n = len(R)
    D = np.full((n, K), np.inf)
    I = np.full((n, K), -1, dtype=np.int64)
    for g in np.unique(groups):
        te, tr = np.flatnonzero(groups == g), np.flatnonzero(groups != g)
        if not len(tr):
            continue
        d, i = sorensen_knn(R[tr], R[te], K)
        D[te, : d.shape[1]], I[te, : d.shape[1]] = d, tr[i]
    return D, I


def restricted_neighbours(
    R: np.ndarray, D: np.ndarray, I: np.ndarray, groups: np.ndarray, rows: np.ndarray, excluded, K: int
) -> tuple[np.ndarray, np.ndarray]:
    """The K nearest references of each of ``rows`` among the rows whose group is neither the row's
    own nor in ``excluded``, from the lists (D, I) of :func:`other_group_neighbours` (which must be
    longer than K). Rows whose list keeps fewer than K entries are searched again. Padded with -1 / inf."""
    excluded = np.asarray(sorted(excluded))
    Dr, Ir = D[rows], I[rows]
    keep = (Ir >= 0) & ~np.isin(groups[np.maximum(Ir, 0)], excluded)
    order = np.argsort(~keep, axis=1, kind="stable")  # kept entries first, in their order
    Dk = np.where(np.take_along_axis(keep, order, 1), np.take_along_axis(Dr, order, 1), np.inf)[:, :K]
    Ik = np.where(np.take_along_axis(keep, order, 1), np.take_along_axis(Ir, order, 1), -1)[:, :K]
    short = keep.sum(axis=1) < K
    if short.any():
        allowed = ~np.isin(groups, excluded)
        for g in np.unique(groups[rows[short]]):
            q = np.flatnonzero(short & (groups[rows] == g))
            ref = np.flatnonzero(allowed & (groups != g))
            Dk[q], Ik[q] = np.inf, -1
            if len(ref):
                d, i = sorensen_knn(R[ref], R[rows[q]], K)
                Dk[q, : d.shape[1]], Ik[q, : d.shape[1]] = d, ref[i]
    return Dk, Ik


@dataclass(frozen=True)
class FloorVote:
    """Building and floor voted from one representation's neighbour list (:func:`hierarchical_vote`)."""

    rep: Representation
    k_floor: int = 10
    k_building: int = 20
    weight_power: float = 1.0


@dataclass(frozen=True)
class PositionVote:
    """Position = the distance^-weight_power weighted mean of the first ``k`` neighbours on the chosen
    building and floor in one representation's neighbour list (:func:`position_on_floor`)."""

    rep: Representation
    k: int = 5
    weight_power: float = 1.0


def vote_floors(D: np.ndarray, I: np.ndarray, building: np.ndarray, floor: np.ndarray, pos: np.ndarray, v: FloorVote):
    """(building, floor) of each query, voted from the padded lists (D, I) (see :func:`hierarchical_vote`)."""
    Ds, Is = _unpadded(D, I)
    bb, ff, _ = hierarchical_vote(Ds, Is, building, floor, pos, VoteSettings(1, v.k_floor, v.k_building, v.weight_power))
    return bb, ff


def _unpadded(D: np.ndarray, I: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Padding (-1, inf) replaced by each row's last real entry (every row must hold one)."""
    pad = I < 0
    if not pad.any():
        return D, I
    last = np.maximum((~pad).sum(axis=1) - 1, 0)
    r = np.arange(len(I))
    return np.where(pad, D[r, last][:, None], D), np.where(pad, I[r, last][:, None], I)


def position_on_floor(
    D: np.ndarray,
    I: np.ndarray,
    bb: np.ndarray,
    ff: np.ndarray,
    building: np.ndarray,
    floor: np.ndarray,
    pos: np.ndarray,
    k: int,
    weight_power: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean position of each query's first ``k`` neighbours in (D, I) that lie on its chosen
    building ``bb`` and floor ``ff``. Returns (positions (n, 2), found (n,) bool); rows with no such
    neighbour are NaN and not found."""
    on, count, near, dist = _on_floor(D, I, bb, ff, building, floor, pos)
    return _weighted_mean(on, count, near, 1.0 / dist**weight_power, k)


def _on_floor(D, I, bb, ff, building, floor, pos):
    """What :func:`position_on_floor` needs whatever its k and weight power: (each neighbour on the
    chosen building and floor (n, K), their running count, the neighbours' positions (n, K, 2), the
    distances with padding at 1 and floored at 1e-9 (n, K))."""
    valid = I >= 0
    Ii = np.maximum(I, 0)
    on = valid & (building[Ii] == bb[:, None]) & (floor[Ii] == ff[:, None])
    return on, np.cumsum(on, axis=1), pos[Ii], np.maximum(np.where(valid, D, 1.0), 1e-9)


def _weighted_mean(on, count, near, inv, k):
    """The ``inv``-weighted mean of the first ``k`` neighbours ``on`` the floor: (positions, found)."""
    w = np.where(on & (count <= k), inv, 0.0)
    tot = w.sum(axis=1)
    found = tot > 0
    P = np.full((len(on), 2), np.nan)
    P[found] = np.einsum("nk,nkd->nd", w[found], near[found]) / tot[found, None]
    return P, found


def _fall_back(P, found, floor_list, bb, ff, building, floor, pos, k, weight_power) -> np.ndarray:
    """:func:`split_vote`'s fallbacks, row by row: a row whose position list held no neighbour on the
    chosen floor takes the floor list's weighted mean there, else the floor list's nearest neighbour."""
    miss = np.flatnonzero(~found)
    if len(miss):
        Df, If = floor_list
        P[miss], found2 = position_on_floor(Df[miss], If[miss], bb[miss], ff[miss], building, floor, pos, k, weight_power)
        rest = miss[~found2]
        P[rest] = pos[np.maximum(If[rest, 0], 0)]
    return P


def split_vote(
    lists: dict,
    fv: FloorVote,
    pv: PositionVote,
    building: np.ndarray,
    floor: np.ndarray,
    pos: np.ndarray,
    floors_voted: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Building and floor from ``lists[fv.rep]`` (or ``floors_voted``, the same computed before),
    position from ``lists[pv.rep]`` on that floor; when the position list holds no neighbour on the
    chosen floor, the floor list's (else the floor list's nearest neighbour)."""
    Df, If = lists[fv.rep]
    bb, ff = floors_voted if floors_voted is not None else vote_floors(Df, If, building, floor, pos, fv)
    P, found = position_on_floor(*lists[pv.rep], bb, ff, building, floor, pos, pv.k, pv.weight_power)
    return bb, ff, _fall_back(P, found, (Df, If), bb, ff, building, floor, pos, pv.k, pv.weight_power)


def floor_grid(reps, k_floors=(5, 10, 20), k_buildings=(5, 20), weight_powers=(1.0, 2.0)) -> list[FloorVote]:
    return [FloorVote(r, *c) for r in reps for c in itertools.product(k_floors, k_buildings, weight_powers)]


#: The position vote's candidates. The weight power reaches 16: with the grid ending at 4 (and k at
#: 15), leaving one phone out chose 4 in all 16 splits, the grid's edge. Sorensen distances between
#: near and far neighbours differ by a few tenths, so only a steep weight lets the nearest few
#: dominate a list of 10-30. With the powers to 16 and k to 30, the splits choose 8-16 and k 5-30
#: (UJIIndoorLoc held out by phone: 6.17 -> 5.96 m in the 4 phone folds, 6.28 -> 6.24 m leaving
#: one phone out); powers to 32 give the same (6.24 m), a plateau.
POSITION_KS = (1, 2, 3, 5, 7, 10, 15, 20, 30)
POSITION_WEIGHT_POWERS = (1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0)


def position_grid(reps, ks=POSITION_KS, weight_powers=POSITION_WEIGHT_POWERS) -> list[PositionVote]:
    return [PositionVote(r, *c) for r in reps for c in itertools.product(ks, weight_powers)]


@dataclass
class SplitChoice:
    floor: FloorVote
    position: PositionVote
    fitted: float  # penalised score of the choice over the inner held-out queries, m


def split_search(
    lists: dict,
    rows: np.ndarray,
    building: np.ndarray,
    floor: np.ndarray,
    pos: np.ndarray,
    floors: list[FloorVote],
    positions: list[PositionVote],
    default_k: int = 5,
) -> SplitChoice:
    """Leave-one-group-out choice of a :class:`FloorVote` and a :class:`PositionVote`.

    ``lists`` maps each representation to (D, I) for the queries ``rows`` (indices into ``building``,
    ``floor``, ``pos``), each query's references being drawn from the other groups only (so the
    scores are held out). First the building/floor vote with the lowest mean penalised score (the
    position being the floor list's ``default_k`` neighbours on the floor, weight power 1), then, on
    the floors it chose, the position vote with the lowest mean penalised score.
    """
    b, f, p = building[rows], floor[rows], pos[rows]
    best_f = None
    for fv in floors:
        pv = PositionVote(fv.rep, default_k, 1.0)
        pen = float(score(*split_vote(lists, fv, pv, building, floor, pos), b, f, p).penalised_m.mean())
        if best_f is None or pen < best_f[0]:
            best_f = (pen, fv)
    assert best_f is not None
    fv = best_f[1]
    voted = vote_floors(*lists[fv.rep], building, floor, pos, fv)
    pens = _position_penalties(lists, fv, positions, voted, building, floor, pos, b, f, p)
    best_p = None
    for pv in positions:  # in the grid's order: the first of equal scores wins
        if best_p is None or pens[pv] < best_p[0]:
            best_p = (pens[pv], pv)
    assert best_p is not None
    return SplitChoice(fv, best_p[1], best_p[0])


def _position_penalties(lists, fv, positions, voted, building, floor, pos, b, f, p) -> dict:
    """Each position vote's mean penalised score, the same numbers as scoring
    ``split_vote(lists, fv, pv, ..., voted)`` one candidate at a time, with what the candidates share
    computed once: per representation :func:`_on_floor`, per weight power the weights."""
    bb, ff = voted
    out: dict = {}
    for rep in dict.fromkeys(pv.rep for pv in positions):
        on, count, near, dist = _on_floor(*lists[rep], bb, ff, building, floor, pos)
        mine = [pv for pv in positions if pv.rep == rep]
        for wp in dict.fromkeys(pv.weight_power for pv in mine):
            inv = 1.0 / dist**wp
            for pv in (q for q in mine if q.weight_power == wp):
                P = _fall_back(*_weighted_mean(on, count, near, inv, pv.k), lists[fv.rep], bb, ff, building, floor, pos, pv.k, wp)
                out[pv] = float(score(bb, ff, P, b, f, p).penalised_m.mean())
    return out

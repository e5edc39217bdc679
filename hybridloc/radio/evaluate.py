"""Fingerprint evaluation (``hybridloc eval fingerprint``).

* Indoor Location Competition site: every trace is labelled as a passive survey (PDR bridged between
  its waypoints); traces are split into ``folds`` groups; each group is located with a radio map built
  from all the others (all floors), and every held-out scan between two waypoints is scored against the
  waypoints interpolated to its time.
* UJIIndoorLoc: cross-validation grouped by user (every user's rows are located with the other users'
  rows as references), with a plain 3-NN on raw dBm measured in the same run; grouped by phone (the
  validation file's phones are not in the training file) with nested leave-one-phone-out choice of the
  settings, for the joint building/floor/position vote (:func:`evaluate_uji_phone`) and for the floor
  and position votes chosen apart (:func:`evaluate_uji_phone_split`, also leaving one phone out at a
  time); and, when the validation file (validationData.csv) lies beside the training one or is named,
  the standard split (every training row a reference, every validation row a query), also answered
  with the split votes chosen on the whole training file.
* Indoor Location Competition routes held out whole: each scan's error beside the distance from its
  truth to the nearest reference label on its floor (what limits it: the map's coverage), in route
  folds (a quarter of the routes out of the map at once) and leaving one route out (every other walk
  in the map, the kNN's settings chosen per floor on the other floors; a plain 3-NN beside it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.msft import find_ilc_traces, read_ilc_site, read_ilc_trace
from ..types import RfScan
from .locate import KnnLocator, LocateResult, ProbabilisticLocator
from .radiomap import BuildParams, build_radio_map
from .survey import LabelledScan, label_trace


@dataclass
class TraceData:
    name: str
    floor: str
    labelled: list[LabelledScan]
    wp_t: np.ndarray
    wp_xy: np.ndarray
    scans: list[RfScan]


def load_site_surveys(site_dir: str | Path, every: int = 1, technology: str = "wifi") -> list[TraceData]:
    out = []
    for p in find_ilc_traces(site_dir)[::every]:
        tr = read_ilc_trace(p)
        if tr.imu is None or len(tr.waypoints) < 2:
            continue
        scans = [s for s in tr.scans if s.technology.value == technology]
        lab = label_trace(tr, source=p.name)
        out.append(TraceData(p.name, tr.floor or "", lab, tr.waypoints.t, tr.waypoints.pos_enu, scans))
    return out


@dataclass
class FingerprintScore:
    errors: list[float] = field(default_factory=list)
    floor_hits: list[bool] = field(default_factory=list)
    region_hits: list[bool] = field(default_factory=list)
    region_areas: list[float] = field(default_factory=list)
    no_fix: int = 0
    by_trace: dict[str, list[float]] = field(default_factory=dict)  # the errors of each test trace's scans
    cover_m: list[float] = field(default_factory=list)  # per entry of errors: the truth's distance to the nearest reference label on its floor, m

    def add(self, res: LocateResult, truth_xy: np.ndarray, truth_floor: str, cover_m: float = float("nan")) -> None:
        if res.fix is None:
            self.no_fix += 1
            return
        self.cover_m.append(cover_m)
        self.floor_hits.append(res.fix.floor == truth_floor)
        self.errors.append(float(np.linalg.norm(res.fix.pos_enu[:2] - truth_xy)) if res.fix.floor == truth_floor else float("nan"))
        if res.region is not None:
            self.region_hits.append(res.region.floor == truth_floor and res.region.contains(truth_xy))
            self.region_areas.append(res.region.area_m2)


#: Two walks follow the same route when each one's waypoints lie this close (mean, m) to the other's.
SAME_ROUTE_M = 1.0


def route_groups(traces: list, tol_m: float = SAME_ROUTE_M) -> np.ndarray:
    """Group id per trace (anything with ``floor`` and ``wp_xy``, the waypoints (N, 2) m): walks of
    the same route share one (same floor; each walk's waypoints within ``tol_m``, on average, of the
    other's nearest waypoint, either way). Indoor Location Competition surveyors walked some planned
    routes more than once, minutes apart, with the very same marks; a fold that holds out one walk of
    such a route while its repeat stays in the map scores a path the map has already seen walked."""
    n = len(traces)
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    centre = [t.wp_xy.mean(axis=0) if len(t.wp_xy) else np.zeros(2) for t in traces]
    for i in range(n):
        for j in range(i + 1, n):
            a, b = traces[i].wp_xy, traces[j].wp_xy
            if traces[i].floor != traces[j].floor or not len(a) or not len(b) or np.hypot(*(centre[i] - centre[j])) > 10 * tol_m:
                continue
            d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
            if max(d.min(axis=1).mean(), d.min(axis=0).mean()) < tol_m:
                parent[root(i)] = root(j)
    roots = [root(i) for i in range(n)]
    ids = {r: k for k, r in enumerate(dict.fromkeys(roots))}
    return np.array([ids[r] for r in roots], dtype=int)


def route_folds(traces: list[TraceData], folds: int, rng: np.random.Generator) -> np.ndarray:
    """Fold per trace with every route's walks in one fold (routes dealt to folds in random order)."""
    g = route_groups(traces)
    order = rng.permutation(int(g.max()) + 1 if len(g) else 0)
    return order[g] % folds


def _trace_truth(t: TraceData) -> tuple[list[RfScan], np.ndarray]:
    """The scans of trace ``t`` between its first and last waypoints, and the waypoints interpolated to
    each scan's time (N, 2) m: what a scan is scored against."""
    scans = [s for s in t.scans if t.wp_t[0] <= s.t <= t.wp_t[-1]]
    ts = [s.t for s in scans]
    return scans, np.column_stack([np.interp(ts, t.wp_t, t.wp_xy[:, 0]), np.interp(ts, t.wp_t, t.wp_xy[:, 1])]).reshape(-1, 2)


def evaluate_ilc(
    traces: list[TraceData],
    folds: int = 4,
    method: str = "prob",
    params: BuildParams | None = None,
    plan=None,
    fold_of: np.ndarray | None = None,
    **loc_kw,
) -> FingerprintScore:
    """Leave-traces-out: trace i is in fold ``fold_of[i]`` (default i mod ``folds``: walks recorded
    one after the other land in different folds)."""
    from scipy.spatial import cKDTree

    score = FingerprintScore()
    fold_of = np.arange(len(traces)) % folds if fold_of is None else np.asarray(fold_of)
    for f in range(folds):
        train = [t for i, t in enumerate(traces) if fold_of[i] != f]
        test = [t for i, t in enumerate(traces) if fold_of[i] == f]
        refs = [ls for t in train for ls in t.labelled]
        label_xy: dict[str | None, list] = {}
        for ls in refs:
            label_xy.setdefault(ls.floor, []).append(ls.pos_enu[:2])
        trees = {fl: cKDTree(np.array(v)) for fl, v in label_xy.items()}
        if method == "prob":
            loc = ProbabilisticLocator(build_radio_map(refs, plan=plan, params=params), **loc_kw)
        else:
            loc = KnnLocator(refs, **loc_kw)
        for t in test:
            scans, truth = _trace_truth(t)
            if not scans:
                continue
            results = [loc.locate(s) for s in scans] if method == "prob" else loc.locate_many(scans)
            n0 = len(score.errors)
            cover = trees[t.floor].query(truth)[0] if t.floor in trees else np.full(len(truth), np.inf)
            for res, xy, c in zip(results, truth, cover):
                score.add(res, xy, t.floor, float(c))
            score.by_trace[t.name] = score.errors[n0:]
    return score


#: The weighted kNN's settings a leave-one-route-out evaluation chooses among, per floor on the other
#: floors: (k, max_age_s) - the neighbours, and how old a cached reading may be at scan time, s.
LORO_SETTINGS: tuple[tuple[int, float], ...] = tuple((k, a) for a in (4.0, 8.0, 16.0) for k in (3, 4, 5, 7, 9))


@dataclass
class RoutesLeftOut:
    """Leave one route out: each route's walks (:func:`route_groups`) located with every other walk of
    the site in the map, so no repeat of the route is in it and the rest of the building is. The weighted
    kNN's settings are chosen for each floor on the other floors' scans (leave one floor out), and the
    plain 3-NN (Euclidean, raw dBm) of the literature is measured on the same scans."""

    n_routes: int
    settings: tuple[tuple[int, float], ...]
    #: every candidate setting's mean error on the right floor over all floors, m (what fitting on the
    #: scored scans themselves would pick from)
    fitted_mean_m: dict[tuple[int, float], float]
    chosen: dict[str, tuple[int, float]]  # floor -> the setting chosen on the other floors
    held_out: FingerprintScore  # each scan answered with its floor's chosen setting
    plain: FingerprintScore
    floor_mean_m: dict[str, tuple[float, float]]  # floor -> (held out, plain) mean on the right floor, m


def _right_floor_errors(results: list[LocateResult], truth_floor: np.ndarray, truth_xy: np.ndarray) -> np.ndarray:
    """Horizontal error of each answer, m; NaN where it names another floor or has no fix."""
    return np.array(
        [
            float(np.linalg.norm(r.fix.pos_enu[:2] - xy)) if r.fix is not None and r.fix.floor == fl else np.nan
            for r, fl, xy in zip(results, truth_floor, truth_xy)
        ],
        dtype=float,
    )


def _right_floor_mean(errors: np.ndarray, mask: np.ndarray) -> float:
    """Mean of the finite ``errors`` in ``mask`` (:func:`_right_floor_errors`), m; inf when there are none."""
    e = errors[mask]
    e = e[np.isfinite(e)]
    return float(np.mean(e)) if e.size else math.inf


def evaluate_ilc_loro(traces: list[TraceData], settings: tuple[tuple[int, float], ...] = LORO_SETTINGS) -> RoutesLeftOut:
    """Leave one route out (:class:`RoutesLeftOut`). One locator per reading age is built over every
    reference once and sliced for each route (:meth:`KnnLocator.subset`: the answers of a fresh build
    without the route's walks)."""
    from scipy.spatial import cKDTree

    if not settings:
        raise ValueError("leave one route out needs at least one kNN setting")
    groups = route_groups(traces)
    refs = [ls for t in traces for ls in t.labelled]
    if not refs:
        raise ValueError("leave one route out needs labelled scans")
    owner = np.concatenate([np.full(len(t.labelled), g) for t, g in zip(traces, groups)])
    ages = list(dict.fromkeys(a for _, a in settings))
    full = {a: KnnLocator(refs, k=max(k for k, b in settings if b == a), max_age_s=a) for a in ages}
    full_plain = KnnLocator(refs, k=3, representation="raw", metric="euclidean")
    ref_xy = np.array([r.pos_enu[:2] for r in refs])
    ref_floor = np.array([r.floor for r in refs])
    answers: dict[tuple[int, float], list[LocateResult]] = {s: [] for s in settings}
    plain: list[LocateResult] = []
    truth_xy, truth_floor, cover = [], [], []
    n_routes = int(groups.max()) + 1 if len(groups) else 0
    for r in range(n_routes):
        keep = owner != r
        test = [t for t, g in zip(traces, groups) if g == r]
        if not keep.any():
            continue  # the site's only route: no map left to locate it with
        subs = {a: full[a].subset(keep) for a in ages}
        sub_plain = full_plain.subset(keep)
        for t in test:
            scans, xy = _trace_truth(t)
            if not scans:
                continue
            on = keep & (ref_floor == t.floor)
            cover.extend(cKDTree(ref_xy[on]).query(xy)[0] if on.any() else np.full(len(xy), np.inf))
            truth_xy.extend(xy)
            truth_floor.extend([t.floor] * len(scans))
            for k, a in settings:
                answers[(k, a)].extend(subs[a].with_k(k).locate_many(scans, regions=False))
            plain.extend(sub_plain.locate_many(scans, regions=False))
    txy, tfl = np.array(truth_xy).reshape(-1, 2), np.array(truth_floor)
    errors = {s: _right_floor_errors(answers[s], tfl, txy) for s in settings}  # once per setting
    everywhere = np.ones(len(tfl), bool)
    fitted = {s: _right_floor_mean(errors[s], everywhere) for s in settings}
    # each floor's setting: the lowest mean on the other floors' scans (ties to the earlier candidate)
    chosen = {}
    for fl in dict.fromkeys(tfl.tolist()):
        others = tfl != fl
        chosen[fl] = min(settings, key=lambda s: _right_floor_mean(errors[s], others)) if others.any() else settings[0]
    held, pl = FingerprintScore(), FingerprintScore()
    held_answers = [answers[chosen[fl]][i] for i, fl in enumerate(tfl)]
    for res, res_plain, fl, xy, c in zip(held_answers, plain, tfl, txy, cover):
        held.add(res, xy, fl, float(c))
        pl.add(res_plain, xy, fl, float(c))
    held_errors = np.array([errors[chosen[fl]][i] for i, fl in enumerate(tfl)], dtype=float)
    plain_errors = _right_floor_errors(plain, tfl, txy)
    by_floor = {fl: (_right_floor_mean(held_errors, tfl == fl), _right_floor_mean(plain_errors, tfl == fl)) for fl in chosen}
    return RoutesLeftOut(n_routes, tuple(settings), fitted, chosen, held, pl, by_floor)


#: A UJIIndoorLoc test scan is "inside the map" when another user's reference on its floor lies this close, m.
UJI_COVERED_M = 5.0


#: The two kNN answers UJIIndoorLoc is scored with: ours and the plain one of the literature.
UJI_METHODS = (("ours", "weighted 5-NN, Sorensen, powed-rel"), ("plain", "plain 3-NN, Euclidean, raw dBm"))


def _uji_labelled(path: str) -> tuple[list[LabelledScan], np.ndarray]:
    """The rows of a UJIIndoorLoc file that heard something, as labelled scans, and their users."""
    from ..io.uji import read_uji
    from .sources import uji_floor_name

    d = read_uji(path)
    rows = np.flatnonzero(np.isfinite(d.rssi_dbm).any(axis=1))
    return [LabelledScan(d.scan(r), d.pos[r].copy(), 1.0, uji_floor_name(d.building[r], d.floor[r])) for r in rows], d.user[rows]


def _uji_locators(refs: list[LabelledScan], k: int) -> dict[str, KnnLocator]:
    """The locators of :data:`UJI_METHODS` over ``refs``."""
    return {"ours": KnnLocator(refs, k=k), "plain": KnnLocator(refs, k=3, representation="raw", metric="euclidean")}


def _uji_score(loc: KnnLocator, test: list[LabelledScan]) -> tuple[list[float], list[bool], list[bool]]:
    """Per query: 2-D error (NaN on a wrong floor), floor hit, building hit (floor names are ``b<B>_f<F>``)."""
    e, fh, bh = [], [], []
    for t, r in zip(test, loc.locate_many([t.scan for t in test])):
        on_floor = r.fix is not None and r.fix.floor == t.floor
        bh.append(r.fix is not None and r.fix.floor.split("_")[0] == t.floor.split("_")[0])
        fh.append(on_floor)
        e.append(float(np.linalg.norm(r.fix.pos_enu - t.pos_enu)) if on_floor else float("nan"))
    return e, fh, bh


def evaluate_uji(path: str, k: int = 5) -> dict:
    """Grouped-by-user cross-validation of weighted kNN (Sorensen on powed-rel) against a plain 3-NN
    on raw dBm (Euclidean).

    Leaving a user out also leaves out the places only that user walked (user 3 alone covered one
    floor of building 2): 9 % of the scans lie more than ``UJI_COVERED_M`` from any other user's
    reference on their floor, where no fingerprint method can answer well. The standard validation
    split (not shipped here) was taken inside the training set's coverage, so the scores are also
    reported on the covered scans, the nearer proxy for it.
    """
    from scipy.spatial import cKDTree

    labelled, users = _uji_labelled(path)
    res = {name: ([], [], []) for name, _ in UJI_METHODS}
    covered = []
    for u in np.unique(users):
        refs = [ls for ls, uu in zip(labelled, users) if uu != u]
        test = [ls for ls, uu in zip(labelled, users) if uu == u]
        by_floor: dict[str, list] = {}
        for r in refs:
            by_floor.setdefault(r.floor, []).append(r.pos_enu[:2])
        trees = {f: cKDTree(np.array(v)) for f, v in by_floor.items()}
        covered += [t.floor in trees and trees[t.floor].query(t.pos_enu[:2])[0] <= UJI_COVERED_M for t in test]
        for name, loc in _uji_locators(refs, k).items():
            for acc, part in zip(res[name], _uji_score(loc, test)):
                acc += part
    cov = np.array(covered, bool)
    out: dict = {"covered_share": float(cov.mean())}
    for n, v in res.items():
        e, fh, bh = np.array(v[0]), np.array(v[1], bool), np.array(v[2], bool)
        out[n] = {
            sub: {"errors": e[m], "floor": float(fh[m].mean()), "building": float(bh[m].mean())}
            for sub, m in (("all", np.ones(len(e), bool)), ("covered", cov))
        }
    return out


#: Outer folds of the phone-grouped UJIIndoorLoc evaluation (phones dealt to folds by sklearn's GroupKFold).
UJI_PHONE_FOLDS = 4

#: The representations the phone-grouped search chooses among (the vote settings: hierarchy.vote_grid).
UJI_REPS = (
    ("powed", math.e, True),
    ("powed", 2.0, True),
    ("exponential", 24.0, True),
    ("powed", math.e, False),
)


def _uji_arrays(path: str):
    """(X dBm with MISSING_DBM, position (n, 2), building, floor, phone) of the rows that heard something."""
    return _uji_arrays_waps(path)[1:]


def _uji_arrays_waps(path: str):
    """The access point names (the columns of X), then :func:`_uji_arrays`'s arrays."""
    from ..io.uji import read_uji
    from .locate import MISSING_DBM

    d = read_uji(path)
    rows = np.flatnonzero(np.isfinite(d.rssi_dbm).any(axis=1))
    X = np.where(np.isfinite(d.rssi_dbm[rows]), d.rssi_dbm[rows], MISSING_DBM)
    return d.waps, X, d.pos[rows], d.building[rows], d.floor[rows], d.phone[rows]


def evaluate_uji_phone(path: str, folds: int = UJI_PHONE_FOLDS, votes=None, reps=None) -> dict:
    """Cross-validation grouped by phone, with nested selection of the settings.

    UJIIndoorLoc's validation file was recorded months later by phones the training file does not
    hold, so phones (not users: one phone served three users) are the groups. Outer loop: phones dealt
    to ``folds`` folds (GroupKFold); each fold's rows are located with the other folds' rows as
    references. Inner loop, on the references only: leave-one-phone-out over the grid of
    representations (:data:`UJI_REPS`) x vote settings (:func:`~.hierarchy.vote_grid`), the winner
    being the lowest penalised score (error + 50 m per wrong building + 4 m per wrong floor). The plain
    3-NN (Euclidean on raw dBm, nothing tuned) answers the same outer folds.

    Returns {"ours": Scores, "plain": Scores, "covered": mask, "chosen": [(rep label, VoteSettings,
    fitted penalised m, held-out penalised m), ...] per outer fold}.
    """
    from scipy.spatial import cKDTree
    from sklearn.model_selection import GroupKFold
    from sklearn.neighbors import NearestNeighbors

    from .hierarchy import Representation, VoteSettings, grouped_search, hierarchical_vote, score, sorensen_knn, vote_grid

    X, pos, b, f, ph = _uji_arrays(path)
    votes = votes or vote_grid(ks=(1, 2, 3, 5, 7, 10), k_floors=(5, 10, 20), k_buildings=(5, 20), weight_powers=(1.0, 2.0))
    reps = [Representation(*r) for r in (reps or UJI_REPS)]
    fl = b * 100 + f  # floors are numbered per building
    n = len(X)
    res = {name: (np.zeros(n, int), np.zeros(n, int), np.zeros((n, 2))) for name in ("ours", "plain")}
    covered = np.zeros(n, bool)
    chosen = []
    for tr, te in GroupKFold(n_splits=folds).split(X, groups=ph):
        sr = grouped_search(X[tr], b[tr], fl[tr], pos[tr], ph[tr], reps, votes)
        v = sr.vote
        K = max(v.k, v.k_floor, v.k_building)
        R = sr.rep(X)
        D, I = sorensen_knn(R[tr], R[te], K)
        for name, (D_, I_, s_) in (
            ("ours", (D, I, v)),
            ("plain", (*NearestNeighbors(n_neighbors=3).fit(X[tr]).kneighbors(X[te]), VoteSettings(3, 3, 3))),
        ):
            bb, ff, P = hierarchical_vote(D_, I_, b[tr], fl[tr], pos[tr], s_)
            res[name][0][te], res[name][1][te], res[name][2][te] = bb, ff, P
        held = float(score(res["ours"][0][te], res["ours"][1][te], res["ours"][2][te], b[te], fl[te], pos[te]).penalised_m.mean())
        chosen.append((sr.rep.label(), v, sr.fitted, held))
        for F in np.unique(fl[te]):
            q = te[fl[te] == F]
            r = tr[fl[tr] == F]
            if len(r):
                covered[q] = cKDTree(pos[r]).query(pos[q])[0] <= UJI_COVERED_M
    out: dict = {"covered": covered, "chosen": chosen, "n_phones": len(np.unique(ph)), "folds": folds}
    for name, (bb, ff, P) in res.items():
        out[name] = score(bb, ff, P, b, fl, pos)
    return out


#: Neighbours searched once per UJIIndoorLoc row among the other phones' rows (every nested split's
#: list is cut from it), and kept per query for the split votes.
UJI_SEARCH_K = 100
UJI_LIST_K = 40


def _uji_split_lists(base: dict, ph: np.ndarray, rows: np.ndarray, excluded) -> dict:
    """rep -> (D, I) of ``rows`` among the rows of phones neither their own nor ``excluded``."""
    from .hierarchy import restricted_neighbours

    return {rep: restricted_neighbours(R, D, I, ph, rows, excluded, UJI_LIST_K) for rep, (R, D, I) in base.items()}


def evaluate_uji_phone_split(path: str, folds: int = UJI_PHONE_FOLDS, reps=None, floors=None, positions=None) -> dict:
    """The building/floor vote and the position vote chosen apart (each with its own representation,
    :func:`~.hierarchy.split_search`), held out by phone two ways:

    * ``"kfold"``: the same ``folds`` GroupKFold folds as :func:`evaluate_uji_phone` (a quarter of the
      phones out at once: a floor only those phones walked has no reference left);
    * ``"lopo"``: leave one phone out (every other phone's references in the map, as for the validation
      file, whose phones walked inside the training file's coverage).

    Each outer split's settings are chosen by leave-one-phone-out over its own references only. The
    neighbour searches are done once per representation (:func:`~.hierarchy.other_group_neighbours`);
    each split's lists are cut from them (:func:`~.hierarchy.restricted_neighbours`, exact). The plain
    3-NN (Euclidean, raw dBm) answers the LOPO splits beside it. ``"full"`` is the choice over the
    whole file (leave-one-phone-out over every phone), the one a validation file is answered with.
    """
    from scipy.spatial import cKDTree
    from sklearn.model_selection import GroupKFold
    from sklearn.neighbors import NearestNeighbors

    from .hierarchy import (
        Representation,
        VoteSettings,
        floor_grid,
        hierarchical_vote,
        other_group_neighbours,
        position_grid,
        score,
        split_search,
        split_vote,
    )

    X, pos, b, f, ph = _uji_arrays(path)
    fl = b * 100 + f
    reps = [Representation(*r) for r in (reps or UJI_REPS)]
    floors = floors or floor_grid(reps)
    positions = positions or position_grid(reps)
    base = {}
    for rep in reps:
        R = rep(X)
        base[rep] = (R, *other_group_neighbours(R, ph, UJI_SEARCH_K))
    n = len(X)
    out: dict = {"n_phones": len(np.unique(ph)), "folds": folds}
    phones = np.unique(ph)
    splits = {
        "kfold": list(GroupKFold(n_splits=folds).split(X, groups=ph)),
        "lopo": [(np.flatnonzero(ph != p), np.flatnonzero(ph == p)) for p in phones],
    }
    for name, sp in splits.items():
        bb, ff, P = np.zeros(n, int), np.zeros(n, int), np.zeros((n, 2))
        covered = np.zeros(n, bool)
        chosen = []
        for tr, te in sp:
            out_ph = set(np.unique(ph[te]).tolist())
            c = split_search(_uji_split_lists(base, ph, tr, out_ph), tr, b, fl, pos, floors, positions)
            bb[te], ff[te], P[te] = split_vote(_uji_split_lists(base, ph, te, out_ph), c.floor, c.position, b, fl, pos)
            held = float(score(bb[te], ff[te], P[te], b[te], fl[te], pos[te]).penalised_m.mean())
            chosen.append((sorted(out_ph), c, held))
            for F in np.unique(fl[te]):
                q, r = te[fl[te] == F], tr[fl[tr] == F]
                if len(r):
                    covered[q] = cKDTree(pos[r]).query(pos[q])[0] <= UJI_COVERED_M
        out[name] = {"ours": score(bb, ff, P, b, fl, pos), "covered": covered, "chosen": chosen}
    # the plain 3-NN held out by phone alike
    pb, pf, pP = np.zeros(n, int), np.zeros(n, int), np.zeros((n, 2))
    for tr, te in splits["lopo"]:
        D_, I_ = NearestNeighbors(n_neighbors=3).fit(X[tr]).kneighbors(X[te])
        pb[te], pf[te], pP[te] = hierarchical_vote(D_, tr[I_], b, fl, pos, VoteSettings(3, 3, 3))
    out["lopo"]["plain"] = score(pb, pf, pP, b, fl, pos)
    everyone = np.arange(n)
    out["full"] = split_search(_uji_split_lists(base, ph, everyone, set()), everyone, b, fl, pos, floors, positions)
    return out


def answer_uji_split(train_path: str, test_path: str, choice) -> dict:
    """The validation file's rows answered with ``choice`` (a :class:`~.hierarchy.SplitChoice`, e.g.
    :func:`evaluate_uji_phone_split`'s ``"full"``) over every training row. Returns
    {"scores": Scores, "n": rows}."""
    from .hierarchy import Scores, score, sorensen_knn, split_vote
    from .locate import MISSING_DBM

    wt, Xt, pt, bt, ft, _ = _uji_arrays_waps(train_path)
    wv, Xv0, pv, bv, fv, _ = _uji_arrays_waps(test_path)
    col = {w: j for j, w in enumerate(wv)}
    Xv = np.stack([Xv0[:, col[w]] if w in col else np.full(len(Xv0), MISSING_DBM) for w in wt], axis=1)  # the training file's columns
    lists = {}
    for rep in {choice.floor.rep, choice.position.rep}:
        lists[rep] = sorensen_knn(rep(Xt), rep(Xv), UJI_LIST_K)
    bb, ff, P = split_vote(lists, choice.floor, choice.position, bt, bt * 100 + ft, pt)
    s: Scores = score(bb, ff, P, bv, bv * 100 + fv, pv)
    return {"scores": s, "n": len(Xv)}


def evaluate_uji_split(train_path: str, test_path: str, k: int = 5) -> dict:
    """The standard UJIIndoorLoc protocol: references = every training row, queries = every row of the
    validation file, answered by our weighted kNN and by the plain 3-NN on raw dBm in the same run.
    Returns name -> {"errors", "floor", "building", "n"} (errors NaN where the floor is wrong)."""
    refs, test = _uji_labelled(train_path)[0], _uji_labelled(test_path)[0]
    if not refs or not test:
        raise ValueError(f"no usable rows in {train_path if not refs else test_path}")
    out = {}
    for name, loc in _uji_locators(refs, k).items():
        e, fh, bh = _uji_score(loc, test)
        out[name] = {"errors": np.array(e), "floor": float(np.mean(fh)), "building": float(np.mean(bh)), "n": len(test)}
    return out


def find_uji_validation(train_path: str) -> Path | None:
    """UJIIndoorLoc's validation file beside the training one (validationData.csv, gzipped or not)."""
    folder = Path(train_path).parent
    for name in ("validationData.csv", "validationData.csv.gz"):
        if (folder / name).is_file():
            return folder / name
    return None


def _fmt(e: np.ndarray) -> str:
    e = e[np.isfinite(e)]
    return f"mean {e.mean():.2f} m, median {np.median(e):.2f}, p75 {np.percentile(e, 75):.2f}, p95 {np.percentile(e, 95):.2f} (n={len(e)})"


@dataclass
class IlcMethodScore:
    label: str
    score: FingerprintScore


@dataclass
class RoutesHeldOut:
    """The ILC folds with every route's walks in one fold (:func:`route_folds`), weighted 5-NN."""

    n_repeated: int  # walks that follow a route walked more than once
    n_seen: int  # of those, how many the plain folds put beside a repeat kept in the map
    score: FingerprintScore
    repeated_errors: np.ndarray
    other_errors: np.ndarray
    #: the same folds by the cell likelihood on maps with the path-loss prior (pathloss.py): the kernel's
    #: reach, and the model carried ``PATHLOSS_FAR_REACH_M`` past the labelled scans (unlabelled corridors)
    pathloss: FingerprintScore | None = None
    pathloss_far: FingerprintScore | None = None


#: How far past the labelled scans the path-loss map of the routes held out reaches, m (the scans that
#: lie farther than 10 m from every label are 8 % of site1's; 30 m covers nearly all of them)
PATHLOSS_FAR_REACH_M = 30.0


@dataclass
class FingerprintEval:
    """What ``hybridloc eval fingerprint`` reports (rendered by :mod:`hybridloc.cli.eval`)."""

    uji: str = ""
    uji_validation: Path | None = None
    uji_split: dict | None = None  # evaluate_uji_split, when a validation file is scored
    uji_cv: dict | None = None  # evaluate_uji
    uji_phone: dict | None = None  # evaluate_uji_phone
    uji_phone_split: dict | None = None  # evaluate_uji_phone_split
    uji_split_votes: dict | None = None  # answer_uji_split with uji_phone_split's "full" choice, when a validation file is scored
    ilc: str = ""
    folds: int = 4
    n_ilc_traces: int = 0
    ilc_methods: list[IlcMethodScore] = field(default_factory=list)
    routes: RoutesHeldOut | None = None
    routes_left_out: RoutesLeftOut | None = None


def run_fingerprint_eval(uji: str, ilc: str, folds: int = 4, every: int = 1, uji_validation: str | None = None) -> FingerprintEval:
    from ..errors import MissingData

    out = FingerprintEval(uji=uji, ilc=ilc, folds=folds)
    if uji:
        if not Path(uji).is_file():
            raise MissingData(f"UJIIndoorLoc file {uji} not found (pass --uji '' to skip)")
        if uji_validation == "":
            val = None
        elif uji_validation:
            if not Path(uji_validation).is_file():
                raise MissingData(f"UJIIndoorLoc validation file {uji_validation} not found")
            val = Path(uji_validation)
        else:
            val = find_uji_validation(uji)
        if ilc and not Path(ilc).is_dir():  # before the long UJIIndoorLoc part
            raise MissingData(f"Indoor Location Competition folder {ilc} not found (pass --ilc '' to skip)")
        out.uji_validation = val
        if val is not None:
            out.uji_split = evaluate_uji_split(uji, str(val))
        out.uji_cv = evaluate_uji(uji)
        out.uji_phone = evaluate_uji_phone(uji)
        out.uji_phone_split = evaluate_uji_phone_split(uji)
        if val is not None:
            out.uji_split_votes = answer_uji_split(uji, str(val), out.uji_phone_split["full"])
    if ilc:
        if not Path(ilc).is_dir():
            raise MissingData(f"Indoor Location Competition folder {ilc} not found (pass --ilc '' to skip)")
        traces = load_site_surveys(ilc, every)
        plan = read_ilc_site(ilc)
        out.n_ilc_traces = len(traces)
        for method, kw, label, params in (
            ("knn", {"k": 5, "max_age_s": 8.0}, "weighted 5-NN, powed", None),
            ("prob", {"max_age_s": 8.0}, "cell likelihood", BuildParams(max_age_s=8.0)),
            ("prob", {"max_age_s": 8.0}, "cell lik., path loss", BuildParams(max_age_s=8.0, prior="path-loss")),
        ):
            s = evaluate_ilc(traces, folds, method, plan=plan, params=params, **kw)
            out.ilc_methods.append(IlcMethodScore(label, s))
        # The folds above deal walks recorded one after the other to different folds, so a route walked
        # twice in a row nearly always has one walk in the map. Held out whole, routes show what a path the
        # map has never seen walked gets.
        groups = route_groups(traces)
        repeated = {t.name for t, g in zip(traces, groups) if np.count_nonzero(groups == g) > 1}
        ordered = np.arange(len(traces)) % folds
        seen = sum(1 for i, g in enumerate(groups) if traces[i].name in repeated and np.any((groups == g) & (ordered != ordered[i])))
        rfolds = route_folds(traces, folds, np.random.default_rng(0))
        s = evaluate_ilc(traces, folds, "knn", fold_of=rfolds, k=5, max_age_s=8.0)
        rep = np.array([x for k, v in s.by_trace.items() if k in repeated for x in v])
        rest = np.array([x for k, v in s.by_trace.items() if k not in repeated for x in v])
        out.routes = RoutesHeldOut(len(repeated), seen, s, rep, rest)
        # Can a model of each transmitter place the scans of unlabelled corridors? The cell likelihood on
        # maps whose thin cells take a fitted path-loss prediction, at the kernel's reach and carried
        # past the labels over the walkable floor.
        for reach, attr in ((None, "pathloss"), (PATHLOSS_FAR_REACH_M, "pathloss_far")):
            bp = BuildParams(max_age_s=8.0, prior="path-loss", reach_m=reach)
            setattr(out.routes, attr, evaluate_ilc(traces, folds, "prob", plan=plan, params=bp, fold_of=rfolds, max_age_s=8.0, region=False))
        # The folds above take a quarter of the routes out of the map at once; leaving one route out
        # keeps the rest of the site in it, as a client on a route no survey walked meets it.
        out.routes_left_out = evaluate_ilc_loro(traces)
    return out

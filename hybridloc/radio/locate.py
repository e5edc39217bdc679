"""Fingerprint positioning: a probabilistic cell likelihood and weighted kNN, both answering with an
:class:`~hybridloc.types.AbsoluteFix` and a 95 % :class:`~hybridloc.types.ContainmentRegion`.

Probabilistic model (per floor f, cell c, observed transmitters O with readings r_j):

    log L(c) = sum_{j in O} [ log pd(c,j) - 1/2 min(z_j^2, z_max^2) - log s(c,j) ]
             + sum_{j not in O} log(1 - pd(c,j))

with z_j = (r_j - mu(c,j)) / s(c,j), s^2 = sd^2 + sigma_meas^2. The second sum is the model for
missing transmitters (a strong transmitter the map expects but the scan lacks counts against c);
it is computed as a per-cell constant minus the observed terms, so a query costs O(|O| x cells).
The quadratic is truncated at ``z_max`` (a Huber-like guard against a moved access point or a body
in the way). Readings are treated as independent, which overcounts evidence from correlated
transmitters; the log-likelihood is divided by a temperature ``tau`` (>= 1) so that the 95 % region
is a 95 % region (``hybridloc eval fingerprint`` prints its hit rate).

Floors: the posterior over cells of every floor is normalised jointly with a uniform prior per unit
walkable area; the floor probability is each floor's share. The fix is the posterior mean and
covariance on the most probable floor (plus the cell's own cell^2/12 spread); the region is the
smallest set of that floor's cells holding 95 % of its posterior, as polygons.

"No fix" answers (fix None, region None, a reason): no known transmitter in the scan, every reading at
the detection floor, or a map of another site.
"""

from __future__ import annotations

import copy
import functools
import math
import os
import threading
import weakref
from dataclasses import dataclass, field

import numpy as np
import shapely
from scipy import sparse
from sklearn.neighbors import NearestNeighbors

from ..types import AbsoluteFix, ContainmentRegion, FixSource, RfScan
from .radiomap import FLOOR_DBM, RadioMap
from .survey import LabelledScan

#: Log-likelihood of hearing a transmitter the floor's map does not hold (p_d 0.005, weak reading).
UNMAPPED_LOGLIK = math.log(0.005) - 0.5 * 9.0 - math.log(10.0)
#: Standard deviation per axis added to every kNN fix, m (see KnnLocator.locate_many).
KNN_SIGMA_FLOOR = 3.0
#: Value used for "not heard" in fingerprint vectors, dBm.
MISSING_DBM = -110.0
#: "powed-rel" fingerprints: each scan shifted so the mean of its REL_TOP_N strongest readings is this, dBm.
REL_TARGET_DBM = -60.0
REL_TOP_N = 16


@dataclass
class LocateResult:
    fix: AbsoluteFix | None
    region: ContainmentRegion | None
    floor_probs: dict[str, float] = field(default_factory=dict)
    reason: str = ""
    n_known: int = 0


@dataclass
class _FloorCache:
    name: str
    col: np.ndarray  # (M,) map transmitter index -> this floor's column, -1 when not on this floor
    cells: np.ndarray
    mu_T: np.ndarray  # (m, n)
    isd_T: np.ndarray  # (m, n) 1 / s
    c0_T: np.ndarray  # (m, n) log pd - log(1 - pd) - log s
    base: np.ndarray  # (n,) sum_j log(1 - pd)
    log_area: float
    cell: float


def _logsumexp(x: np.ndarray) -> float:
    """log sum exp(x), shifted by the maximum (scipy's general version costs ~0.2 ms a call here)."""
    m = float(np.max(x))
    return m + math.log(float(np.exp(x - m).sum())) if math.isfinite(m) else m


class ProbabilisticLocator:
    def __init__(
        self,
        rmap: RadioMap,
        sigma_meas: float = 3.0,
        z_max: float = 3.0,
        tau: float = 4.0,
        mass: float = 0.95,
        region: bool = True,
        max_age_s: float | None = None,
        missing_weight: float = 1.0,
        min_support: float = 0.0,
        prefilter: int | None = 400,
        n_prefilter_tx: int = 8,
        tau_region: float | None = 30.0,
    ):
        self.map = rmap
        self.sigma_meas = sigma_meas
        self.z_max = z_max
        self.tau = tau
        self.mass = mass
        self.region = region
        self.max_age_s = max_age_s
        self.prefilter = prefilter
        self.n_prefilter_tx = n_prefilter_tx
        self.tau_region = tau_region or tau
        self._floors = []
        for f in rmap.floors.values():
            keep = f.support >= min_support
            f = FloorMapView(f, keep)
            s = np.sqrt(f.sd.astype(np.float64) ** 2 + sigma_meas**2)
            pd = f.pd.astype(np.float64)
            c0 = np.log(pd) - missing_weight * np.log1p(-pd) - np.log(s)
            col = np.full(len(rmap.transmitters), -1, dtype=np.int64)
            col[f.tx] = np.arange(len(f.tx))
            self._floors.append(
                _FloorCache(
                    f.name,
                    col,
                    f.cells,
                    np.ascontiguousarray(f.mu.T, dtype=np.float32),
                    np.ascontiguousarray((1.0 / s).T, dtype=np.float32),
                    np.ascontiguousarray(c0.T, dtype=np.float32),
                    missing_weight * np.log1p(-pd).sum(axis=1),
                    math.log(len(f.cells) * f.cell_size**2),
                    f.cell_size,
                )
            )

    def locate(self, scan: RfScan, site: str | None = None) -> LocateResult:
        if site is not None and self.map.site and site != self.map.site:
            return LocateResult(None, None, reason=f"the map is of site {self.map.site!r}, not {site!r}")
        tix = self.map.tx_index
        off = self.map.device_offsets.get(scan.device_model, 0.0)
        J, r = [], []
        for k, v in scan.rssi_dbm.items():
            if self.max_age_s is not None and scan.age_s.get(k, 0.0) > self.max_age_s:
                continue
            j = tix.get(k)
            if j is not None:
                J.append(j)
                r.append(v - off)
        if not J:
            return LocateResult(None, None, reason="no known transmitter in the scan")
        r = np.asarray(r, dtype=np.float32)
        if float(r.max()) <= FLOOR_DBM + 1e-6:
            return LocateResult(None, None, reason="every reading is at the detection floor", n_known=len(J))
        J = np.asarray(J)
        zz = np.float32(self.z_max**2)
        logs, names = [], []
        cells_used, raw = [], []
        for fc in self._floors:
            cj = fc.col[J]
            here = cj >= 0
            c = cj[here]
            rh = r[here]
            n_cells = fc.mu_T.shape[1]
            cand = None
            if self.prefilter and n_cells > self.prefilter and len(c) > self.n_prefilter_tx:
                # Two stages (same model): the strongest readings alone rank the cells, and the full
                # likelihood is evaluated on the best ``prefilter`` of them. The cells left out hold
                # negligible posterior mass: a cell far from the strongest transmitters is unlikely.
                top = np.argsort(-rh)[: self.n_prefilter_tx]
                d = (rh[top][:, None] - fc.mu_T[c[top]]) * fc.isd_T[c[top]]
                coarse = -np.minimum(d * d, zz).sum(axis=0, dtype=np.float64)  # fit of the strongest readings only
                cand = np.argpartition(-coarse, self.prefilter)[: self.prefilter]
                mu, isd, c0, base = fc.mu_T[c][:, cand], fc.isd_T[c][:, cand], fc.c0_T[c][:, cand], fc.base[cand]
            else:
                mu, isd, c0, base = fc.mu_T[c], fc.isd_T[c], fc.c0_T[c], fc.base
            d = (rh[:, None] - mu) * isd
            q = np.minimum(d * d, zz)
            ll = base + (c0 - 0.5 * q).sum(axis=0, dtype=np.float64)
            # heard here but never mapped on this floor: as unlikely as the map allows anywhere
            ll += (~here).sum() * UNMAPPED_LOGLIK
            logs.append(ll / self.tau - fc.log_area)
            raw.append(ll)
            names.append(fc.name)
            cells_used.append(fc.cells if cand is None else fc.cells[cand])
        ev = np.array([_logsumexp(x) for x in logs])
        fp = np.exp(ev - _logsumexp(ev))
        best = int(np.argmax(fp))
        fc = self._floors[best]
        cells = cells_used[best]
        w = np.exp(logs[best] - logs[best].max())
        w /= w.sum()
        mean = w @ cells
        dxy = cells - mean
        cov = (dxy * w[:, None]).T @ dxy + np.eye(2) * (fc.cell**2 / 12.0)
        fix = AbsoluteFix(
            scan.t, mean, 0.5 * (cov + cov.T), FixSource.WIFI if scan.technology.value == "wifi" else FixSource.BLE, fc.name, float(fp[best])
        )
        region = None
        if self.region:
            # The region may use a higher temperature than the fix (tau_region): the independence
            # assumption makes the posterior too sharp for its 95 % set to hold 95 % of the truths.
            wr = np.exp((raw[best] - raw[best].max()) / self.tau_region)
            wr /= wr.sum()
            order = np.argsort(-wr)
            k = int(np.searchsorted(np.cumsum(wr[order]), self.mass)) + 1
            sel = order[:k]
            h = fc.cell / 2.0
            boxes = shapely.box(cells[sel, 0] - h, cells[sel, 1] - h, cells[sel, 0] + h, cells[sel, 1] + h)
            # Grid cells tile the floor edge to edge: a coverage union (edge matching, ~14x faster than a
            # general union on a few hundred cells) gives the same polygons; the general union stays as
            # the fallback should rounding leave the edges unmatched.
            shape = shapely.coverage_union_all(boxes)
            if not shape.is_valid:
                shape = shapely.union_all(boxes)
            region = ContainmentRegion(fc.name, shape, self.mass, scan.t)
        return LocateResult(fix, region, dict(zip(names, fp.tolist())), n_known=len(J))


class FloorMapView:
    """The cells of a floor map selected by a mask (same attributes as FloorMap)."""

    def __init__(self, f, keep: np.ndarray):
        self.name, self.cell_size, self.tx = f.name, f.cell_size, f.tx
        self.cells, self.mu, self.sd, self.pd = f.cells[keep], f.mu[keep], f.sd[keep], f.pd[keep]


class _TxRegistry:
    """Transmitter ids numbered as small integers, for the scans' cached readings (:func:`scan_readings`).
    A registry only grows; past :data:`TX_REGISTRY_MAX` ids (a server locating phones for months meets
    ever new randomised hotspot addresses) the next call starts a new one, and a scan whose codes came
    from another registry has them made again."""

    __slots__ = ("codes", "gen", "lock")

    def __init__(self, gen: int):
        self.codes: dict[str, int] = {}
        self.gen = gen
        self.lock = threading.Lock()

    def encode(self, keys) -> np.ndarray:
        codes = self.codes
        out = [codes.get(k, -1) for k in keys]
        if -1 in out:
            with self.lock:  # the first sight of a transmitter: numbered once, whatever thread sees it
                out = [codes.setdefault(k, len(codes)) for k in keys]
        return np.array(out, dtype=np.int64)


#: ids a registry holds before the next one starts (~100 MB of ids)
TX_REGISTRY_MAX = 1_000_000
_TX = _TxRegistry(0)
_TX_SWAP = threading.Lock()


def _registry() -> _TxRegistry:
    global _TX
    reg = _TX
    if len(reg.codes) > TX_REGISTRY_MAX:
        with _TX_SWAP:
            if _TX is reg:
                _TX = _TxRegistry(reg.gen + 1)
            reg = _TX
    return reg


def _after_fork_in_child() -> None:
    # a thread of the parent may have held a lock at the fork: the child's copies start free
    global _TX_SWAP
    _TX_SWAP = threading.Lock()
    _TX.lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def scan_readings(scan: RfScan, reg: _TxRegistry | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """A scan's readings as arrays, in the order of its ``rssi_dbm``: (transmitter codes in ``reg``, the
    current registry by default; dBm as float64; ages in s or None when the scan has none). Made once
    per scan and kept on it (a scan is immutable; the SLAM batch turns the same scans into fingerprint
    rows for every locator of every EM round); the codes made again for another registry."""
    reg = reg or _registry()
    got = scan.__dict__.get("_readings")
    if got is None or got[0] != reg.gen:
        keys = list(scan.rssi_dbm)
        if got is None:
            vals = np.fromiter(scan.rssi_dbm.values(), dtype=np.float64, count=len(keys))
            ages = np.array([scan.age_s.get(k, 0.0) for k in keys], dtype=np.float64) if scan.age_s else None
        else:
            vals, ages = got[2], got[3]
        got = (reg.gen, reg.encode(keys), vals, ages)
        scan.__dict__["_readings"] = got  # not a field: repr, equality and pickling leave it out
    return got[1], got[2], got[3]


def fingerprint_matrix(
    scans: list[RfScan], tx_index: dict[str, int], offsets: dict[str, float] | None = None, max_age_s: float | None = None
) -> np.ndarray:
    """(n, m) matrix of readings in dBm with MISSING_DBM for transmitters not heard (or heard more
    than ``max_age_s`` before the scan: a stale cached reading describes another place).

    Filled from each scan's cached arrays (:func:`scan_readings`) in one scatter: entry (i, j) is the
    float32 of the float64 ``dBm - offset``, as a per-reading loop writes it (no scan holds a
    transmitter twice, so the order of the writes does not matter)."""
    X = np.full((len(scans), len(tx_index)), MISSING_DBM, dtype=np.float32)
    if not scans or not tx_index:
        return X
    reg = _registry()  # one registry for the whole call
    tx_codes = reg.encode(list(tx_index))
    parts = [scan_readings(s, reg) for s in scans]
    counts = np.array([len(p[0]) for p in parts], dtype=np.int64)
    if not counts.sum():
        return X
    # the column of each reading's transmitter (-1: not in tx_index), by a search of tx_index's sorted
    # codes (a cost in the readings, not in every id the process has met)
    order = np.argsort(tx_codes, kind="stable")
    sorted_codes = tx_codes[order]
    tx_cols = np.fromiter(tx_index.values(), dtype=np.int64, count=len(tx_index))[order]
    codes = np.concatenate([p[0] for p in parts])
    vals = np.concatenate([p[1] for p in parts])
    rows = np.repeat(np.arange(len(scans)), counts)
    at = np.minimum(np.searchsorted(sorted_codes, codes), len(sorted_codes) - 1)
    cols = np.where(sorted_codes[at] == codes, tx_cols[at], -1)
    keep = cols >= 0
    if max_age_s is not None:
        ages = np.concatenate([p[2] if p[2] is not None else np.zeros(len(p[0])) for p in parts])
        keep &= ~(ages > max_age_s)
    if offsets:
        vals = vals - np.repeat(np.array([offsets.get(s.device_model, 0.0) for s in scans], dtype=np.float64), counts)
    X[rows[keep], cols[keep]] = vals[keep]
    return X


def powed(X: np.ndarray, beta: float = math.e) -> np.ndarray:
    """Torres-Sospedra et al.'s "powed" representation: ((x - min) / -min)^beta, 0 for missing.

    It compresses the weak, noisy end of the dBm scale so that strong readings dominate distances.
    """
    lo = MISSING_DBM
    return np.clip((X - lo) / -lo, 0.0, None) ** beta


def sorensen_neighbours(R: sparse.csc_array, R_sum: np.ndarray, Q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """k nearest rows of ``R`` for each row of ``Q`` under the Sorensen (Bray-Curtis) distance.

    d(x, y) = sum|x - y| / sum(x + y) on non-negative fingerprints (Torres-Sospedra et al. 2015 find
    it the best of 51 measures for WiFi fingerprinting, with the powed representation). Because
    |x - y| = x + y - 2 min(x, y), d = 1 - 2 sum min(x, y) / (sum x + sum y): only entries both
    fingerprints hold contribute to the sum of minima. ``R`` is kept column-compressed (a reference
    hears a small share of a building's transmitters), so a query costs O(references hearing what the
    query heard), not O(references x transmitters). ``R_sum`` holds the row sums of ``R``.
    Returns (distances, indices), each (len(Q), k), nearest first.

    The sums of minima are compiled (:func:`._compiled.sums_of_minima`): each reference's minima added
    column by column from zero, in ascending column order, as the sparse product of the query's columns
    of ``R`` with a vector of ones did before it (the same sums to the bit; that form ran the two sparse
    matrices per query that were most of a crowd-SLAM batch re-solve's kNN time).
    """
    from ._compiled import sums_of_minima  # Numba imported on first use

    n = R.shape[0]
    k = min(k, n)
    D = np.empty((len(Q), k))
    I = np.empty((len(Q), k), dtype=np.int64)
    Q = np.asarray(Q)
    dt = np.result_type(R.data.dtype, Q.dtype)  # the minimum's dtype, as numpy's would promote them
    indptr, indices, data = R.indptr, R.indices, R.data.astype(dt, copy=False)
    for i, q in enumerate(Q):
        inter = sums_of_minima(indptr, indices, data, q.astype(dt, copy=False), n)
        d = 1.0 - 2.0 * inter / np.maximum(R_sum + float(q.sum()), 1e-12)
        part = np.argpartition(d, k - 1)[:k] if k < n else np.arange(n)
        order = part[np.argsort(d[part], kind="stable")]
        D[i], I[i] = d[order], order
    return D, I


class KnnLocator:
    """Weighted k-nearest-neighbour positioning over labelled reference scans.

    Fingerprints are compared in Torres-Sospedra's "powed" representation; with references from several
    phone models each scan is first shifted so its 16 strongest readings average -60 dBm
    ("powed-rel"), which removes the unknown RSSI offset of the querying phone. The distance is
    Sorensen's (``metric="sorensen"``, the default: :func:`sorensen_neighbours`) or Euclidean
    (scikit-learn's search; the only choice for the "raw" dBm representation, which is negative).
    Floor = the inverse-distance weighted vote of the k neighbours; position = inverse-distance
    weighted mean of the neighbours on that floor; covariance = their weighted spread plus the labels'
    own uncertainty; region = the union of discs of radius 2 sigma around them (a 95 % region for a
    2-D Gaussian needs 2.45 sigma; the neighbours' spread already widens it).
    """

    def __init__(
        self,
        refs: list[LabelledScan],
        k: int = 5,
        representation: str = "auto",
        tx: list[str] | None = None,
        max_age_s: float | None = None,
        metric: str = "sorensen",
        memo: bool = False,
    ):
        if not refs:
            raise ValueError("kNN needs reference scans")
        auto = representation == "auto"
        if auto:
            representation = self._auto_representation(refs)
        if representation not in ("powed", "powed-rel", "raw"):
            raise ValueError(f"unknown representation {representation!r}")
        if metric not in ("sorensen", "euclidean"):
            raise ValueError(f"unknown metric {metric!r}; choose sorensen or euclidean")
        if metric == "sorensen" and representation == "raw":
            raise ValueError("the Sorensen distance needs non-negative fingerprints: use a powed representation")
        self.refs = refs
        txs = tx or sorted({k for r in refs for k in r.scan.rssi_dbm})
        self.tx_index = {t: i for i, t in enumerate(txs)}
        self._tx_given = bool(tx)  # a fixed index: a subset keeps it (subset)
        self._auto = auto
        self.representation = representation
        self.metric = metric
        self.k_asked = k  # k before the cap at the reference count (extended keeps asking for it)
        self.k = min(k, len(refs))
        self.max_age_s = max_age_s
        X = self._rep(fingerprint_matrix([r.scan for r in refs], self.tx_index, max_age_s=max_age_s))
        self._set_labels(refs)
        # each query scan's search result, by the scan (a search row depends only on its own scan and on
        # the references' fingerprints): the SLAM batch asks the same scans of the same references in
        # every EM round and every batch; a server locating each scan once leaves it off
        self._memo: dict[int, tuple] | None = {} if memo and metric == "sorensen" else None
        if metric == "sorensen":
            self._R = sparse.csc_array(X.astype(np.float32))
            self._R_sum = X.sum(axis=1, dtype=np.float64)
        else:
            self._X = X  # with_k fits its own search on it (scikit-learn picks its algorithm by k)
            self._nn = NearestNeighbors(n_neighbors=self.k).fit(X)

    @staticmethod
    def _auto_representation(refs: list[LabelledScan]) -> str:
        """``representation="auto"``: several phone models make fingerprints offset-free."""
        return "powed-rel" if len({r.scan.device_model for r in refs}) > 1 else "powed"

    def subset(self, keep) -> KnnLocator:
        """This locator over the references ``keep`` (a boolean mask over ``refs`` or indices into it,
        in ascending order) with the answers of a locator built afresh over them: the transmitters only
        the others heard leave the index, as from a map that never met them. The fingerprints are
        sliced out of this locator's instead of read and represented again, the cost of building one;
        a leave-one-group-out evaluation builds one per group. A row of the representation depends
        only on its own scan's readings, all of them in both indexes, so the slice holds the very
        numbers a fresh build computes; each row's sum is this locator's, the same float32 numbers
        summed in float64 with the dropped columns' zeros between them (equal to a fresh build's to
        the bit on the tests' and site1's references)."""
        keep = np.asarray(keep)
        if keep.dtype == bool and keep.shape != (len(self.refs),):
            raise ValueError(f"subset: a mask needs one entry per reference ({len(self.refs)}), got shape {keep.shape}")
        rows = np.flatnonzero(keep) if keep.dtype == bool else keep.astype(np.int64)
        if rows.size and (np.any(np.diff(rows) <= 0) or rows[0] < 0 or rows[-1] >= len(self.refs)):
            raise ValueError("subset: indices must be ascending, distinct and index the references")
        refs = [self.refs[i] for i in rows]
        if not refs:
            raise ValueError("kNN needs reference scans")
        if self._auto and self._auto_representation(refs) != self.representation:  # the fresh build's choice differs
            return KnnLocator(
                refs,
                k=self.k,
                tx=list(self.tx_index) if self._tx_given else None,
                max_age_s=self.max_age_s,
                metric=self.metric,
                memo=self._memo is not None,
            )
        names = list(self.tx_index)
        if self._tx_given:
            cols = np.arange(len(names))
        else:  # the transmitters the kept references heard (stale or not), in this index's sorted order
            cols = np.flatnonzero(np.asarray(self._heard[rows].sum(axis=0)).ravel() > 0)
        out = copy.copy(self)
        out.__dict__.pop("_heard", None)  # this locator's, over its own references
        out.tx_index = {names[c]: i for i, c in enumerate(cols)}
        out.k = min(self.k, len(refs))
        out._memo = {} if self._memo is not None else None
        if self.metric == "sorensen":
            # the rows' stored entries (no explicit zeros: a fresh build stores the same ones) and their
            # sums, which differ from a fresh build's only by the zeros of the columns dropped
            out._R = self._R[rows][:, cols]
            out._R_sum = self._R_sum[rows]
        else:
            out._X = self._X[np.ix_(rows, cols)]
            out._nn = NearestNeighbors(n_neighbors=out.k).fit(out._X)
        out._set_labels(refs)
        return out

    def extended(self, refs: list[LabelledScan]) -> KnnLocator:
        """This locator with ``refs`` appended to its references: the answers of a locator built afresh
        over ``self.refs + refs``, for the cost of representing ``refs`` alone (a server whose map grows
        by one walk's labels at a time, :meth:`hybridloc.server.service.Server.add_labels`).

        Transmitters only ``refs`` heard join the index in its sorted place; the old rows keep their
        represented values (a row depends only on its own scan's readings) under the renumbered columns,
        and their row sums (float32 values summed in float64; a fresh build sums the same numbers with
        zeros between them). The neighbours, floors and positions are a fresh build's; the distances
        agree to the float64 rounding of those sums. A fresh build instead where the fresh one would
        choose another representation (a new phone model among several) or the metric is Euclidean."""
        refs = list(refs)
        if not refs:
            return self
        every = self.refs + refs
        if self.metric != "sorensen" or (self._auto and self._auto_representation(every) != self.representation):
            return KnnLocator(
                every,
                k=self.k_asked,
                representation="auto" if self._auto else self.representation,
                tx=list(self.tx_index) if self._tx_given else None,
                max_age_s=self.max_age_s,
                metric=self.metric,
                memo=self._memo is not None,
            )
        out = copy.copy(self)
        out.__dict__.pop("_heard", None)
        if not self._tx_given:
            names = sorted(set(self.tx_index).union(*(r.scan.rssi_dbm for r in refs)))
            out.tx_index = {t: i for i, t in enumerate(names)}
        old = sparse.coo_array(self._R)
        remap = np.empty(len(self.tx_index), dtype=np.int64)
        for t, j in self.tx_index.items():
            remap[j] = out.tx_index[t]
        X = self._rep(fingerprint_matrix([r.scan for r in refs], out.tx_index, max_age_s=self.max_age_s))
        new = sparse.coo_array(X.astype(np.float32))
        n_old = len(self.refs)
        rows = np.concatenate([old.coords[0], new.coords[0] + n_old])
        cols = np.concatenate([remap[old.coords[1]], new.coords[1]])
        data = np.concatenate([old.data, new.data]).astype(np.float32, copy=False)
        R = sparse.csc_array((data, (rows, cols)), shape=(len(every), len(out.tx_index)))
        R.sort_indices()
        out._R = R
        out._R_sum = np.concatenate([self._R_sum, X.sum(axis=1, dtype=np.float64)])
        out.k = min(self.k_asked, len(every))
        out._memo = {} if self._memo is not None else None
        out._set_labels(every)
        return out

    @functools.cached_property
    def _heard(self) -> sparse.csr_array:
        """(references, transmitters) 1 where a reference's scan holds the transmitter at all (stale or
        not: the index a build makes), for :meth:`subset`."""
        cols = [self.tx_index[t] for r in self.refs for t in r.scan.rssi_dbm if t in self.tx_index]
        counts = [sum(t in self.tx_index for t in r.scan.rssi_dbm) for r in self.refs]
        rows = np.repeat(np.arange(len(self.refs)), counts)
        return sparse.csr_array((np.ones(len(cols), np.int32), (rows, np.array(cols, dtype=np.int64))), shape=(len(self.refs), len(self.tx_index)))

    #: Entries a memo holds before it starts again (~1 kB each at k = 30; the scans are not held)
    MEMO_MAX = 200_000

    def _set_labels(self, refs: list[LabelledScan]) -> None:
        self.refs = refs
        self.pos = np.array([r.pos_enu for r in refs])
        self.sig = np.array([r.sigma for r in refs])
        self.floors = np.array([r.floor or "" for r in refs])
        self.classes_ = np.unique(self.floors)
        self._floor_code = np.searchsorted(self.classes_, self.floors)

    def relabel(self, refs: list[LabelledScan]) -> KnnLocator | None:
        """This locator over ``refs``, when they are the same scans (the same objects, in the same order)
        with other labels (positions, sigmas, floors): the fingerprint index and the memo of searches are
        shared, since a search reads only the scans. None when the scans differ."""
        if len(refs) != len(self.refs) or any(a.scan is not b.scan for a, b in zip(refs, self.refs)):
            return None
        out = copy.copy(self)
        out._set_labels(refs)
        return out

    def with_k(self, k: int) -> KnnLocator:
        """This locator asking for ``k`` neighbours: the references' fingerprints (the dominant cost of
        building a locator) shared, the memo of searches its own (a search row holds k neighbours); the
        Euclidean metric's search structure fitted again (scikit-learn chooses it by k). Its answers are
        those of a locator built afresh with ``k``."""
        out = copy.copy(self)
        out.k_asked = k
        out.k = min(k, len(self.refs))
        if self._memo is not None:
            out._memo = {}
        if self.metric != "sorensen":
            out._nn = NearestNeighbors(n_neighbors=out.k).fit(self._X)
        return out

    def memo_keys(self) -> set[int]:
        """The keys (scan ids) the memo of searches holds now (empty without a memo)."""
        return set(self._memo or ())

    def memo_since(self, keys: set[int]) -> dict[int, tuple]:
        """The memo's entries not under ``keys`` (:meth:`memo_keys` of an earlier moment), without their
        weak references: (distances, indices, readings known) by scan id, picklable. A process forked
        from this one searched them; its scans that existed before the fork have the same ids here."""
        return {k: v[1:] for k, v in (self._memo or {}).items() if k not in keys}

    def memo_adopt(self, entries: dict[int, tuple], scans) -> int:
        """Take the entries of :meth:`memo_since` for those of ``scans`` (this process's objects) whose id
        they name: each search row depends only on its scan and on this locator's references, so a row
        searched by a forked copy of this locator is this one's. Returns how many were taken."""
        memo = self._memo
        if memo is None or not entries:
            return 0
        n = 0
        for s in scans:
            key = id(s)
            got = entries.get(key)
            if got is None or key in memo:
                continue
            if len(memo) >= self.MEMO_MAX:
                break
            memo[key] = (weakref.ref(s, lambda _, key=key: memo.pop(key, None)), *got)
            n += 1
        return n

    def _search(self, scans: list[RfScan]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(distances, indices, readings known) of each scan: from the memo where it holds the scan, the
        others searched together (:meth:`neighbours`; the same rows as a search of all of them)."""

        def searched(some: list[RfScan]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            X = fingerprint_matrix(some, self.tx_index, max_age_s=self.max_age_s)
            return *self.neighbours(self._rep(X)), (X > MISSING_DBM).sum(axis=1)

        memo = self._memo
        if memo is None:
            return searched(scans)
        got = [memo.get(id(s)) for s in scans]
        miss = [i for i, (s, g) in enumerate(zip(scans, got)) if g is None or g[0]() is not s]
        if miss:
            dist, idx, known = searched([scans[i] for i in miss])
            if len(memo) + len(miss) > self.MEMO_MAX:
                memo.clear()
            for j, i in enumerate(miss):
                # a weak reference to the scan: its entry leaves the memo when the scan dies (before its
                # id can name another scan), and the memo keeps no scan alive
                key = id(scans[i])
                got[i] = memo[key] = (weakref.ref(scans[i], lambda _, key=key: memo.pop(key, None)), dist[j], idx[j], known[j])
        k = self.k
        if not scans:
            return np.empty((0, k)), np.empty((0, k), dtype=np.int64), np.zeros(0, dtype=np.int64)
        return np.stack([g[1] for g in got]), np.stack([g[2] for g in got]), np.array([g[3] for g in got])

    def _rep(self, X):
        if self.representation == "powed-rel":
            # Device-independent: shift each scan so that the mean of its REL_TOP_N strongest readings
            # is REL_TARGET_DBM (removes a phone's RSSI offset, which the references cannot know), then
            # powed. The mean of many strong readings estimates the offset more steadily than the
            # strongest few, which swing with the distance to the nearest access point (UJIIndoorLoc,
            # grouped by user, covered scans: top 3 -> top 16 readings, 6.42 -> 5.71 m, floor 95.3 -> 96.5 %).
            heard = X > MISSING_DBM
            top = -np.sort(-np.where(heard, X, -np.inf), axis=1)[:, :REL_TOP_N]
            ref = np.where(np.isfinite(top), top, np.nan)
            shift = REL_TARGET_DBM - np.nan_to_num(np.nanmean(ref, axis=1), nan=REL_TARGET_DBM)
            X = np.where(heard, np.minimum(X + shift[:, None], 0.0), MISSING_DBM)
            return powed(X)
        return powed(X) if self.representation == "powed" else X

    def neighbours(self, Xr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distances, indices) of the k nearest references of represented fingerprints ``Xr``."""
        if self.metric == "sorensen":
            return sorensen_neighbours(self._R, self._R_sum, Xr.astype(np.float32), self.k)
        return self._nn.kneighbors(Xr)

    def nearest(self, scans: list[RfScan]) -> tuple[np.ndarray, np.ndarray]:
        """(distances, indices) (n, k) of each scan's k nearest references in fingerprint space (the
        locator's representation and metric): how well the references explain the scan."""
        return self._search(scans)[:2]

    def locate_many(self, scans: list[RfScan], regions: bool = True) -> list[LocateResult]:
        """The answer to each scan (module docstring); ``regions=False`` leaves out the containment
        regions (region None; the fixes are the same), which cost as much as the rest of an answer."""
        dist, idx, known = self._search(scans)
        n, n_cls = len(scans), len(self.classes_)
        w_all = 1.0 / np.maximum(dist, 1e-9)
        # each scan's floor vote: the weights binned by (scan, floor) in one bincount (a bin sums its
        # weights in the order a bincount per scan did)
        code = self._floor_code[idx]
        fprob = np.bincount((np.arange(n)[:, None] * n_cls + code).ravel(), weights=w_all.ravel(), minlength=n * n_cls).reshape(n, n_cls)
        fprob /= fprob.sum(axis=1, keepdims=True)
        best = np.argmax(fprob, axis=1)
        out: list[LocateResult | None] = []
        # the regions' discs of every scan buffered in one call and each scan's discs united in one
        # call over a row of the (scans, k) array (None where a neighbour is on another floor): the
        # same GEOS buffers and unions, in the same order, as one call per scan
        discs = shapely.points(self.pos[idx]) if n and regions else None
        pending = []  # (i, mean, cov, where in out)
        for i in range(n):
            if known[i] == 0:
                out.append(LocateResult(None, None, reason="no known transmitter in the scan"))
                continue
            on = code[i] == best[i]  # the neighbours on the chosen floor
            nb = idx[i][on]
            w = w_all[i][on] / w_all[i][on].sum()
            mean = w @ self.pos[nb]
            dxy = self.pos[nb] - mean
            # neighbours' spread + their labels' uncertainty + a floor for what the neighbours cannot
            # show: when all k agree on a wrong place (a similar-looking corridor) the spread is small
            # but the error is not. 3 m per axis ~ the median WiFi error on the ILC data.
            cov = (dxy * w[:, None]).T @ dxy + np.eye(2) * (float(w @ self.sig[nb] ** 2) + KNN_SIGMA_FLOOR**2)
            if discs is not None:
                discs[i, ~on] = None
            pending.append((i, mean, cov, len(out)))
            out.append(None)
        if not pending:
            return out  # type: ignore[return-value]
        areas: list = [None] * len(pending)
        if discs is not None:
            rows = np.array([i for i, _, _, _ in pending])
            covs = np.stack([c for _, _, c, _ in pending])
            # eigenvalues of every scan's covariance in one call (the same LAPACK call per matrix); the
            # region's disc radius is 2 sigma of the major axis (of the covariance as summed: the fix
            # holds it symmetrised)
            radii = 2.0 * np.sqrt(np.maximum(np.linalg.eigvalsh(covs).max(axis=1), 1e-6))
            areas = list(shapely.union_all(shapely.buffer(discs[rows], np.broadcast_to(radii[:, None], discs[rows].shape)), axis=1))
        names = [str(c) for c in self.classes_]
        for (i, mean, cov, at), area in zip(pending, areas):
            b = best[i]
            fl = self.classes_[b]
            # PD by construction (the spread is PSD, the floor term adds KNN_SIGMA_FLOOR^2 I), symmetric,
            # finite: the checked constructor's tests would cost as much as the rest of the answer
            fix = AbsoluteFix.trusted(scans[i].t, mean, 0.5 * (cov + cov.T), FixSource.WIFI, fl or None, float(fprob[i, b]))
            region = ContainmentRegion(fl or None, area, 0.95, scans[i].t) if area is not None else None
            out[at] = LocateResult(fix, region, dict(zip(names, fprob[i].tolist())), n_known=int(known[i]))
        return out  # type: ignore[return-value]

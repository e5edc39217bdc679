"""Loop front end of crowd SLAM: fingerprint loop candidates between walks, their likelihood, and PCM.

What it does (issue #20 point 2; ``../shared/notes/slam.md`` 3.2, 3.3, 4.3, 4.4), per floor:

1. **Freshness** (slam.md 3.1, 4.1). A reading older than ``max_age_s`` at the scan's time is cached,
   not heard here: it is dropped (:func:`fresh_vector`). The scan's time is the median last-seen time
   ``t - age`` of its fresh readings (:func:`scan_time`), not the time the scan was reported.
2. **Fingerprint vectors** ``r = RSS - floor_dbm`` (``floor_dbm`` -100 dBm: "not heard" is 0) on the
   fresh readings, optionally after removing a per-walk RSS offset (median alignment on shared
   transmitters, eq. 2 below), in a scipy CSR matrix (scans x transmitters).
3. **Similarity** ``S(a, b)``, one of :data:`MEASURES`:

   * ``unloc``: sum_k min(a_k, b_k) / sum_k max(a_k, b_k) over the union (UnLoc; weighted Jaccard);
   * ``cosine``: a.b / (|a| |b|);
   * ``jaccard``: |A & B| / |A | B| of the transmitter sets;
   * ``unloc_exp``: ``unloc`` on ``exp(r / 10 dB)``: the strong readings dominate (linear-ish power).

4. **Candidates from an inverted index**, never all pairs (:func:`index_pairs`): row block by row
   block, the sparse product ``N_blk N^T`` of the unit-length fresh vectors touches only pairs sharing a
   transmitter and gives their cosine; each scan keeps its ``prefilter`` (50) most cosine-similar scans
   of other walks (optionally only those sharing >= ``min_shared`` transmitters >= ``strong_dbm``), and
   only those are scored with the chosen measure. On site1 F2 this scores 5.5 % of the cross-walk pairs
   and keeps 99.0 % of the top-3 lists and 100 % of the mutual top-3 pairs of a full scoring (the
   rule "share >= 3 transmitters >= -80 dBm" alone scored 44 % and kept 96 %). Each scan keeps its best
   match in each other walk of the floor, and of those its ``k`` best; a pair is a candidate when it is
   in either list, **mutual** when in both.
5. **Similarity -> distance likelihood learned without ground truth** (:class:`DistanceModel`):
   scan pairs *inside* one walk with ``|dt| >= 4 s`` (independent scans) and dead-reckoned distance
   ``d <= 25 m`` are labelled by their dead-reckoned distance. Per similarity bin, EM fits

       p(d | S) = pi(S) Rayleigh(d; sigma_in(S)) + (1 - pi(S)) g(d)                              (1)

   with g the density of the distance between random walkable points of the floor (truncated to
   ``[0, 25 m]``; without walkable points the fallback ``g(d) = 2 d / D^2`` of two points in a large
   open area, D = 25 m). Then ``pi`` is smoothed non-decreasing and ``sigma_in`` non-increasing in S
   (isotonic regression weighted by the bin counts) and interpolated to each candidate's S.
   Within-walk pairs sample distances as the walks do (few closer than a walker covers in 4 s), not as
   loop candidates do; ``reweight`` weights each pair by ``g(d) / p_w(d)`` (eq. 1b, p_w the histogram of
   within-walk distances) to correct for it. It is off: on site1 the unweighted fit is the one that
   agrees with the mixture fitted to the *true* distances of cross-walk pairs of the same similarity
   (F2, unloc S >= 0.6: within-walk unweighted pi 0.95, sigma 5.0 m; weighted 0.78, 5.4 m; cross-walk
   truth 0.98, 6.0 m). That check used waypoints, as a diagnostic of the method, not to tune a number.
6. **Pairwise consistency (PCM, Mangelson et al. 2018; slam.md 4.4)** per pair of walks A, B: heading
   is absolute, so a candidate (i, j) implies the translation ``t = q_A(i) - q_B(j)`` between the two
   walks' dead-reckoned frames. Two candidates c = (i, j), c' = (i', j') agree when

       (t - t')^T [ (s_c^2 + s_c'^2) I + Cov_A(i, i') + Cov_B(j, j') ]^-1 (t - t') <= chi2_2(0.99) = 9.21    (3)

   with ``Cov_A(i, i') = |C_A(i') - C_A(i)|`` (the dead-reckoning covariance accumulated between the two
   scans). The largest set of mutually consistent candidates (maximum clique, exact Bron-Kerbosch with
   pivoting, :func:`max_clique`) is accepted when it holds >= ``min_clique_scans`` distinct scans on
   each walk spanning >= ``min_clique_span_m`` (largest distance between its scans, both walks).

Every candidate is returned as a :class:`Loop` with ``accepted`` and a ``reason`` (the audit trail):
``below-s-min``, ``not-mutual``, ``model`` (p_inlier < ``min_p_inlier``), ``pcm`` (outside the
accepted clique), ``pcm-small`` (the best clique is too small or too short).

Per-walk RSS offset (eq. 2): a reference per transmitter ``ref_k = median RSS`` over the floor's fresh
readings; a walk's offset ``o_w = median_k (RSS_wk - ref_k)`` over its readings; repeated twice.
The references are stored by :meth:`LoopDetector.fit`, so :meth:`LoopDetector.detect_new` treats a
new walk exactly as :meth:`LoopDetector.detect` would.

Choice of measure and settings (``python -m benchmarks.bench_loop_signal`` on ILC site1 F1-F3, 301
walks, 4,958 scans). The criterion needs no ground truth: at matched candidate rates (the similarity
threshold above which the mutual top-3 candidates number 0.05, 0.1, 0.2 per scan) the mixture of eq. 1
fitted to the *within-walk* pairs above that threshold, and the probability it implies of d < 5 m;
the score is its mean over floors and rates. Truth (waypoints) only scores, printed for the record:

=================  ===============  ========================  =====================  ====================
measure            no-truth score   truth: P(d<5 m) of        accepted after PCM:    walk-pair translation
                   (+ offset rem.)  mutual candidates at      P(d<5 m)               error, p90 (m)
                                    0.05 / 0.1 / 0.2 per      F1 / F2 / F3           F1 / F2 / F3
                                    scan (mean F1-F3)
=================  ===============  ========================  =====================  ====================
unloc_exp          0.404 (0.406)    0.58 / 0.58 / 0.58        0.52 / 0.59 / 0.60     7.5 / 8.0 / 8.6
unloc              0.371 (0.387)    0.64 / 0.58 / 0.56        0.53 / 0.63 / 0.48     7.7 / 10.0 / 10.4
cosine             0.357 (0.359)    0.62 / 0.56 / 0.51        0.51 / 0.61 / 0.47     8.5 / 9.2 / 11.2
jaccard            0.349 (0.348)    0.53 / 0.49 / 0.43        0.46 / 0.58 / 0.38     9.3 / 10.1 / 12.5
=================  ===============  ========================  =====================  ====================

Chosen: ``unloc_exp``, without the per-walk offset removal (it gains 0.002, below the 0.01 the benchmark
asks of it; every site1 walk is from one phone model, OPPO PBCM10: turn it on for a mixed-device crowd). With it
(and ``s_min`` 0.5, ``min_p_inlier`` 0.5, k = 3, PCM at 9.21 with >= 3 scans over >= 6 m): 0.22 / 0.22 /
0.17 accepted loops per scan, median true distance 5.0 / 4.1 / 4.1 m, 98 / 97 / 96 % of them within the
99 % radius ``3.03 sigma_in`` of their own model; 78 / 63 / 72 of 105 / 99 / 97 walks linked; the
clique-mean translation of each linked walk pair (:func:`pair_translations`) is off by a median
4.2 / 2.5 / 3.7 m (p90 7.5 / 8.0 / 8.6 m; the crude vote of slam.md 3.3: 7.4 m, p90 20.9 m).
2-5 s per floor on one core.

What this says: a single fingerprint places a scan to sigma_in ~ 4.5-5 m in this mall (the within-walk
model says so without truth, the truth-fitted mixture of cross-walk pairs says 5.6-6 m), so even a right
loop lies within 5 m with probability 1 - exp(-25 / (2 * 4.7^2)) = 0.43 (0.54 at 4 m): the loop precision at 5 m of
the issue (>= 0.9) cannot come from scan-level loops; it needs the walk-pair translations (sigma / sqrt(n))
and the back end's combination of many loops. The loops are returned with the spread that is true of them.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from sklearn.isotonic import IsotonicRegression

from ..types import RfScan

#: The similarity measures :func:`pair_similarity` knows.
MEASURES = ("unloc", "cosine", "jaccard", "unloc_exp")

#: chi2 quantile of 2 degrees of freedom at 0.99: -2 ln(0.01).
CHI2_2_99 = -2.0 * math.log(0.01)


# ---------------------------------------------------------------------------------------------- config
@dataclass(frozen=True)
class FrontendConfig:
    """Settings of the loop front end (module docstring for the role of each)."""

    max_age_s: float = 4.0  # freshness: slam.md 3.1 (site1); a per-site value
    floor_dbm: float = -100.0  # r = RSS - floor_dbm
    measure: str = "unloc_exp"
    remove_offset: bool = False  # per-walk RSS offset by median alignment (eq. 2)
    prefilter: int = 50  # index: each scan's this many most cosine-similar scans of other walks are scored (0: all)
    strong_dbm: float = -100.0  # index: a "strong" reading (-100: any)
    min_shared: int = 1  # index: and only pairs sharing at least this many strong transmitters
    k: int = 3  # mutual top-k
    one_per_walk: bool = True  # a scan's top-k holds at most one scan of each other walk
    s_min: float = 0.5
    # distance model (eq. 1)
    min_dt_s: float = 4.0
    max_dr_m: float = 25.0
    reweight: bool = False  # importance weights g(d) / p_w(d) on within-walk pairs (eq. 1b)
    n_bins: int = 10
    min_bin_pairs: int = 30
    em_iters: int = 200
    min_p_inlier: float = 0.5  # the model gate: a candidate more likely an outlier than an inlier is dropped
    # PCM (eq. 3)
    pcm_chi2: float = CHI2_2_99
    min_clique_scans: int = 3
    min_clique_span_m: float = 6.0
    max_exact_clique: int = 80  # above this many candidates in one walk pair, a greedy clique
    row_block: int = 2048  # index: rows per sparse product block (bounds memory)

    def __post_init__(self) -> None:
        if self.measure not in MEASURES:
            raise ValueError(f"unknown similarity measure {self.measure!r}; choose one of {MEASURES}")
        if self.k < 1 or self.min_shared < 1:
            raise ValueError("k and min_shared must be >= 1")


# ---------------------------------------------------------------------------------------------- data
@dataclass
class WalkScans:
    """The front end's view of one walk on one floor (``slam_spec``)."""

    walk: int
    floor: str
    node: np.ndarray  # (n,) graph node id of each scan node
    t: np.ndarray  # (n,) scan node times, s
    q: np.ndarray  # (n, 2) dead-reckoned positions in the walk's own frame, m (heading absolute)
    C: np.ndarray  # (n, 2, 2) cumulative dead-reckoning covariance from the walk start
    scans: list[RfScan]

    def __post_init__(self) -> None:
        self.node = np.asarray(self.node, dtype=int).reshape(-1)
        self.t = np.asarray(self.t, dtype=float).reshape(-1)
        self.q = np.asarray(self.q, dtype=float).reshape(-1, 2)
        self.C = np.asarray(self.C, dtype=float).reshape(-1, 2, 2)
        n = len(self.scans)
        if not (len(self.node) == len(self.t) == len(self.q) == len(self.C) == n):
            raise ValueError(f"WalkScans {self.walk}: node, t, q, C and scans must have one row per scan ({n})")


@dataclass
class Loop:
    """One loop candidate (accepted or not: the audit trail)."""

    walk_a: int
    node_a: int
    t_a: float
    walk_b: int
    node_b: int
    t_b: float
    similarity: float
    p_inlier: float
    sigma_in: float
    accepted: bool
    reason: str = ""


# ---------------------------------------------------------------------------------------------- freshness
def fresh_vector(scan: RfScan, max_age: float) -> dict[str, float]:
    """The readings of ``scan`` at most ``max_age`` s old (a reading with no age is taken as fresh)."""
    ages = scan.age_s
    return {k: v for k, v in scan.rssi_dbm.items() if ages.get(k, 0.0) <= max_age}


def scan_time(scan: RfScan, max_age: float) -> float:
    """Median last-seen time ``t - age`` of the fresh readings, s (slam.md 4.1). A scan with no fresh
    reading gets the last-seen time of its freshest reading; one with no reading at all, ``scan.t``."""
    ages = [scan.age_s.get(k, 0.0) for k in scan.rssi_dbm]
    if not ages:
        return float(scan.t)
    fresh = [a for a in ages if a <= max_age]
    return float(scan.t - (np.median(fresh) if fresh else min(ages)))


# ---------------------------------------------------------------------------------------------- vectors
@dataclass
class FloorVectors:
    """The fresh fingerprint vectors of a set of walks on one floor (rows: scans in walk order)."""

    R: sp.csr_matrix  # (n, m) RSS - floor_dbm of fresh readings (offset removed if asked), >= 0
    walk_row: np.ndarray  # (n,) index into the walk list of each row
    scan_row: np.ndarray  # (n,) index of the scan in its walk
    tx: list[str]  # column -> transmitter id


def walk_offsets(walks: list[WalkScans], max_age_s: float, rounds: int = 2) -> tuple[dict[str, float], np.ndarray]:
    """Per-walk RSS offsets by median alignment on shared transmitters (module docstring, eq. 2).
    Returns the per-transmitter references (after alignment) and the offset of each walk, dB."""
    readings = [[(k, v) for s in w.scans for k, v in fresh_vector(s, max_age_s).items()] for w in walks]
    off = np.zeros(len(walks))
    ref: dict[str, float] = {}
    for _ in range(rounds):
        per_tx: dict[str, list[float]] = defaultdict(list)
        for w, rd in enumerate(readings):
            for k, v in rd:
                per_tx[k].append(v - off[w])
        ref = {k: float(np.median(v)) for k, v in per_tx.items()}
        off = np.array([float(np.median([v - ref[k] for k, v in rd])) if rd else 0.0 for rd in readings])
        off -= np.median(off) if len(off) else 0.0
    return ref, off


def offsets_from_reference(walks: list[WalkScans], ref: dict[str, float], max_age_s: float) -> np.ndarray:
    """The offset of each walk against fixed references (eq. 2 with ``ref`` held)."""
    out = np.zeros(len(walks))
    for w, ws in enumerate(walks):
        d = [v - ref[k] for s in ws.scans for k, v in fresh_vector(s, max_age_s).items() if k in ref]
        out[w] = float(np.median(d)) if d else 0.0
    return out


def floor_vectors(walks: list[WalkScans], cfg: FrontendConfig, offsets: np.ndarray | None = None) -> FloorVectors:
    """Stack the fresh vectors of ``walks`` into a CSR matrix (``offsets`` dB subtracted per walk)."""
    col: dict[str, int] = {}
    rows, cols, vals, walk_row, scan_row = [], [], [], [], []
    r = 0
    for w, ws in enumerate(walks):
        o = 0.0 if offsets is None else float(offsets[w])
        for i, s in enumerate(ws.scans):
            for k, v in fresh_vector(s, cfg.max_age_s).items():
                x = v - o - cfg.floor_dbm
                if x > 0:
                    rows.append(r)
                    cols.append(col.setdefault(k, len(col)))
                    vals.append(x)
            walk_row.append(w)
            scan_row.append(i)
            r += 1
    R = sp.csr_matrix((np.array(vals, dtype=float), (np.array(rows, dtype=int), np.array(cols, dtype=int))), shape=(r, len(col)))
    R.sum_duplicates()
    return FloorVectors(R, np.array(walk_row, dtype=int), np.array(scan_row, dtype=int), list(col))


def _transform(R: sp.csr_matrix, measure: str) -> sp.csr_matrix:
    if measure == "unloc_exp":
        return R._with_data(np.expm1(R.data / 10.0), copy=True)  # exp(r/10) - 1: 0 stays "not heard"
    if measure == "jaccard":
        return R._with_data(np.ones_like(R.data), copy=True)
    return R


def pair_similarity(R: sp.csr_matrix, I: np.ndarray, J: np.ndarray, measure: str, block: int = 200_000) -> np.ndarray:
    """S(R[I[n]], R[J[n]]) for each pair n, computed on the sparse rows only (module docstring, 3.)."""
    X = _transform(R.tocsr(), measure)
    # the sums of minima compiled (slam/_compiled.py: scipy's sums to the bit) where they apply
    compiled = measure != "cosine" and X.dtype == np.float64 and X.has_canonical_format
    out = np.empty(len(I))
    norms = np.sqrt(np.asarray(X.multiply(X).sum(axis=1)).ravel()) if measure == "cosine" else None
    tot = np.asarray(X.sum(axis=1)).ravel()
    for s in range(0, len(I), block):
        a, b = I[s : s + block], J[s : s + block]
        Xa, Xb = (None, None) if compiled else (X[a], X[b])
        if measure == "cosine":
            assert norms is not None and Xa is not None
            num = np.asarray(Xa.multiply(Xb).sum(axis=1)).ravel()
            den = norms[a] * norms[b]
        else:  # sum min / sum max, with sum max = sum a + sum b - sum min (weighted Jaccard)
            num = _sums_of_minima(X, a, b) if compiled else np.asarray(Xa.minimum(Xb).sum(axis=1)).ravel()
            den = tot[a] + tot[b] - num
        with np.errstate(invalid="ignore", divide="ignore"):
            out[s : s + block] = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return out


def _sums_of_minima(X: sp.csr_matrix, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    from ._compiled import sum_of_minima  # Numba imported on first use

    return sum_of_minima(X.indptr, X.indices, X.data, np.asarray(a, dtype=np.int64), np.asarray(b, dtype=np.int64))


def index_pairs(
    V: FloorVectors, cfg: FrontendConfig, rows: np.ndarray | None = None, allowed: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j) of rows of different walks worth scoring, from the inverted index: sparse products of
    row blocks with the transposed matrix, so only pairs sharing a transmitter are ever touched.

    * ``prefilter`` > 0: j is among i's ``prefilter`` most cosine-similar rows of other walks
      (N_blk N^T, N the rows of R normalised to unit length: the cosine is a product); else every pair
      sharing a transmitter;
    * and they share >= ``min_shared`` strong (>= ``strong_dbm``) transmitters.

    The exact measure is then computed on these pairs only. ``rows``: only these rows as the first
    member (default all); ``allowed`` (n,) bool: only these as the second. i != j."""
    R = V.R
    n = R.shape[0]
    # binary strong readings (copies: eliminate_zeros works in place and must not touch R's index arrays)
    strong = R.data >= (cfg.strong_dbm - cfg.floor_dbm)
    B = sp.csr_matrix((strong.astype(np.float32), R.indices.copy(), R.indptr.copy()), shape=R.shape)
    B.eliminate_zeros()
    need_strong = cfg.min_shared > 1 or bool(np.any(~strong))
    if cfg.prefilter > 0:
        norms = np.sqrt(np.asarray(R.multiply(R).sum(axis=1)).ravel())
        X = sp.csr_matrix(sp.diags(1.0 / np.where(norms > 0, norms, 1.0)) @ R)
    else:
        X = B
    XT = X.T.tocsr()
    rows = np.arange(n) if rows is None else np.asarray(rows, dtype=int)
    I_all, J_all = [], []
    for s in range(0, len(rows), cfg.row_block):
        blk = rows[s : s + cfg.row_block]
        P = (X[blk] @ XT).tocoo()
        i, j, c = blk[P.row], P.col, P.data
        keep = V.walk_row[i] != V.walk_row[j]
        if allowed is not None:
            keep &= allowed[j]
        if cfg.prefilter <= 0:  # P counts shared strong transmitters
            keep &= c >= cfg.min_shared - 0.5
            need = False
        else:
            need = need_strong
        i, j, c = i[keep], j[keep], c[keep]
        if cfg.prefilter > 0 and len(i):  # top-`prefilter` by cosine per row
            o = np.lexsort((-c, i))
            io = i[o]
            start = np.r_[0, np.flatnonzero(io[1:] != io[:-1]) + 1]
            rank = np.arange(len(o)) - np.repeat(start, np.diff(np.r_[start, len(o)]))
            sel = o[rank < cfg.prefilter]
            i, j = i[sel], j[sel]
        if need and len(i):
            shared = np.asarray(B[i].multiply(B[j]).sum(axis=1)).ravel()
            keep = shared >= cfg.min_shared - 0.5
            i, j = i[keep], j[keep]
        I_all.append(i)
        J_all.append(j)
    if not I_all:
        return np.zeros(0, int), np.zeros(0, int)
    return np.concatenate(I_all).astype(int), np.concatenate(J_all).astype(int)


def top_k(I: np.ndarray, J: np.ndarray, S: np.ndarray, walk_of: np.ndarray, k: int, one_per_walk: bool) -> np.ndarray:
    """Indices into (I, J, S) of each row I's k most similar J (at most one per walk of J if asked)."""
    if len(I) == 0:
        return np.zeros(0, int)
    idx = np.arange(len(I))
    if one_per_walk:  # best per (i, walk of j)
        o = np.lexsort((-S, walk_of[J], I))
        first = np.ones(len(o), bool)
        first[1:] = (I[o][1:] != I[o][:-1]) | (walk_of[J[o]][1:] != walk_of[J[o]][:-1])
        idx = o[first]
    o = idx[np.lexsort((-S[idx], I[idx]))]
    Io = I[o]
    start = np.r_[0, np.flatnonzero(Io[1:] != Io[:-1]) + 1]
    rank = np.arange(len(o)) - np.repeat(start, np.diff(np.r_[start, len(o)]))
    return o[rank < k]


# ---------------------------------------------------------------------------------------------- distance model
def rayleigh_pdf(d: np.ndarray, sigma: float) -> np.ndarray:
    return d / sigma**2 * np.exp(-0.5 * (d / sigma) ** 2)


@dataclass
class DistanceDensity:
    """g(d) of eq. 1: a histogram density on [0, d_max] (random walkable pairs), or 2 d / d_max^2."""

    d_max: float
    edges: np.ndarray | None = None
    dens: np.ndarray | None = None

    @classmethod
    def from_points(cls, pts: np.ndarray, d_max: float, rng: np.random.Generator, n_pairs: int = 200_000, bin_m: float = 1.0) -> DistanceDensity:
        pts = np.asarray(pts, dtype=float).reshape(-1, 2)
        if len(pts) < 2:
            return cls(d_max)
        a, b = rng.integers(len(pts), size=(2, n_pairs))
        d = np.linalg.norm(pts[a] - pts[b], axis=1)
        d = d[(a != b) & (d <= d_max)]
        if len(d) < 100:
            return cls(d_max)
        edges = np.arange(0.0, d_max + bin_m, bin_m)
        h, _ = np.histogram(d, edges)
        h = h + 0.5  # a pseudo-count: no empty bin (a zero would make any inlier infinitely likely)
        return cls(d_max, edges, h / (h.sum() * np.diff(edges)))

    def __call__(self, d: np.ndarray) -> np.ndarray:
        d = np.asarray(d, dtype=float)
        if self.edges is None or self.dens is None:
            return np.where((d >= 0) & (d <= self.d_max), 2.0 * d / self.d_max**2, 0.0) + 1e-12
        k = np.clip(np.searchsorted(self.edges, d, side="right") - 1, 0, len(self.dens) - 1)
        return self.dens[k]


def fit_mixture(
    d: np.ndarray, g: np.ndarray, weights: np.ndarray | None = None, iters: int = 200, pi0: float = 0.5, sigma0: float = 3.0, tol: float = 1e-7
) -> tuple[float, float]:
    """EM for p(d) = pi Rayleigh(d; sigma) + (1 - pi) g(d) (eq. 1), ``g`` the outlier density at each d,
    each sample with an optional weight ``v_n`` (importance weights, eq. 1b). E-step: responsibility
    r_n = pi R_n / (pi R_n + (1 - pi) g_n); M-step: pi = sum v r / sum v, sigma^2 = sum v r d^2 / (2 sum v r)
    (the weighted Rayleigh MLE)."""
    d = np.asarray(d, dtype=float)
    v = np.ones_like(d) if weights is None else np.asarray(weights, dtype=float)
    pi, sigma = pi0, sigma0
    for _ in range(iters):
        r = pi * rayleigh_pdf(d, sigma)
        w = v * r / (r + (1 - pi) * g + 1e-300)
        sw = w.sum()
        pi_new = float(sw / v.sum())
        sigma_new = float(math.sqrt(max((w * d * d).sum() / (2 * sw), 1e-6))) if sw > 0 else sigma
        done = abs(pi_new - pi) < tol and abs(sigma_new - sigma) < tol
        pi, sigma = min(max(pi_new, 1e-6), 1 - 1e-6), max(sigma_new, 0.05)
        if done:
            break
    return pi, sigma


def importance_weights(d: np.ndarray, g: np.ndarray, d_max: float, bin_m: float = 1.0, cap: float = 10.0) -> np.ndarray:
    """v(d) = g(d) / p_w(d) (eq. 1b): within-walk pairs are drawn from the walks' own distance
    distribution p_w (few pairs closer than a walker covers in ``min_dt_s``), loop candidates from the
    floor's; reweighting each within-walk pair by v turns its distances, bin by bin, into a sample of
    p(S | d) g(d), i.e. of p(d | S) between walks. p_w: histogram of all within-walk d (+0.5 per bin),
    v capped at ``cap`` times its mean, normalised to mean 1."""
    if len(d) == 0:
        return np.ones(0)
    edges = np.arange(0.0, d_max + bin_m, bin_m)
    h, _ = np.histogram(d, edges)
    pw = (h + 0.5) / ((h + 0.5).sum() * bin_m)
    k = np.clip(np.searchsorted(edges, d, side="right") - 1, 0, len(pw) - 1)
    v = g / pw[k]
    v = np.minimum(v, cap * v.mean())
    return v / v.mean()


@dataclass
class DistanceModel:
    """Similarity -> distance likelihood (eq. 1), learned from pairs inside walks."""

    centers: np.ndarray  # (b,) median similarity of each bin
    n: np.ndarray  # (b,) pairs per bin
    pi_raw: np.ndarray
    sigma_raw: np.ndarray
    pi: np.ndarray  # smoothed: non-decreasing in S
    sigma: np.ndarray  # smoothed: non-increasing in S
    measure: str
    refs: dict[str, dict[str, float]] = field(default_factory=dict)  # floor -> transmitter reference RSS (eq. 2)

    def evaluate(self, s) -> tuple[np.ndarray, np.ndarray]:
        """(pi(S), sigma_in(S)) at similarities ``s``: linear between bin centres, held outside."""
        s = np.asarray(s, dtype=float)
        return np.interp(s, self.centers, self.pi), np.interp(s, self.centers, self.sigma)

    def table(self) -> str:
        lines = ["   S      n    pi_raw  sigma_raw   pi   sigma_in"]
        for c, n, a, b, p, q in zip(self.centers, self.n, self.pi_raw, self.sigma_raw, self.pi, self.sigma):
            lines.append(f"{c:6.3f} {n:6d} {a:8.3f} {b:8.2f} {p:7.3f} {q:7.2f}")
        return "\n".join(lines)


def within_walk_pairs(V: FloorVectors, walks: list[WalkScans], cfg: FrontendConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows (I, J) of scan pairs inside one walk with |dt| >= min_dt_s, dead-reckoned distance <= max_dr_m,
    both with a fresh reading; and that distance."""
    I, J, D = [], [], []
    nnz = np.diff(V.R.indptr)
    start = 0
    for ws in walks:
        n = len(ws.scans)
        a, b = np.triu_indices(n, 1)
        d = np.linalg.norm(ws.q[a] - ws.q[b], axis=1)
        keep = (np.abs(ws.t[a] - ws.t[b]) >= cfg.min_dt_s) & (d <= cfg.max_dr_m) & (nnz[start + a] > 0) & (nnz[start + b] > 0)
        I.append(start + a[keep])
        J.append(start + b[keep])
        D.append(d[keep])
        start += n
    if not I:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    return np.concatenate(I), np.concatenate(J), np.concatenate(D)


def fit_distance_model(S: np.ndarray, d: np.ndarray, g: np.ndarray, cfg: FrontendConfig, measure: str, v: np.ndarray | None = None) -> DistanceModel:
    """Bin by similarity quantiles, EM per bin (eq. 1; sample weights ``v``, eq. 1b), isotonic smoothing
    weighted by bin counts."""
    if len(S) < cfg.min_bin_pairs:
        raise ValueError(f"only {len(S)} within-walk pairs: too few to learn the similarity -> distance model")
    nb = max(1, min(cfg.n_bins, len(S) // cfg.min_bin_pairs))
    edges = np.quantile(S, np.linspace(0, 1, nb + 1))
    k = np.clip(np.searchsorted(edges, S, side="right") - 1, 0, nb - 1)
    cen, n, pis, sigs = [], [], [], []
    for b in range(nb):
        m = k == b
        if m.sum() < cfg.min_bin_pairs // 2:
            continue
        p, s = fit_mixture(d[m], g[m], None if v is None else v[m], cfg.em_iters)
        cen.append(float(np.median(S[m])))
        n.append(int(m.sum()))
        pis.append(p)
        sigs.append(s)
    c, w = np.array(cen), np.array(n, dtype=float)
    pi_s = IsotonicRegression(increasing=True, y_min=0.0, y_max=1.0).fit(c, pis, sample_weight=w).predict(c)
    sg_s = IsotonicRegression(increasing=False, y_min=0.05).fit(c, sigs, sample_weight=w).predict(c)
    return DistanceModel(c, np.array(n), np.array(pis), np.array(sigs), pi_s, sg_s, measure)


# ---------------------------------------------------------------------------------------------- PCM
def max_clique(adj: list[int]) -> list[int]:
    """A maximum clique of the graph with bitset adjacency ``adj[v]`` (int bitmask, no self loops):
    Bron-Kerbosch with Tomita pivoting, exact. Ties: the first found (vertices in index order)."""
    best: list[int] = []

    def expand(R: list[int], P: int, X: int) -> None:
        nonlocal best
        if P == 0:
            if X == 0 and len(R) > len(best):
                best = list(R)
            return
        if len(R) + P.bit_count() <= len(best):  # bound: cannot beat the best
            return
        # pivot u in P | X maximising |P & N(u)|
        PX, u, nu = P | X, -1, -1
        while PX:
            v = (PX & -PX).bit_length() - 1
            PX &= PX - 1
            c = (P & adj[v]).bit_count()
            if c > nu:
                u, nu = v, c
        cand = P & ~adj[u]
        while cand:
            v = (cand & -cand).bit_length() - 1
            cand &= cand - 1
            expand(R + [v], P & adj[v], X & adj[v])
            P &= ~(1 << v)
            X |= 1 << v

    expand([], (1 << len(adj)) - 1, 0)
    return sorted(best)


def greedy_clique(adj: list[int]) -> list[int]:
    """A clique grown greedily from the highest-degree vertex (for walk pairs above ``max_exact_clique``)."""
    n = len(adj)
    order = sorted(range(n), key=lambda v: -adj[v].bit_count())
    best: list[int] = []
    for s in order[: min(n, 10)]:
        R, P = [s], adj[s]
        while P:
            v = max((u for u in range(n) if P >> u & 1), key=lambda u: (P & adj[u]).bit_count())
            R.append(v)
            P &= adj[v]
        if len(R) > len(best):
            best = R
    return sorted(best)


def pcm_adjacency(tA: np.ndarray, CA: np.ndarray, CB: np.ndarray, sig: np.ndarray, chi2: float) -> list[int]:
    """Bitset adjacency of eq. 3 for candidates with implied translations ``tA`` (c, 2), cumulative
    covariances ``CA``, ``CB`` (c, 2, 2) of their scans on each walk and inlier spreads ``sig`` (c,)."""
    c = len(tA)
    a, b = np.triu_indices(c, 1)
    dt = tA[a] - tA[b]
    # Cov(q(i') - q(i)) ~= |C(i') - C(i)|: the covariance accumulated between the two scans (sign by order)
    dA, dB = CA[a] - CA[b], CB[a] - CB[b]
    dA *= np.where(np.trace(dA, axis1=1, axis2=2) < 0, -1.0, 1.0)[:, None, None]
    dB *= np.where(np.trace(dB, axis1=1, axis2=2) < 0, -1.0, 1.0)[:, None, None]
    S = dA + dB + (sig[a] ** 2 + sig[b] ** 2)[:, None, None] * np.eye(2)
    x = np.linalg.solve(S, dt[..., None])[..., 0]
    ok = np.einsum("ni,ni->n", dt, x) <= chi2
    adj = [0] * c
    for u, v in zip(a[ok].tolist(), b[ok].tolist()):
        adj[u] |= 1 << v
        adj[v] |= 1 << u
    return adj


def _span(q: np.ndarray) -> float:
    if len(q) < 2:
        return 0.0
    return float(np.max(np.linalg.norm(q[:, None, :] - q[None, :, :], axis=-1)))


# ---------------------------------------------------------------------------------------------- detector
class LoopDetector:
    """Fingerprint loop candidates between walks, their likelihood and PCM (module docstring).

    ``walkable``: optional floor -> (m, 2) walkable sample points (site frame, m) for g(d) of eq. 1."""

    def __init__(self, config: FrontendConfig | None = None, walkable: dict[str, np.ndarray] | None = None, seed: int = 0):
        self.cfg = config or FrontendConfig()
        self.walkable = walkable or {}
        self.seed = seed
        self.model: DistanceModel | None = None
        self._g: dict[str, DistanceDensity] = {}

    def density(self, floor: str) -> DistanceDensity:
        if floor not in self._g:
            pts = self.walkable.get(floor)
            rng = np.random.default_rng(self.seed)
            self._g[floor] = DistanceDensity.from_points(pts, self.cfg.max_dr_m, rng) if pts is not None else DistanceDensity(self.cfg.max_dr_m)
        return self._g[floor]

    def _floor_vectors(self, walks: list[WalkScans], floor: str) -> FloorVectors:
        offsets = None
        if self.cfg.remove_offset and self.model is not None and floor in self.model.refs:
            offsets = offsets_from_reference(walks, self.model.refs[floor], self.cfg.max_age_s)
        return floor_vectors(walks, self.cfg, offsets)

    def within_walk_data(self, walks: list[WalkScans]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(S, d, g(d), v) of every within-walk pair of ``walks`` (all floors) with the current offsets;
        v the importance weights of eq. 1b per floor (all 1 without ``reweight``)."""
        S, D, G, W = [], [], [], []
        for floor, ws in _by_floor(walks).items():
            V = self._floor_vectors(ws, floor)
            I, J, d = within_walk_pairs(V, ws, self.cfg)
            g = self.density(floor)(d)
            S.append(pair_similarity(V.R, I, J, self.cfg.measure))
            D.append(d)
            G.append(g)
            W.append(importance_weights(d, g, self.cfg.max_dr_m) if self.cfg.reweight else np.ones(len(d)))
        if not S:
            return np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)
        return np.concatenate(S), np.concatenate(D), np.concatenate(G), np.concatenate(W)

    def fit(self, walks: list[WalkScans]) -> DistanceModel:
        """Learn the similarity -> distance model from pairs inside walks (eq. 1; no ground truth) and,
        if ``remove_offset``, the per-floor transmitter references (eq. 2)."""
        refs = {}
        if self.cfg.remove_offset:
            for floor, ws in _by_floor(walks).items():
                refs[floor], _ = walk_offsets(ws, self.cfg.max_age_s)
        self.model = DistanceModel(np.zeros(1), np.zeros(1, int), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), self.cfg.measure, refs)
        S, d, g, v = self.within_walk_data(walks)
        model = fit_distance_model(S, d, g, self.cfg, self.cfg.measure, v)
        model.refs = refs
        self.model = model
        return model

    def detect(self, walks: list[WalkScans]) -> list[Loop]:
        """Every candidate between different walks on the same floor, accepted or not (fits first if needed)."""
        if self.model is None:
            self.fit(walks)
        out: list[Loop] = []
        for floor, ws in _by_floor(walks).items():
            out.extend(self._detect_floor(ws, floor, None))
        return out

    def detect_new(self, new: list[WalkScans], old: list[WalkScans]) -> list[Loop]:
        """Candidates involving at least one walk of ``new`` (against ``old`` and each other), with the
        fitted model and references (no refit). Equal to the loops of :meth:`detect` on ``old + new``
        that involve a new walk, for the same fitted model."""
        if self.model is None:
            raise RuntimeError("LoopDetector.detect_new needs a fitted model: call fit() first")
        out: list[Loop] = []
        new_ids = {w.walk for w in new}
        for floor, ws in _by_floor(list(old) + list(new)).items():
            if any(w.walk in new_ids for w in ws):
                out.extend(self._detect_floor(ws, floor, new_ids))
        return out

    def detect_incremental(self, new: list[WalkScans], old: list[WalkScans], vectors: FloorVectors | None = None) -> list[Loop]:
        """:meth:`detect_new` for the online path (one new walk on a floor already held): the old scans
        whose own top-k is scored are only those that a new scan lists among its ``prefilter`` most
        similar (detect_new scores every old scan sharing a transmitter with a new one: most of the
        floor). The mutual candidates - hence every candidate that can pass the model gate and PCM, and
        the accepted loops - are the same as detect_new's: a mutual pair (old i, new j) needs i in j's
        list, which puts i among the scored old scans. What is dropped is audit trail only: pairs where
        an unscored old scan lists a new one that does not list it back (rejected there as
        ``below-s-min`` or ``not-mutual``).
        ``vectors``: the floor vectors of ``old + new`` in that order (rows walk by walk; the caller
        keeps them between calls), else built here."""
        if self.model is None:
            raise RuntimeError("LoopDetector.detect_incremental needs a fitted model: call fit() first")
        out: list[Loop] = []
        new_ids = {w.walk for w in new}
        for floor, ws in _by_floor(list(old) + list(new)).items():
            if any(w.walk in new_ids for w in ws):
                out.extend(self._detect_floor(ws, floor, new_ids, vectors, reverse="listed"))
        return out

    # ------------------------------------------------------------------ per floor
    def _candidates(self, V: FloorVectors, new_walks: np.ndarray | None, reverse: str = "touched"):
        """Candidate pairs (i < j rows), similarity, mutual flag. ``new_walks``: walk-list indices that
        are new (only pairs touching them are kept; rows whose top-k matter are scored in full).
        ``reverse``: which old rows get their own top-k scored: "touched" (every old row sharing a
        transmitter with a new row) or "listed" (those a new row lists, :meth:`detect_incremental`)."""
        cfg = self.cfg
        if new_walks is None:
            I, J = index_pairs(V, cfg)
        else:
            is_new = np.isin(V.walk_row, new_walks)
            # rows of new scans against everything; then the old rows whose own list may hold a new
            # scan (the index is not symmetric), against everything
            new_rows = np.flatnonzero(is_new)
            I0, J0 = index_pairs(V, cfg, rows=new_rows)
            if reverse == "listed":
                touched = np.unique(J0[~is_new[J0]])
            else:
                H = sp.csr_matrix((np.ones_like(V.R.data), V.R.indices, V.R.indptr), shape=V.R.shape)
                reach = np.diff((H @ H[new_rows].T).tocsr().indptr) > 0
                touched = np.flatnonzero(reach & ~is_new)
            I1, J1 = index_pairs(V, cfg, rows=touched)
            I, J = np.concatenate([I0, I1]), np.concatenate([J0, J1])
        S = pair_similarity(V.R, I, J, cfg.measure)
        sel = top_k(I, J, S, V.walk_row, cfg.k, cfg.one_per_walk)
        a, b = I[sel], J[sel]
        directed = set(zip(a.tolist(), b.tolist()))
        s_of = dict(zip(zip(a.tolist(), b.tolist()), S[sel].tolist()))
        pairs = {}
        for i, j in directed:
            key = (min(i, j), max(i, j))
            if key in pairs:
                continue
            mutual = (j, i) in directed
            pairs[key] = (s_of.get((i, j), s_of.get((j, i))), mutual)
        if new_walks is not None:
            is_new = np.isin(V.walk_row, new_walks)
            pairs = {k: v for k, v in pairs.items() if is_new[k[0]] or is_new[k[1]]}
        return pairs

    def _detect_floor(
        self, walks: list[WalkScans], floor: str, new_ids: set[int] | None, V: FloorVectors | None = None, reverse: str = "touched"
    ) -> list[Loop]:
        cfg = self.cfg
        assert self.model is not None
        if V is None:
            V = self._floor_vectors(walks, floor)
        elif V.R.shape[0] != sum(len(w.scans) for w in walks):
            raise ValueError(f"floor {floor}: the given vectors hold {V.R.shape[0]} rows for {sum(len(w.scans) for w in walks)} scans")
        new_walks = None if new_ids is None else np.array([k for k, w in enumerate(walks) if w.walk in new_ids], dtype=int)
        pairs = self._candidates(V, new_walks, reverse)
        keys = sorted(pairs)
        sims = np.array([pairs[k][0] for k in keys])
        pi, sig = self.model.evaluate(sims) if len(keys) else (np.zeros(0), np.zeros(0))
        loops: list[Loop] = []
        by_walk_pair: dict[tuple[int, int], list[tuple[int, int, int]]] = defaultdict(list)  # -> (loop, scan in A, scan in B)
        for n, (i, j) in enumerate(keys):
            wa, wb = V.walk_row[i], V.walk_row[j]
            if walks[wa].walk > walks[wb].walk:
                i, j, wa, wb = j, i, wb, wa
            A, B = walks[wa], walks[wb]
            ia, jb = int(V.scan_row[i]), int(V.scan_row[j])
            s, mutual = pairs[keys[n]]
            reason = ""
            if s < cfg.s_min:
                reason = "below-s-min"
            elif not mutual:
                reason = "not-mutual"
            elif pi[n] < cfg.min_p_inlier:
                reason = "model"
            else:
                by_walk_pair[(wa, wb)].append((n, ia, jb))
            loops.append(
                Loop(
                    A.walk,
                    int(A.node[ia]),
                    float(A.t[ia]),
                    B.walk,
                    int(B.node[jb]),
                    float(B.t[jb]),
                    float(s),
                    float(pi[n]),
                    float(sig[n]),
                    False,
                    reason,
                )
            )
        for (wa, wb), members in by_walk_pair.items():
            self._pcm(walks[wa], walks[wb], [loops[n] for n, _, _ in members], np.array([m[1] for m in members]), np.array([m[2] for m in members]))
        return loops

    def _pcm(self, A: WalkScans, B: WalkScans, cands: list[Loop], ia: np.ndarray, jb: np.ndarray) -> None:
        """Eq. 3 on the candidates of one walk pair (scans ``ia`` of A, ``jb`` of B); accept the maximum
        clique if it holds enough distinct scans spanning enough path on both walks."""
        cfg = self.cfg
        t = A.q[ia] - B.q[jb]
        sig = np.array([c.sigma_in for c in cands])
        adj = pcm_adjacency(t, A.C[ia], B.C[jb], sig, cfg.pcm_chi2)
        clique = max_clique(adj) if len(cands) <= cfg.max_exact_clique else greedy_clique(adj)
        ua, ub = np.unique(ia[clique]), np.unique(jb[clique])
        big = min(len(ua), len(ub)) >= cfg.min_clique_scans and min(_span(A.q[ua]), _span(B.q[ub])) >= cfg.min_clique_span_m
        members = set(clique)
        for n, c in enumerate(cands):
            c.accepted = big and n in members
            c.reason = "" if c.accepted else ("pcm" if big else "pcm-small")


@dataclass
class PairTranslation:
    """The translation between two walks' dead-reckoned frames implied by their accepted clique (slam.md
    4.4, "one trace-pair edge"): ``q_A(i) - q_B(j) ~ t`` for scans i of A and j of B at the same place."""

    walk_a: int
    walk_b: int
    t: np.ndarray  # (2,) m: mean of the clique's implied translations
    cov: np.ndarray  # (2, 2) m^2: covariance of that mean
    n: int  # loops in the clique


def pair_translations(loops: list[Loop], walks: list[WalkScans]) -> list[PairTranslation]:
    """One :class:`PairTranslation` per walk pair with accepted loops. The mean t of the implied
    translations t_c = q_A(i) - q_B(j); its covariance is the larger (in trace) of the sample covariance of
    the t_c over n and mean(sigma_in^2) / n I (the spread the model expects of n independent matches)."""
    by_node = {(w.walk, int(nd)): (w, i) for w in walks for i, nd in enumerate(w.node)}
    groups: dict[tuple[int, int], list[tuple[np.ndarray, float]]] = defaultdict(list)
    for lp in loops:
        if lp.accepted:
            (A, i), (B, j) = by_node[(lp.walk_a, lp.node_a)], by_node[(lp.walk_b, lp.node_b)]
            groups[(lp.walk_a, lp.walk_b)].append((A.q[i] - B.q[j], lp.sigma_in))
    out = []
    for (wa, wb), g in sorted(groups.items()):
        T = np.array([x for x, _ in g])
        n = len(T)
        model = float(np.mean([s * s for _, s in g])) / n * np.eye(2)
        sample = np.cov(T.T) / n if n > 1 else model
        out.append(PairTranslation(wa, wb, T.mean(axis=0), sample if np.trace(sample) > np.trace(model) else model, n))
    return out


def _by_floor(walks: list[WalkScans]) -> dict[str, list[WalkScans]]:
    out: dict[str, list[WalkScans]] = defaultdict(list)
    for w in walks:
        out[w.floor].append(w)
    return dict(out)

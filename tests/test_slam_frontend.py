"""Loop front end of crowd SLAM (hybridloc.slam.frontend) on small worlds with known truth."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from hybridloc.slam.frontend import (
    CHI2_2_99,
    MEASURES,
    DistanceDensity,
    FrontendConfig,
    Loop,
    LoopDetector,
    WalkScans,
    fit_mixture,
    floor_vectors,
    fresh_vector,
    index_pairs,
    max_clique,
    pair_similarity,
    pair_translations,
    pcm_adjacency,
    rayleigh_pdf,
    scan_time,
    top_k,
    walk_offsets,
)
from hybridloc.types import RfScan, Technology

REASONS = {"", "below-s-min", "not-mutual", "model", "pcm", "pcm-small"}


# ---------------------------------------------------------------------------------------------- a small radio world
class RadioWorld:
    """Open 60 m x 40 m floor, 40 access points; RSS = P0 - 10 n log10(d) + shadowing(p) + noise (dB).
    Shadowing: a Gaussian random field by random Fourier features (sigma 4 dB, length ~4 m)."""

    def __init__(self, rng: np.random.Generator, n_ap: int = 40, size=(60.0, 40.0)):
        self.size = np.array(size)
        self.ap = rng.uniform(0, 1, (n_ap, 2)) * self.size
        self.w = rng.standard_normal((n_ap, 24, 2)) / 4.0
        self.b = rng.uniform(0, 2 * np.pi, (n_ap, 24))
        self.amp = 4.0 * math.sqrt(2.0 / 24)

    def rss(self, p: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        d = np.maximum(np.linalg.norm(self.ap - p, axis=1), 1.0)
        shadow = self.amp * np.cos(np.einsum("akd,d->ak", self.w, p) + self.b).sum(axis=1)
        return -35.0 - 25.0 * np.log10(d) + shadow + rng.normal(0, 2.0, len(d))

    def scan(self, t: float, p: np.ndarray, rng: np.random.Generator, stale: int = 0) -> RfScan:
        r = self.rss(p, rng)
        heard = np.flatnonzero(r > -90.0)
        rssi = {f"ap{k}": float(np.clip(r[k], -100, 0)) for k in heard}
        age = {f"ap{k}": float(rng.uniform(0, 1.5)) for k in heard}
        for k in range(stale):  # cached readings from far away, many seconds old
            rssi[f"stale{k}"], age[f"stale{k}"] = -60.0, 15.0
        return RfScan(t, Technology.WIFI, rssi, age_s=age)


def make_walk(world: RadioWorld, walk: int, floor: str, path: np.ndarray, rng: np.random.Generator, node0: int, speed=1.2, period=2.0):
    """A walk along the polyline ``path`` (site frame); returns WalkScans (dead-reckoned frame: start at
    0, scale 1.05, heading bias 2 deg, random walk noise) and the true positions of its scans."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s_cum = np.r_[0.0, np.cumsum(seg)]
    t = np.arange(0.0, s_cum[-1] / speed, period) + 1000.0 * walk
    s = (t - t[0]) * speed
    truth = np.column_stack([np.interp(s, s_cum, path[:, 0]), np.interp(s, s_cum, path[:, 1])])
    beta = math.radians(2.0)
    R = 1.05 * np.array([[math.cos(beta), -math.sin(beta)], [math.sin(beta), math.cos(beta)]])
    q = (truth - truth[0]) @ R.T + np.cumsum(rng.normal(0, 0.05, (len(t), 2)), axis=0)
    C = (0.05**2 * np.arange(len(t)) + 1e-4)[:, None, None] * np.eye(2)
    scans = [world.scan(ti, pi, rng, stale=2) for ti, pi in zip(t, truth)]
    return WalkScans(walk, floor, np.arange(node0, node0 + len(t)), t, q, C, scans), truth


def corridor_walks(seed: int, n_walks: int = 16, floor: str = "F1"):
    """Walks back and forth along three corridors (y = 8, 20, 32 m) and two cross corridors."""
    rng = np.random.default_rng(seed)
    world = RadioWorld(rng)
    walks, truth, node = [], {}, 0
    for w in range(n_walks):
        y = rng.choice([8.0, 20.0, 32.0])
        x0, x1 = (5.0, 55.0) if rng.random() < 0.5 else (55.0, 5.0)
        xc = rng.choice([15.0, 45.0])
        y2 = 32.0 if y < 20 else 8.0
        path = np.array([[x0, y], [xc, y], [xc, y2]]) if rng.random() < 0.5 else np.array([[x0, y], [x1, y]])
        ws, tr = make_walk(world, w, floor, path, rng, node)
        node += len(ws.t)
        walks.append(ws)
        truth[w] = tr
    return world, walks, truth


# ---------------------------------------------------------------------------------------------- freshness
def test_fresh_vector_drops_stale_readings_and_scan_time_is_their_median_last_seen():
    s = RfScan(100.0, Technology.WIFI, {"a": -50.0, "b": -60.0, "c": -70.0, "d": -80.0, "e": -65.0}, age_s={"a": 0.5, "b": 1.0, "c": 2.0, "d": 10.0})
    # "e" has no age: taken as fresh (last seen at t)
    assert fresh_vector(s, 4.0) == {"a": -50.0, "b": -60.0, "c": -70.0, "e": -65.0}
    assert scan_time(s, 4.0) == pytest.approx(100.0 - np.median([0.5, 1.0, 2.0, 0.0]))
    # nothing fresh: the freshest reading's last-seen time; nothing at all: the scan's own time
    old = RfScan(100.0, Technology.WIFI, {"a": -50.0, "b": -60.0}, age_s={"a": 9.0, "b": 12.0})
    assert fresh_vector(old, 4.0) == {}
    assert scan_time(old, 4.0) == pytest.approx(91.0)
    assert scan_time(RfScan(5.0, Technology.WIFI, {}), 4.0) == 5.0


def test_floor_vectors_use_fresh_readings_only():
    _, walks, _ = corridor_walks(1, n_walks=2)
    V = floor_vectors(walks, FrontendConfig())
    assert not any(k.startswith("stale") for k in V.tx)  # the 15 s old readings never enter
    assert V.R.shape[0] == sum(len(w.scans) for w in walks)
    assert V.R.data.min() > 0


def test_walk_offsets_recover_a_device_offset():
    """Median alignment (eq. 2): a walk heard 6 dB weaker everywhere gets an offset of -6 dB vs the rest."""
    rng = np.random.default_rng(3)
    world = RadioWorld(rng)
    walks = []
    for w in range(5):
        ws, _ = make_walk(world, w, "F1", np.array([[5.0, 20.0], [55.0, 20.0]]), rng, 0)
        if w == 0:
            ws.scans = [RfScan(s.t, s.technology, {k: v - 6.0 for k, v in s.rssi_dbm.items()}, age_s=dict(s.age_s)) for s in ws.scans]
        walks.append(ws)
    _, off = walk_offsets(walks, 4.0)
    # readings of the same places, 2 dB noise: the median difference is within ~1 dB of the truth
    assert off[0] - np.median(off[1:]) == pytest.approx(-6.0, abs=1.0)


# ---------------------------------------------------------------------------------------------- similarity and index
def _brute_similarity(a: dict, b: dict, measure: str, floor=-100.0) -> float:
    keys = set(a) | set(b)
    ra = np.array([max(a.get(k, floor) - floor, 0.0) for k in keys])
    rb = np.array([max(b.get(k, floor) - floor, 0.0) for k in keys])
    if measure == "cosine":
        return float(ra @ rb / (np.linalg.norm(ra) * np.linalg.norm(rb)))
    if measure == "jaccard":
        return len(set(a) & set(b)) / len(keys)
    if measure == "unloc_exp":
        ra, rb = np.expm1(ra / 10.0), np.expm1(rb / 10.0)
    return float(np.minimum(ra, rb).sum() / np.maximum(ra, rb).sum())


@pytest.mark.parametrize("measure", MEASURES)
def test_pair_similarity_matches_its_definition(measure):
    _, walks, _ = corridor_walks(2, n_walks=3)
    cfg = FrontendConfig(measure=measure)
    V = floor_vectors(walks, cfg)
    vecs = [fresh_vector(s, cfg.max_age_s) for w in walks for s in w.scans]
    rng = np.random.default_rng(0)
    I, J = rng.integers(len(vecs), size=(2, 50))
    got = pair_similarity(V.R, I, J, measure)
    want = [_brute_similarity(vecs[i], vecs[j], measure) for i, j in zip(I, J)]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def test_compiled_sums_of_minima_are_scipys_to_the_bit():
    """slam/_compiled.py's sums of minima against the scipy expression they replace, on random rows of
    every width numpy's pairwise summation treats apart (empty, < 8, 8-128, above 128: its halving), with
    negative entries (a column in one row only counts min(x, 0)) and pairs of a row with itself."""
    import scipy.sparse as sp

    from hybridloc.slam._compiled import sum_of_minima

    rng = np.random.default_rng(21)
    rows = []
    for width in [0, 1, 3, 7, 8, 9, 15, 16, 17, 64, 127, 128, 129, 200, 256, 300, 517, 900]:
        for _ in range(4):
            cols = np.sort(rng.choice(1200, size=width, replace=False))
            vals = rng.lognormal(0.0, 2.0, width) * np.where(rng.random(width) < 0.1, -1.0, 1.0)
            rows.append((cols, vals))
    indptr = np.r_[0, np.cumsum([len(c) for c, _ in rows])]
    X = sp.csr_matrix((np.concatenate([v for _, v in rows]), np.concatenate([c for c, _ in rows]), indptr), shape=(len(rows), 1200))
    assert X.has_canonical_format
    I, J = rng.integers(len(rows), size=(2, 5000))
    I[:50] = J[:50]
    want = np.asarray(X[I].minimum(X[J]).sum(axis=1)).ravel()
    got = sum_of_minima(X.indptr, X.indices, X.data, I.astype(np.int64), J.astype(np.int64))
    assert np.array_equal(got, want)


@pytest.mark.parametrize("one_per_walk", [True, False])
def test_index_top_k_equals_brute_force(one_per_walk):
    """The inverted index scores only pairs sharing >= min_shared strong transmitters; its top-k equals the
    top-k of a brute-force scoring of all cross-walk pairs under the same sharing rule."""
    _, walks, _ = corridor_walks(4, n_walks=6)
    cfg = FrontendConfig(prefilter=0, min_shared=4, strong_dbm=-75.0, k=3, one_per_walk=one_per_walk, row_block=7)
    V = floor_vectors(walks, cfg)
    I, J = index_pairs(V, cfg)
    S = pair_similarity(V.R, I, J, cfg.measure)
    got = set(zip(I[top_k(I, J, S, V.walk_row, cfg.k, one_per_walk)].tolist(), J[top_k(I, J, S, V.walk_row, cfg.k, one_per_walk)].tolist()))
    vecs = [fresh_vector(s, cfg.max_age_s) for w in walks for s in w.scans]
    strong = [{k for k, v in x.items() if v >= cfg.strong_dbm} for x in vecs]
    want = set()
    for i in range(len(vecs)):
        scored = []
        for j in range(len(vecs)):
            if V.walk_row[i] != V.walk_row[j] and len(strong[i] & strong[j]) >= cfg.min_shared:
                scored.append((_brute_similarity(vecs[i], vecs[j], cfg.measure), j))
        scored.sort(key=lambda x: (-x[0], x[1]))
        seen: set = set()
        picked = []
        for _s, j in scored:
            if one_per_walk and V.walk_row[j] in seen:
                continue
            seen.add(V.walk_row[j])
            picked.append(j)
            if len(picked) == cfg.k:
                break
        want |= {(i, j) for j in picked}
    assert len(want) > 0
    assert got == want


def test_index_prefilter_keeps_each_scans_most_cosine_similar_scans():
    """With the cosine prefilter the index scores, per scan, its L most cosine-similar scans of other walks
    that share >= min_shared strong transmitters; brute force over all pairs gives the same set."""
    _, walks, _ = corridor_walks(5, n_walks=5)
    cfg = FrontendConfig(prefilter=6, min_shared=2, strong_dbm=-70.0, row_block=5)
    V = floor_vectors(walks, cfg)
    I, J = index_pairs(V, cfg)
    got = set(zip(I.tolist(), J.tolist()))
    vecs = [fresh_vector(s, cfg.max_age_s) for w in walks for s in w.scans]
    strong = [{k for k, v in x.items() if v >= cfg.strong_dbm} for x in vecs]
    want = set()
    for i in range(len(vecs)):
        scored = sorted(
            ((_brute_similarity(vecs[i], vecs[j], "cosine"), j) for j in range(len(vecs)) if V.walk_row[i] != V.walk_row[j]),
            key=lambda x: (-x[0], x[1]),
        )
        want |= {(i, j) for _c, j in scored[: cfg.prefilter] if len(strong[i] & strong[j]) >= cfg.min_shared}
    assert len(want) > 0
    assert got == want


# ---------------------------------------------------------------------------------------------- EM
def _loglik(d, g, pi, sigma):
    return np.log(pi * rayleigh_pdf(d, sigma) + (1 - pi) * g).sum()


@pytest.mark.parametrize("pi_true,sigma_true", [(0.7, 2.0), (0.4, 3.5)])
def test_em_recovers_pi_and_sigma_within_its_standard_errors(pi_true, sigma_true):
    """Synthetic eq. 1 with the fallback g (2 d / 25^2 on [0, 25]); the estimate must lie within 4
    standard errors, the SEs from the observed Fisher information (finite-difference Hessian of the
    log-likelihood at the estimate)."""
    rng = np.random.default_rng(11)
    n = 4000
    g_fn = DistanceDensity(25.0)
    inl = rng.random(n) < pi_true
    d = np.where(inl, rng.rayleigh(sigma_true, n), 25.0 * np.sqrt(rng.random(n)))  # outliers: inverse CDF of 2d/25^2
    d = d[d <= 25.0]
    g = g_fn(d)
    pi, sigma = fit_mixture(d, g, iters=2000, tol=1e-10)
    x0, h = np.array([pi, sigma]), np.array([1e-4, 1e-3])
    H = np.zeros((2, 2))
    for a, b in itertools.product(range(2), range(2)):
        ea, eb = np.eye(2)[a] * h[a], np.eye(2)[b] * h[b]
        f = [_loglik(d, g, *(x0 + sa * ea + sb * eb)) for sa, sb in ((1, 1), (1, -1), (-1, 1), (-1, -1))]
        H[a, b] = (f[0] - f[1] - f[2] + f[3]) / (4 * h[a] * h[b])
    se = np.sqrt(np.diag(np.linalg.inv(-H)))
    assert abs(pi - pi_true) < 4 * se[0], (pi, se[0])
    assert abs(sigma - sigma_true) < 4 * se[1], (sigma, se[1])
    # the SEs are what a sample of this size allows (a few hundredths), not vacuous
    assert se[0] < 0.05 and se[1] < 0.2


def test_weighted_em_equals_em_on_repeated_samples():
    rng = np.random.default_rng(5)
    d = np.abs(rng.normal(3.0, 2.0, 500))
    g = DistanceDensity(25.0)(d)
    w = rng.integers(1, 4, len(d))
    a = fit_mixture(np.repeat(d, w), np.repeat(g, w), iters=3000, tol=1e-12)
    b = fit_mixture(d, g, w.astype(float), iters=3000, tol=1e-12)
    np.testing.assert_allclose(a, b, rtol=1e-6)


# ---------------------------------------------------------------------------------------------- PCM
def test_max_clique_is_exact_on_small_graphs():
    """Against enumeration of every vertex subset of random graphs (n <= 11)."""
    rng = np.random.default_rng(7)
    for _ in range(60):
        n = int(rng.integers(1, 12))
        p = rng.uniform(0.2, 0.9)
        A = np.triu(rng.random((n, n)) < p, 1)
        A = A | A.T
        adj = [sum(1 << int(v) for v in np.flatnonzero(A[u])) for u in range(n)]
        best = 0
        for r in range(n, 0, -1):
            if any(all(A[u, v] for u, v in itertools.combinations(c, 2)) for c in itertools.combinations(range(n), r)):
                best = r
                break
        got = max_clique(adj)
        assert len(got) == best
        assert all(A[u, v] for u, v in itertools.combinations(got, 2))


def _pair_walks(n=12, spacing=1.5, offset_b=(30.0, -12.0)):
    """Two walks along the same line: B's dead-reckoned frame is A's shifted by ``offset_b``."""
    x = np.arange(n) * spacing
    qa = np.column_stack([x, np.zeros(n)])
    qb = qa - np.array(offset_b)
    C = (0.02 * np.arange(n) + 1e-3)[:, None, None] * np.eye(2)
    scans = [RfScan(float(i), Technology.WIFI, {}) for i in range(n)]
    A = WalkScans(0, "F1", np.arange(n), np.arange(n) * 2.0, qa, C, scans)
    B = WalkScans(1, "F1", np.arange(n, 2 * n), np.arange(n) * 2.0, qb, C, scans)
    return A, B


def _run_pcm(A, B, pairs, sigma=1.0, cfg=None):
    det = LoopDetector(cfg or FrontendConfig())
    cands = [Loop(A.walk, int(A.node[i]), float(A.t[i]), B.walk, int(B.node[j]), float(B.t[j]), 0.8, 0.9, sigma, False, "pcm") for i, j in pairs]
    det._pcm(A, B, cands, np.array([i for i, _ in pairs]), np.array([j for _, j in pairs]))
    return cands


def test_pcm_rejects_a_planted_inconsistent_candidate_and_accepts_the_consistent_clique():
    A, B = _pair_walks()
    good = [(0, 0), (3, 3), (5, 6), (8, 8), (11, 10)]  # true matches (one-scan slips = 1.5 m <= sigma-scale)
    bad = (2, 10)  # aliased: implies a translation 12 m off
    cands = _run_pcm(A, B, good[:2] + [bad] + good[2:], sigma=1.0)
    acc = [c.accepted for c in cands]
    assert acc == [True, True, False, True, True, True]
    assert cands[2].reason == "pcm"
    # the test of eq. 3 in isolation: consistent pairs pass, the planted one fails against each
    t = A.q[[0, 2]] - B.q[[0, 10]]
    adj = pcm_adjacency(t, A.C[[0, 2]], B.C[[0, 10]], np.array([1.0, 1.0]), CHI2_2_99)
    assert adj == [0, 0]


def test_pair_translation_is_the_clique_mean_with_the_model_spread_as_its_floor():
    A, B = _pair_walks(offset_b=(30.0, -12.0))
    cands = _run_pcm(A, B, [(0, 0), (3, 3), (6, 6), (9, 9), (2, 10)], sigma=2.0)
    (pt,) = pair_translations(cands, [A, B])
    np.testing.assert_allclose(pt.t, [30.0, -12.0])  # exact matches: every implied translation is the offset
    assert pt.n == 4
    np.testing.assert_allclose(pt.cov, 2.0**2 / 4 * np.eye(2))  # no sample spread: the model's sigma^2 / n


def test_pcm_accepts_nothing_from_mutually_inconsistent_aliased_candidates():
    """Only wrong candidates, each implying a different translation (aliasing across a floor): the largest
    consistent set is a single candidate, below min_clique_scans: nothing accepted."""
    A, B = _pair_walks()
    pairs = [(0, 10), (2, 8), (5, 7), (6, 3), (9, 2), (11, 0)]  # i - j = -10, -6, -2, 3, 7, 11 scans: >= 6 m apart, none 0
    t = A.q[[i for i, _ in pairs]] - B.q[[j for _, j in pairs]]
    assert np.min([np.linalg.norm(a - b) for a, b in itertools.combinations(t, 2)]) > 5.0
    cands = _run_pcm(A, B, pairs, sigma=1.0)
    assert not any(c.accepted for c in cands)
    assert {c.reason for c in cands} == {"pcm-small"}


def test_pcm_needs_the_clique_to_span_enough_path():
    A, B = _pair_walks(spacing=0.5)  # 3 consistent scans within 1 m: too short to fix a translation
    cands = _run_pcm(A, B, [(0, 0), (1, 1), (2, 2)], cfg=FrontendConfig(min_clique_span_m=6.0))
    assert not any(c.accepted for c in cands)
    cands = _run_pcm(A, B, [(0, 0), (1, 1), (2, 2)], cfg=FrontendConfig(min_clique_span_m=0.9))
    assert all(c.accepted for c in cands)


# ---------------------------------------------------------------------------------------------- end to end
def test_detect_on_a_simulated_floor():
    """Corridor walks in a radio world: the model is learned from within-walk pairs only; candidates are
    between different walks of the same floor; accepted loops are near in truth."""
    world, walks, truth = corridor_walks(21, n_walks=16)
    rng = np.random.default_rng(22)
    ws_other, tr_other = make_walk(world, 99, "F2", np.array([[5.0, 20.0], [55.0, 20.0]]), rng, 10_000)  # another floor, same place
    truth[99] = tr_other
    det = LoopDetector(FrontendConfig())
    model = det.fit(walks + [ws_other])
    assert np.all(np.diff(model.pi) >= 0) and np.all(np.diff(model.sigma) <= 0)
    loops = det.detect(walks + [ws_other])
    assert loops and all(lp.reason in REASONS for lp in loops)
    assert all(lp.walk_a != lp.walk_b and 99 not in (lp.walk_a, lp.walk_b) for lp in loops)
    assert all(lp.accepted == (lp.reason == "") for lp in loops)
    node_row = {int(n): (w.walk, i) for w in walks for i, n in enumerate(w.node)}

    def d_true(lp):
        return float(np.linalg.norm(truth[lp.walk_a][node_row[lp.node_a][1]] - truth[lp.walk_b][node_row[lp.node_b][1]]))

    acc = [lp for lp in loops if lp.accepted]
    assert len(acc) >= 10
    # within the 99 % quantile of the Rayleigh the model gives each loop, sigma sqrt(-2 ln 0.01)
    inside = np.mean([d_true(lp) <= lp.sigma_in * math.sqrt(CHI2_2_99) for lp in acc])
    assert inside >= 0.9, inside


@pytest.mark.parametrize("prefilter", [0, 5, 50])
def test_detect_new_equals_detect_restricted_to_the_new_walks(prefilter):
    """Also with a small cosine prefilter, whose lists are not symmetric (an old scan may list a new one
    that does not list it back)."""
    _, walks, _ = corridor_walks(31, n_walks=14)
    det = LoopDetector(FrontendConfig(remove_offset=True, prefilter=prefilter))
    det.fit(walks)
    old, new = walks[:11], walks[11:]
    key = lambda lp: (lp.walk_a, lp.node_a, lp.walk_b, lp.node_b)  # noqa: E731
    full = sorted((lp for lp in det.detect(walks) if {lp.walk_a, lp.walk_b} & {w.walk for w in new}), key=key)
    inc = sorted(det.detect_new(new, old), key=key)
    assert len(full) > 0
    assert [(key(a), a.similarity, a.accepted, a.reason) for a in full] == [(key(b), b.similarity, b.accepted, b.reason) for b in inc]


def test_detect_new_needs_a_fitted_model():
    _, walks, _ = corridor_walks(1, n_walks=3)
    with pytest.raises(RuntimeError):
        LoopDetector().detect_new(walks[:1], walks[1:])

"""Crowd SLAM over a set of walks: loops, anchors, robust solve, labels, and EM with the crowd map.

Per floor (slam.md 4.3-4.7):

1. every walk's piece on the floor becomes nodes and odometry (:mod:`.walkgraph`);
2. the front end proposes loops between walks from fingerprint similarity and keeps the pairwise
   consistent ones (:mod:`.frontend`); every candidate is kept with its weight (the audit trail);
3. anchors: survey marks (absolute, 0.5 m), fixes from an existing radio map (Cauchy kernel: a fix in
   the wrong corridor must not bend the walk), and the floor plan. Walks linked by accepted loops form
   components; a component holding no mark and no fix is solved in its own frame and placed on the plan
   by a search over translation, rotation and scale (:func:`.anchoring.anchor_points`); when the search
   is ambiguous the component stays "relative only" and yields no absolute label;
4. the robust solve (:func:`.solve.solve`): first the linear problem (odometry, nuisances, anchors,
   loops under GNC), then with the walkable-area factors on nodes and edge midpoints;
5. every scan of an anchored walk is labelled with its node's position and marginal covariance;
6. EM (slam.md 4.7): the crowd radio map is built from the labels with each walk's fold left out,
   every scan of the fold is located against it, the fixes enter as Cauchy-robust anchors, and the
   floor is solved again, while the labels still move (median > ``em_stop_m``) or a round anchors
   more pieces than the one before (``em_while_anchoring``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from ..radio.survey import LabelledScan
from ..sim.building import graph_components
from ..types import FloorPlan, RfScan, Walk
from .anchoring import MIN_LOG_RATIO
from .register import RegisterConfig, register_walk
from .walkgraph import KIND_SCAN, WalkGraphConfig, WalkPiece, walk_pieces

log = logging.getLogger(__name__)

#: two scans of one walk this far apart in time are independent looks at the place (slam.md 4.3: 4 s)
MIN_PAIR_DT_S = 4.0
#: anchored-status of a walk piece (tracks.csv "anchored" column): its own survey marks, fixes from a radio
#: map, loops to walks that have either, the floor plan (a component placed by search), or none
MARKS, MAP, LOOPS, PLAN, RELATIVE = "marks", "map", "loops", "plan", "relative"


@dataclass
class SlamConfig:
    walk: WalkGraphConfig = field(default_factory=WalkGraphConfig)
    #: survey marks: a person marks a point to about half a metre (radio.survey)
    mark_sigma_m: float = 0.5
    #: radio-map fixes: their own covariance, at least this sd, under a Cauchy kernel of this width
    fix_sigma_floor_m: float = 3.0
    fix_kernel_c: float = 1.0
    #: a fix is used only when its scan is as close to the map as this quantile of the map's own
    #: neighbours where it covers the place (mapped_distance_gate)
    fix_gate_quantile: float = 0.9
    #: a fix whose map-floor probability is below this is not used
    fix_min_floor_prob: float = 0.6
    #: the floor a crowd walk names is a claim, not a fact (a phone's floor comes from its own fixes or a
    #: barometer): a single-floor walk without survey marks is moved to the floor its own fingerprints
    #: name (online.CrowdSlam.vote_floor) when at least ``floor_vote_min_fixes`` of its scans pass the
    #: mapped-distance gate with a floor probability >= fix_min_floor_prob and at least
    #: ``floor_vote_share`` of those name one other floor. Fixed a priori, not tuned: five independent
    #: scans and a 4:1 majority (a fix's floor is right 92-96 % of the time, README's fingerprint rows).
    #: On by default since the live SLAM child votes on each batch's crowd map (CrowdSlam.set_vote_map):
    #: a phone walk is held on the first floor its fixes named, right for 75.3 % of site1's crowd walks,
    #: the vote else that floor 82.2 % on the newest crowd map, 77.5 % on the survey map
    #: (scripts/probe_walk_floors.py). Site1's eval crowd, F = 0.1, against the same code with the vote
    #: off: coverage 72.0 -> 80.3 %, learning 31 -> 35 %, correction 34 -> 35 %, clients with an absolute
    #: track 185 -> 211 (time 2000 -> 2456 s). Voting on the survey map only (an earlier run) gave
    #: 68.6 -> 72.7 % coverage.
    floor_vote: bool = True
    floor_vote_min_fixes: int = 5
    floor_vote_share: float = 0.8
    #: walkable-area factor: r = max(0, d(p) - margin) / sigma on nodes and edge midpoints
    field_sigma_m: float = 0.5
    field_margin_m: float = 0.3
    #: plan anchoring of a component with no mark and no fix: refused when the runner-up placement is
    #: within this log-likelihood of the best (anchoring.MIN_LOG_RATIO: bench_anchoring)
    anchor_min_log_ratio: float = MIN_LOG_RATIO
    #: a component placed by the floor plan: prior on its nodes around the placement (sd of the centroid, m)
    plan_anchor_sd_m: float = 3.0
    #: loops and beacon passes: GNC Geman-McClure kernel width (whitened units). Cross-validated across
    #: site1's floors (eval slam F = 0.1, fused test mean, each floor scored with the width the other two
    #: chose from 1, 2, 3): held out 17.5 m, against 17.0 / 17.6 / 17.0 m for 1 / 2 / 3 on all floors -
    #: no width is distinguishable; 1 keeps the spec's value (loops already carry their own 4-8 m spread)
    loop_kernel_c: float = 1.0
    #: beacon passes (walkgraph): each beacon is an unknown position; a pass puts the walk within this sd
    #: of it (the spread measured for -65 dBm passes on site1, walkgraph.WalkGraphConfig.beacon_min_dbm),
    #: under the same GNC kernel as fingerprint loops (a moved or duplicated beacon is an outlier)
    beacon_sigma_m: float = 3.0
    #: EM rounds with the crowd map (at most; site1 F = 0.1, fused test mean: 0 rounds 18.3 m, 2 17.0 m,
    #: 4 16.2 m), folds of walks left out of each map, stop when labels move less
    em_rounds: int = 5
    em_folds: int = 5
    em_stop_m: float = 0.5
    #: ... but not while a round anchors more pieces than the one before: the stop measures how far the
    #: labels of pieces that were already anchored moved, and says nothing of the pieces EM is still
    #: bringing in. Without this, site1's live batch re-solves of F1 split in two (eval crowd, one run):
    #: 4-5 rounds anchored 63-74 walks by the map, while a first round that happened to move the few
    #: anchored ones less than em_stop_m ended EM there with 35-36 (49-67 relative), so coverage swung
    #: 82.0 -> 71.3 % between two final batches over the same walks
    em_while_anchoring: bool = True
    #: technologies a crowd map is built for
    technologies: tuple[str, ...] = ("wifi", "ble")
    #: kNN locator settings of the EM fixes (the server's: k = 5, readings up to 8 s old)
    knn_k: int = 5
    knn_max_age_s: float = 8.0
    register: RegisterConfig = field(default_factory=RegisterConfig)
    frontend: object | None = None  # FrontendConfig
    solve: object | None = None  # SolveOptions


@dataclass
class LoopRecord:
    """One loop candidate as the audit trail keeps it."""

    walk_a: str
    t_a: float
    walk_b: str
    t_b: float
    similarity: float
    weight: float
    accepted: bool
    floor: str
    p_inlier: float = float("nan")
    reason: str = ""
    node_a: int = -1
    node_b: int = -1
    kind: str = "wifi"  # "wifi": fingerprint loop; "ble": both walks passed the same beacon


@dataclass
class FloorSolution:
    floor: str
    pieces: list[WalkPiece]
    pos: np.ndarray  # (N, 2) node positions (site frame where anchored)
    cov: np.ndarray  # (N, 2, 2) node marginal covariance (NaN where not computed)
    nuisance: np.ndarray  # (K, 2)
    status: list[str]  # per piece: MARKS / MAP / PLAN / RELATIVE
    loops: list[LoopRecord]
    seconds: float = 0.0
    em_moves: list[float] = field(default_factory=list)
    #: every solve of the floor converged; else the largest last step among those that did not settle (m)
    converged: bool = True
    last_step: float = 0.0

    def piece_nodes(self, k: int) -> np.ndarray:
        return self.pieces[k].nodes

    def anchored(self, k: int) -> bool:
        return self.status[k] != RELATIVE

    def track(self, k: int, t: np.ndarray) -> np.ndarray:
        """Corrected positions of piece k at times t (s): between nodes i and j the dead-reckoned shape,
        mapped by the segment's (scale, bias) and closed so that it passes through both nodes."""
        pc = self.pieces[k]
        P = self.pos[pc.nodes]
        t = np.asarray(t, float)
        q = pc.q_at(t)
        j = np.clip(np.searchsorted(pc.t, t, side="right"), 1, max(pc.n - 1, 1))
        i = j - 1
        if pc.n < 2:
            return np.repeat(P[:1], len(t), axis=0)
        seg = pc.segment[np.minimum(i, len(pc.segment) - 1)]
        ab = self.nuisance[pc.nuisance[seg]]
        a, b = ab[:, 0:1], ab[:, 1:2]

        def M(v, a=a, b=b):  # (a, b) acting on v: a v + b perp(v)
            return a * v + b * np.column_stack([-v[:, 1], v[:, 0]])

        qi = pc.q_at(pc.t[i])
        qj = pc.q_at(pc.t[j])
        close = (P[j] - P[i]) - M(qj - qi)
        dt = pc.t[j] - pc.t[i]
        u = np.clip(np.where(dt > 0, (t - pc.t[i]) / np.where(dt > 0, dt, 1.0), 0.0), 0.0, 1.0)[:, None]
        out = P[i] + M(q - qi) + u * close
        before, after = t < pc.t[0], t > pc.t[-1]
        out[before] = P[0] + M(q[before] - pc.q[0], a[before], b[before])
        out[after] = P[-1] + M(q[after] - pc.q[-1], a[after], b[after])
        return out

    def track_sigma(self, k: int, t: np.ndarray) -> np.ndarray:
        """Per-axis sd (m, shape (len(t), 2)) interpolated between the piece's nodes."""
        pc = self.pieces[k]
        sd = np.sqrt(np.maximum(np.stack([self.cov[pc.nodes, 0, 0], self.cov[pc.nodes, 1, 1]], axis=1), 0.0))
        return np.column_stack([np.interp(t, pc.t, sd[:, 0]), np.interp(t, pc.t, sd[:, 1])])


@dataclass
class SlamResult:
    walks: list[Walk]
    names: list[str]
    floors: dict[str, FloorSolution]
    labels: list[LabelledScan]  # every scan of an anchored walk, with its position and sigma
    label_walk: list[int]  # walk index of each label
    seconds: float = 0.0
    stats: dict = field(default_factory=dict)

    @property
    def loops(self) -> list[LoopRecord]:
        return [lp for f in self.floors.values() for lp in f.loops]

    def crowd_map(self, technology: str, site: str, plan: FloorPlan | None, walks: set[int] | None = None):
        """The radio map of one technology from the labels (label uncertainty in its likelihood)."""
        from ..radio.radiomap import BuildParams, build_radio_map

        refs = [ls for ls, w in zip(self.labels, self.label_walk) if ls.scan.technology.value == technology and (walks is None or w in walks)]
        if not refs:
            return None
        return build_radio_map(refs, site=site, plan=plan, params=BuildParams(label_weight=True), technology=technology)


# ------------------------------------------------------------------------------------------ helpers
def _similarity_fit(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares 2-D similarity dst ~ T src + t (Umeyama); translation only for one point."""
    if len(src) == 1:
        return np.eye(2), dst[0] - src[0]
    ms, md = src.mean(0), dst.mean(0)
    s, d = src - ms, dst - md
    # T = [[a, -b], [b, a]]: a = sum(s.d)/sum(|s|^2), b = sum(s x d)/sum(|s|^2)
    n2 = float((s**2).sum())
    if n2 < 1e-6:
        return np.eye(2), md - ms
    a = float((s * d).sum()) / n2
    b = float((s[:, 0] * d[:, 1] - s[:, 1] * d[:, 0]).sum()) / n2
    sc = math.hypot(a, b)
    if not 0.5 < sc < 2.0:  # degenerate (marks close together): keep the rotation, unit scale
        a, b = a / sc, b / sc
    T = np.array([[a, -b], [b, a]])
    return T, md - T @ ms


def _fix_cov(cov: np.ndarray, floor_m: float) -> np.ndarray:
    c = 0.5 * (np.asarray(cov, float)[:2, :2] + np.asarray(cov, float)[:2, :2].T)
    w, V = np.linalg.eigh(c)
    return (V * np.maximum(w, floor_m**2)) @ V.T


@dataclass
class _Anchors:
    """Absolute information per piece: marks (node index within the piece, position) and fixes."""

    marks: dict[int, list[tuple[int, np.ndarray]]] = field(default_factory=dict)
    fixes: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = field(default_factory=dict)


#: the neighbours :func:`mapped_distance_gate` searches
GATE_K = 30


def gate_locator(refs: list[LabelledScan], cfg: SlamConfig):
    """The kNN locator :func:`mapped_distance_gate` searches ``refs`` with (:data:`GATE_K` neighbours).
    A caller holding a locator of the same ``refs`` takes its ``with_k(GATE_K)`` instead, which shares
    its fingerprint index (:meth:`~hybridloc.radio.locate.KnnLocator.with_k`)."""
    from ..radio.locate import KnnLocator

    return KnnLocator(refs, k=min(GATE_K, len(refs)), max_age_s=cfg.knn_max_age_s)


def mapped_distance_gate(refs: list[LabelledScan], cfg: SlamConfig, radius_m: float = 5.0, n_max: int = 2000, locator=None) -> float:
    """The fingerprint distance below which a scan is explained by a map of ``refs`` (no ground truth:
    the references' own labels). For each reference, the nearest other reference whose label lies within
    ``radius_m`` - of another walk, or of the same walk at least ``MIN_PAIR_DT_S`` apart (an independent
    scan of the same place): the distance a scan has to the map where the map covers its place. The
    gate is the ``cfg.fix_gate_quantile`` quantile of those distances; a scan farther from every
    reference comes from a place the map does not cover, and its fix (the nearest mapped place,
    whatever the distance) is not used. ``locator``: :func:`gate_locator` of ``refs``, when the caller
    holds one (built here otherwise)."""
    if len(refs) < 10:
        return math.inf
    loc = locator if locator is not None else gate_locator(refs, cfg)
    rng = np.random.default_rng(0)
    idx = rng.choice(len(refs), size=min(n_max, len(refs)), replace=False)
    dist, nb = loc.nearest([refs[i].scan for i in idx])
    pos = np.array([r.pos_enu for r in refs])
    src = np.array([r.source for r in refs])
    tt = np.array([r.scan.t for r in refs])
    out = []
    for row, i in enumerate(idx):
        other = (src[nb[row]] != src[i]) | (np.abs(tt[nb[row]] - tt[i]) >= MIN_PAIR_DT_S)
        ok = other & (np.linalg.norm(pos[nb[row]] - pos[i], axis=1) <= radius_m)
        if ok.any():
            out.append(float(dist[row][ok][0]))
    return float(np.quantile(out, cfg.fix_gate_quantile)) if len(out) >= 20 else math.inf


def locate_pieces(
    pieces: list[WalkPiece], locate: Callable[[list[RfScan]], list], cfg: SlamConfig, technology: str = "wifi", nearest=None, gate: float = math.inf
) -> dict[int, list]:
    """Fixes for the scan nodes of each piece from a locator (``locate_many``-like callable):
    {piece index: [(node index in piece, pos (2,), cov (2, 2))]}; fixes on another floor are dropped,
    and with ``nearest`` (the locator's ``nearest``) those of scans farther than ``gate`` from every
    reference (:func:`mapped_distance_gate`)."""
    out: dict[int, list] = {}
    batch, where = [], []
    for k, pc in enumerate(pieces):
        for i in np.flatnonzero(pc.scan >= 0):
            s = pc.scans[int(pc.scan[i])]
            if s.technology.value == technology:
                batch.append(s)
                where.append((k, int(i)))
    if not batch:
        return out
    far = np.zeros(len(batch), bool)
    if nearest is not None and math.isfinite(gate):
        far = nearest(batch)[0][:, 0] > gate
    for (k, i), res, too_far in zip(where, locate(batch), far):
        fx = getattr(res, "fix", None)
        if too_far:
            continue
        if fx is None or (fx.floor and fx.floor != pieces[k].floor) or fx.floor_prob < cfg.fix_min_floor_prob:
            continue
        out.setdefault(k, []).append((i, np.asarray(fx.pos_enu, float)[:2], _fix_cov(fx.cov, cfg.fix_sigma_floor_m)))
    return out


# ------------------------------------------------------------------------------------------ the floor
class FloorSlam:
    """The SLAM of one floor: build, anchor, solve, label (module docstring)."""

    def __init__(self, floor: str, pieces: list[WalkPiece], field_=None, cfg: SlamConfig | None = None, walkable_points: np.ndarray | None = None):
        from .frontend import LoopDetector

        self.floor = floor
        self.pieces = pieces
        self.field = field_
        self.cfg = cfg or SlamConfig()
        # random walkable places of the floor: the front end's outlier distance density g(d)
        self.detector = LoopDetector(self.cfg.frontend, walkable={floor: walkable_points} if walkable_points is not None else None)
        self.loops: list = []
        self.map_fixes: dict[int, list] = {}
        self.em_fixes: dict[int, list] = {}
        self.registrations: dict = {}
        self.beacons: dict[str, list[tuple[int, int, float]]] = {}

    # -------------------------------------------------------------- front end
    def _walk_scans(self) -> list:
        from .frontend import WalkScans

        out = []
        for k, pc in enumerate(self.pieces):
            sel = np.flatnonzero((pc.kind == KIND_SCAN) & (pc.scan >= 0))
            sel = np.array([i for i in sel if pc.scans[int(pc.scan[i])].technology.value == "wifi"], dtype=np.int64)
            if len(sel) == 0:
                continue
            out.append(WalkScans(k, self.floor, pc.node0 + sel, pc.t[sel], pc.q[sel], pc.C[sel], [pc.scans[int(pc.scan[i])] for i in sel]))
        return out

    def detect_loops(self) -> None:
        self.beacons = self.beacon_passes()
        ws = self._walk_scans()
        self.loops = []
        if len(ws) >= 2:
            try:
                self.detector.fit(ws)
            except ValueError as exc:  # too few pairs inside walks to learn the similarity model
                log.info("floor %s: no fingerprint loops (%s)", self.floor, exc)
                return
            self.loops = self.detector.detect(ws)

    def beacon_passes(self) -> dict[str, list[tuple[int, int, float]]]:
        """{beacon id: [(piece, node index in piece, dBm)]} for beacons passed by two or more pieces."""
        out: dict[str, list] = {}
        for k, pc in enumerate(self.pieces):
            for i in np.flatnonzero(pc.beacon >= 0):
                b = int(pc.beacon[i])
                out.setdefault(pc.beacons[b], []).append((k, int(i), float(pc.beacon_dbm[b])))
        return {b: v for b, v in out.items() if len({k for k, _, _ in v}) >= 2}

    def _links(self) -> list[tuple[int, int, int, int]]:
        """(piece a, node in a, piece b, node in b) of every accepted fingerprint loop and beacon co-pass."""
        out = []
        acc = [lp for lp in self.loops if lp.accepted]
        for lp, a, b in zip(acc, *self._pieces_of_loops(acc)):
            out.append((a, lp.node_a - self.pieces[a].node0, b, lp.node_b - self.pieces[b].node0))
        for obs in self.beacons.values():
            for x in range(len(obs)):
                for y in range(x + 1, len(obs)):
                    if obs[x][0] != obs[y][0]:
                        out.append((obs[x][0], obs[x][1], obs[y][0], obs[y][1]))
        return out

    # -------------------------------------------------------------- graph
    def _number(self) -> None:
        n = 0
        for pc in self.pieces:
            pc.node0 = n
            n += pc.n
        self._starts = np.array([pc.node0 for pc in self.pieces])

    def _graph(self, pieces_idx: list[int], init: dict[int, np.ndarray], anchors: _Anchors, plan_prior: dict[int, tuple], with_field: bool):
        """A factor graph over the given pieces (nodes numbered densely in that order)."""
        from .factors import FactorGraph, Kernel

        cfg = self.cfg
        g = FactorGraph()
        local0: dict[int, int] = {}
        for k in pieces_idx:
            pc = self.pieces[k]
            ids = g.add_nodes(init[k])
            local0[k] = int(ids[0])
        nuis: dict[int, np.ndarray] = {}
        ii, jj, DD, SS, KK = [], [], [], [], []
        wc = cfg.walk
        for k in pieces_idx:
            pc = self.pieces[k]
            ks = np.asarray(g.add_nuisances(np.tile([1.0, 0.0], (pc.n_segments, 1))), dtype=np.int64)
            nuis[k] = ks
            g.add_nuisance_prior(int(ks[0]), (1.0, 0.0), np.diag([wc.scale_sd**2, wc.bias_sd**2]))
            if len(ks) > 1:
                g.add_nuisance_links_many(ks[:-1], ks[1:], np.tile(np.diag([wc.scale_drift_sd**2, wc.bias_drift_sd**2]), (len(ks) - 1, 1, 1)))
            D, S = pc.odometry()
            base = local0[k]
            ii.append(base + np.arange(pc.n - 1))
            jj.append(base + np.arange(1, pc.n))
            DD.append(D)
            SS.append(S)
            KK.append(ks[pc.segment])
        if ii:
            g.add_odometry_many(np.concatenate(ii), np.concatenate(jj), np.concatenate(DD), np.concatenate(SS), np.concatenate(KK))
        for k in pieces_idx:
            base = local0[k]
            for i, z in anchors.marks.get(k, []):
                g.add_position_prior(base + i, z, np.eye(2) * cfg.mark_sigma_m**2)
            for i, z, R in anchors.fixes.get(k, []):
                g.add_position_prior(base + i, z, R, kernel=Kernel("cauchy", cfg.fix_kernel_c))
            if k in plan_prior:
                z_all, sd = plan_prior[k]
                # the placement fixes the component's centroid to sd: a prior of sd*sqrt(n) on each of its n nodes
                for i in range(self.pieces[k].n):
                    g.add_position_prior(base + i, z_all[i], np.eye(2) * sd**2)
        loop_ids: list[tuple[int, int]] = []  # (loop index in self.loops, graph loop id)
        for li, (lp, ka, kb) in enumerate(zip(self.loops, *self._pieces_of_loops(self.loops))):
            if not lp.accepted:
                continue
            if ka not in local0 or kb not in local0:
                continue
            ia = local0[ka] + (lp.node_a - self.pieces[ka].node0)
            ib = local0[kb] + (lp.node_b - self.pieces[kb].node0)
            gid = g.add_loop(ia, ib, np.eye(2) * lp.sigma_in**2, kernel=Kernel("gm", cfg.loop_kernel_c))
            loop_ids.append((li, gid))
        beacon_ids: list[tuple[str, int, int]] = []  # (beacon, piece, graph loop id)
        for b, obs in sorted(self.beacons.items()):
            here = [(k, i) for k, i, _ in obs if k in local0]
            if len({k for k, _ in here}) < 2:
                continue
            init_b = np.mean([init[k][i] for k, i in here], axis=0)
            bn = int(g.add_nodes(init_b[None, :])[0])
            for k, i in here:
                gid = g.add_loop(local0[k] + i, bn, np.eye(2) * cfg.beacon_sigma_m**2, kernel=Kernel("gm", cfg.loop_kernel_c))
                beacon_ids.append((b, k, gid))
        self._beacon_loop_ids = beacon_ids
        if with_field and self.field is not None:
            nodes = np.concatenate([local0[k] + np.arange(self.pieces[k].n) for k in pieces_idx])
            g.add_field(nodes, self.field, cfg.field_sigma_m, cfg.field_margin_m)
            # the middle of every edge longer than 1 m (a wall between two nodes is what it catches)
            ei = [local0[k] + e for k in pieces_idx for e in np.flatnonzero(np.linalg.norm(np.diff(self.pieces[k].q, axis=0), axis=1) > 1.0)]
            if ei:
                ei = np.asarray(ei, dtype=np.int64)
                g.add_edge_field(ei, ei + 1, self.field, cfg.field_sigma_m, cfg.field_margin_m, fractions=(0.5,))
        return g, local0, nuis, loop_ids

    def _pieces_of_loops(self, loops) -> tuple[list[int], list[int]]:
        """The pieces holding each loop's node_a and node_b (nodes are numbered piece by piece from
        ``_starts``), in one search for all loops."""
        if not loops:
            return [], []
        na = np.fromiter((lp.node_a for lp in loops), dtype=np.int64, count=len(loops))
        nb = np.fromiter((lp.node_b for lp in loops), dtype=np.int64, count=len(loops))
        return (np.searchsorted(self._starts, na, side="right") - 1).tolist(), (np.searchsorted(self._starts, nb, side="right") - 1).tolist()

    def node_status(self, status: list[str]) -> np.ndarray:
        """The per-piece ``status`` repeated for each node of the piece (nodes are numbered piece by piece)."""
        return np.repeat(np.asarray(status, dtype=object), [pc.n for pc in self.pieces])

    # -------------------------------------------------------------- solve
    def anchors(self, pieces_idx=None) -> _Anchors:
        """Absolute information of the pieces (all, or ``pieces_idx``): their survey marks, and their
        map and EM fixes where they agree on one placement of the walk (:func:`.register.register_walk`;
        the registration is kept in ``self.registrations``). A piece with marks takes no fixes."""
        cfg = self.cfg
        anchors = _Anchors()
        self.registrations = {}
        for k in range(len(self.pieces)) if pieces_idx is None else pieces_idx:
            pc = self.pieces[k]
            mk = [(int(i), np.array([pc.marks[int(pc.mark[i])].x, pc.marks[int(pc.mark[i])].y])) for i in np.flatnonzero(pc.mark >= 0)]
            if mk:
                anchors.marks[k] = mk
            fx = self.map_fixes.get(k, []) + self.em_fixes.get(k, [])
            if fx and k not in anchors.marks:
                # a walk is placed by its fixes only when they agree on one placement (register.py)
                qf = np.array([pc.q[i] for i, _, _ in fx])
                zf = np.array([z for _, z, _ in fx])
                sd = np.array([math.sqrt(float(np.linalg.eigvalsh(R).max())) for _, _, R in fx])
                reg = register_walk(qf, zf, sd, pc.step_q, self.field, cfg.register)
                self.registrations[k] = reg
                if reg.placed:
                    near = np.linalg.norm(qf @ reg.T.T + reg.t - zf, axis=1) <= 2.0 * cfg.register.support_m
                    anchors.fixes[k] = [f for f, ok in zip(fx, near) if ok]
        return anchors

    def solve(self) -> FloorSolution:
        from .solve import solve

        t0 = time.monotonic()
        cfg = self.cfg
        self._number()
        n_p = len(self.pieces)
        anchors = self.anchors()
        links = self._links()
        comp = graph_components(n_p, [(a, b) for a, _, b, _ in links])
        status = [RELATIVE] * n_p
        init: dict = {}
        plan_prior: dict[int, tuple] = {}
        absolute_roots = {comp[k] for k in range(n_p) if k in anchors.marks or k in anchors.fixes}
        # initial positions of pieces in absolute components: from their own marks/fixes, else through a
        # relative solve of the component pinned by the pieces that have them
        for root in sorted(set(comp.tolist())):
            members = [k for k in range(n_p) if comp[k] == root]
            if root in absolute_roots:
                own = {}
                for k in members:
                    pts = anchors.marks.get(k) or []
                    src = [self.pieces[k].q[i] for i, _ in pts]
                    dst = [z for _, z in pts]
                    if not pts and anchors.fixes.get(k):
                        reg = self.registrations[k]
                        own[k] = (reg.T, reg.t)
                        continue
                    if pts:
                        own[k] = _similarity_fit(np.asarray(src), np.asarray(dst))
                rel = self._relative_layout(members, own, links)
                for k in members:
                    init[k] = rel[k]
                    status[k] = MARKS if k in anchors.marks else MAP if k in anchors.fixes else LOOPS
                continue
            rel = self._relative_layout(members, {}, links)
            if self.field is None:
                for k in members:
                    init[k] = rel[k]
                continue
            from .anchoring import anchor_points

            pts = np.concatenate([rel[k] for k in members])
            an = anchor_points(pts, self.field, min_log_ratio=cfg.anchor_min_log_ratio)
            if an.ambiguous:
                for k in members:
                    init[k] = rel[k]
                continue
            sd_node = cfg.plan_anchor_sd_m * math.sqrt(len(pts))
            for k in members:
                placed = rel[k] @ an.T.T + an.t
                init[k] = placed
                plan_prior[k] = (placed, sd_node)
                status[k] = PLAN
        self.status = status
        anchored = [k for k in range(n_p) if status[k] != RELATIVE]
        relative = [k for k in range(n_p) if status[k] == RELATIVE]
        N = sum(pc.n for pc in self.pieces)
        pos = np.full((N, 2), np.nan)
        cov = np.full((N, 2, 2), np.nan)
        K = sum(pc.n_segments for pc in self.pieces)
        nuisance = np.tile([1.0, 0.0], (K, 1))
        weights = np.zeros(len(self.loops))
        beacon_w: dict[tuple[str, int], float] = {}
        converged, last_step = True, 0.0
        k0 = 0
        seg0 = {}
        for k, pc in enumerate(self.pieces):
            seg0[k] = k0
            pc.nuisance = k0 + np.arange(pc.n_segments)
            k0 += pc.n_segments
        for group, with_field in ((anchored, True), (relative, False)):
            if not group:
                continue
            g, local0, nuis, loop_ids = self._graph(group, {k: init[k] for k in group}, anchors, plan_prior, with_field=False)
            sol = solve(g, cfg.solve)
            if with_field and self.field is not None:
                g2, local0, nuis, loop_ids = self._graph(
                    group, {k: sol.pos[local0[k] : local0[k] + self.pieces[k].n] for k in group}, anchors, plan_prior, True
                )
                sol = solve(g2, cfg.solve, x0=sol)
            converged &= sol.converged
            last_step = max(last_step, sol.last_step)
            for k in group:
                pc = self.pieces[k]
                sl = slice(local0[k], local0[k] + pc.n)
                pos[pc.nodes] = sol.pos[sl]
                nuisance[pc.nuisance] = sol.nuisance[nuis[k]]
            if group is anchored:
                # marginal covariance of every node of the group's pieces (numbered 0..n-1 in order; the
                # beacon variables after them need none)
                C = sol.marginals(np.arange(sum(self.pieces[k].n for k in group)))
                for k in group:
                    pc = self.pieces[k]
                    cov[pc.nodes] = C[local0[k] : local0[k] + pc.n]
            for li, gid in loop_ids:
                weights[li] = sol.loop_weight[gid]
            for b, k, gid in self._beacon_loop_ids:
                beacon_w[(b, k)] = float(sol.loop_weight[gid])
        records = []
        piece_a, piece_b = self._pieces_of_loops(self.loops)
        for li, lp in enumerate(self.loops):
            ka, kb = piece_a[li], piece_b[li]
            records.append(
                LoopRecord(
                    self.pieces[ka].name,
                    float(lp.t_a),
                    self.pieces[kb].name,
                    float(lp.t_b),
                    float(lp.similarity),
                    float(weights[li]) if lp.accepted else 0.0,
                    bool(lp.accepted and weights[li] >= 0.5),
                    self.floor,
                    float(lp.p_inlier),
                    lp.reason if not lp.accepted else ("" if weights[li] >= 0.5 else "robust-weight"),
                    int(lp.node_a),
                    int(lp.node_b),
                )
            )
        # beacon co-passes as loops of the audit trail: weight = the smaller of the two passes' weights
        for b, obs in sorted(self.beacons.items()):
            for x in range(len(obs)):
                for y in range(x + 1, len(obs)):
                    (ka, ia, da), (kb, ib, db) = obs[x], obs[y]
                    if ka == kb:
                        continue
                    w = min(beacon_w.get((b, ka), 0.0), beacon_w.get((b, kb), 0.0))
                    pa, pb = self.pieces[ka], self.pieces[kb]
                    records.append(
                        LoopRecord(
                            pa.name,
                            float(pa.t[ia]),
                            pb.name,
                            float(pb.t[ib]),
                            min(da, db),
                            w,
                            w >= 0.5,
                            self.floor,
                            reason="" if w >= 0.5 else "robust-weight",
                            node_a=pa.node0 + ia,
                            node_b=pb.node0 + ib,
                            kind="ble",
                        )
                    )
        return FloorSolution(
            self.floor, self.pieces, pos, cov, nuisance, status, records, time.monotonic() - t0, converged=converged, last_step=last_step
        )

    def _relative_layout(self, members: list[int], own: dict[int, tuple], links: list[tuple[int, int, int, int]]) -> dict[int, np.ndarray]:
        """Initial node positions of a component's pieces: pieces with their own anchor transform are
        placed by it; the others follow along accepted loops (breadth first: a piece linked to a placed
        one is shifted by the median loop offset), and the first piece of a free component sits at its
        own frame. ``links``: the floor's :meth:`_links`."""
        placed: dict[int, np.ndarray] = {}
        for k, (T, t) in own.items():
            placed[k] = self.pieces[k].q @ T.T + t
        if not placed:
            k = members[0]
            placed[k] = self.pieces[k].q.copy()
        adj: dict[int, list] = {}
        mset = set(members)
        for ka, ia, kb, ib in links:
            if ka in mset and kb in mset:
                adj.setdefault(ka, []).append((kb, ia, ib))
                adj.setdefault(kb, []).append((ka, ib, ia))
        frontier = list(placed)
        while frontier:
            nxt = []
            for k in frontier:
                by: dict[int, list] = {}
                for other, i_self, i_other in adj.get(k, []):
                    if other not in placed:
                        by.setdefault(other, []).append(placed[k][i_self] - self.pieces[other].q[i_other])
                for other, offs in by.items():
                    placed[other] = self.pieces[other].q + np.median(np.asarray(offs), axis=0)
                    nxt.append(other)
            frontier = nxt
        for k in members:  # not reached (should not happen inside a component): own frame
            placed.setdefault(k, self.pieces[k].q.copy())
        return placed


# ------------------------------------------------------------------------------------------ site level
def _labels(fs: FloorSolution, walk_of_piece: list[int]) -> tuple[list[LabelledScan], list[int]]:
    """Every scan of every anchored piece with its position and sd: node scans from their node (position
    and marginal covariance), the others (BLE) from the corrected track at their time."""
    out, wk = [], []
    for k, pc in enumerate(fs.pieces):
        if not fs.anchored(k):
            continue
        at_node = {int(pc.scan[i]): pc.node0 + int(i) for i in np.flatnonzero(pc.scan >= 0)}
        rest = [j for j in range(len(pc.scans)) if j not in at_node]
        if rest:
            tr = np.array([pc.scans[j].t for j in rest])
            xy, sd = fs.track(k, tr), fs.track_sigma(k, tr)
        for j, s in enumerate(pc.scans):
            if j in at_node:
                n = at_node[j]
                c = fs.cov[n]
                sig = float(math.sqrt(max(0.5 * (c[0, 0] + c[1, 1]), 0.0))) if np.all(np.isfinite(c)) else 5.0
                pos = fs.pos[n].copy()
            else:
                r = rest.index(j)
                pos = xy[r]
                sig = float(np.sqrt(0.5 * (sd[r] ** 2).sum())) if np.all(np.isfinite(sd[r])) else 5.0
            out.append(LabelledScan(s, pos, sig, fs.floor, pc.name))
            wk.append(walk_of_piece[k])
    return out, wk


def _all_labels(floors: dict[str, FloorSolution], walk_of: dict[str, list[int]]) -> tuple[list[LabelledScan], list[int]]:
    labels: list[LabelledScan] = []
    label_walk: list[int] = []
    for fname, fs in floors.items():
        lb, wk = _labels(fs, walk_of[fname])
        labels += lb
        label_walk += wk
    return labels, label_walk


def set_em_fixes(
    slams, labels: list[LabelledScan], label_walk: list[int], fold_of: Callable[[int], int], cfg: SlamConfig, cache: dict | None = None
) -> bool:
    """One EM E-step (module docstring, 6): the crowd map of every fold of walks but one is built from
    ``labels`` (``label_walk``: the walk of each, ``fold_of(walk)``: its fold), the pieces of that
    fold's walks in each :class:`FloorSlam` of ``slams`` are located against it, and the fixes become
    their ``em_fixes``. False (nothing set) when fewer than 20 WiFi labels exist.

    ``cache``: a dict the caller keeps across the E-steps of one solve. A fold whose labels are the same
    scans as in the previous step (only their positions moved) keeps its locators' fingerprint index and
    searches (:meth:`~hybridloc.radio.locate.KnnLocator.relabel`): a search reads only the scans, so the
    fixes are those a fresh locator gives."""
    from ..radio.locate import KnnLocator

    wifi = [i for i, ls in enumerate(labels) if ls.scan.technology.value == "wifi"]
    if len(wifi) < 20:
        return False
    slams = list(slams)
    for fsl in slams:
        fsl.em_fixes = {}
    memo = cache is not None
    for f in range(max(cfg.em_folds, 2)):
        refs = [labels[i] for i in wifi if fold_of(label_walk[i]) != f]
        if len(refs) < 10:
            continue
        held = cache.get(f) if cache is not None else None
        loc = held[0].relabel(refs) if held is not None else None
        if loc is None:
            loc = KnnLocator(refs, k=cfg.knn_k, max_age_s=cfg.knn_max_age_s, memo=memo)
        gl = held[1].relabel(refs) if held is not None else None
        if gl is None:
            gl = loc.with_k(GATE_K)  # loc: the same refs and settings; the fingerprint index shared
        if cache is not None:
            cache[f] = (loc, gl)
        gate = mapped_distance_gate(refs, cfg, locator=gl)
        for fsl in slams:
            sel = [k for k, pc in enumerate(fsl.pieces) if fold_of(pc.walk) == f]
            if not sel:
                continue
            got = locate_pieces([fsl.pieces[k] for k in sel], partial(loc.locate_many, regions=False), cfg, "wifi", loc.nearest, gate)
            for j, v in got.items():
                fsl.em_fixes[sel[j]] = v
    return True


def anchored_more(old: FloorSolution, new: FloorSolution) -> bool:
    """Whether ``new`` (an EM round's solution of the same pieces) holds more pieces absolutely placed
    than ``old`` (:attr:`SlamConfig.em_while_anchoring`)."""
    return sum(s != RELATIVE for s in new.status) > sum(s != RELATIVE for s in old.status)


def _walkable_points(floor, n: int, rng: np.random.Generator) -> np.ndarray | None:
    """n uniform random points of the floor's walkable area (rejection sampling in its bounds)."""
    import shapely

    area = floor.walkable
    if area.is_empty:
        return None
    x0, y0, x1, y1 = area.bounds
    out = np.zeros((0, 2))
    for _ in range(50):
        c = rng.uniform([x0, y0], [x1, y1], size=(4 * n, 2))
        out = np.vstack([out, c[shapely.contains_xy(area, c[:, 0], c[:, 1])]])
        if len(out) >= n:
            return out[:n]
    return out if len(out) else None


def run_slam(
    walks: list[Walk],
    plan: FloorPlan | None = None,
    radio_map=None,
    config: SlamConfig | None = None,
    names: list[str] | None = None,
    progress: Callable[[str, str, int, int], None] | None = None,
) -> SlamResult:
    """Crowd SLAM over ``walks`` (module docstring). ``radio_map``: an existing map whose fixes anchor
    the walks (heavy-tailed). ``progress(stage, floor, done, total)`` is called as floors advance."""
    from ..radio.locate import KnnLocator

    cfg = config or SlamConfig()
    t0 = time.monotonic()
    names = names or [str(w.walk_id) if w.walk_id is not None else w.device for w in walks]
    by_floor: dict[str, list[WalkPiece]] = {}
    for wi, w in enumerate(walks):
        for pc in walk_pieces(w, wi, cfg.walk, name=names[wi]):
            by_floor.setdefault(pc.floor, []).append(pc)
    fields = {}
    if plan is not None:
        from .floorplan import WalkableField

        for f in plan.floors:
            if f.name in by_floor:
                fields[f.name] = WalkableField.from_floor(f)
    floors: dict[str, FloorSolution] = {}
    slams: dict[str, FloorSlam] = {}
    labels: list[LabelledScan] = []
    label_walk: list[int] = []
    locator = None
    if radio_map is not None and radio_map.references:
        locator = KnnLocator(radio_map.references, k=cfg.knn_k, max_age_s=cfg.knn_max_age_s)
        map_gate = mapped_distance_gate(radio_map.references, cfg)
    total = len(by_floor)
    for n_done, (fname, pieces) in enumerate(sorted(by_floor.items())):
        if progress:
            progress("loops", fname, n_done, total)
        pts = None
        if plan is not None and fname in plan.floor_names:
            pts = _walkable_points(plan.floor(fname), 2000, np.random.default_rng(0))
        fsl = FloorSlam(fname, pieces, fields.get(fname), cfg, pts)
        fsl._number()
        fsl.detect_loops()
        if locator is not None:
            fsl.map_fixes = locate_pieces(pieces, partial(locator.locate_many, regions=False), cfg, radio_map.technology, locator.nearest, map_gate)
        if progress:
            progress("solve", fname, n_done, total)
        fs = fsl.solve()
        slams[fname] = fsl
        floors[fname] = fs
    walk_of = {fname: [pc.walk for pc in fs.pieces] for fname, fs in floors.items()}
    # EM with the crowd map: each fold of walks located against the map of the others
    folds = np.arange(len(walks)) % max(cfg.em_folds, 2)
    em_cache: dict = {}
    for rnd in range(cfg.em_rounds):
        labels, label_walk = _all_labels(floors, walk_of)
        if not set_em_fixes(slams.values(), labels, label_walk, lambda w: int(folds[w]), cfg, em_cache):
            break
        moves = []
        prev = dict(floors)
        for n_done, (fname, fsl) in enumerate(sorted(slams.items())):
            if progress:
                progress(f"em {rnd + 1}", fname, n_done, total)
            old = floors[fname]
            new = fsl.solve()
            both = np.isfinite(old.pos[:, 0]) & np.isfinite(new.pos[:, 0])
            both &= fsl.node_status(old.status) != RELATIVE
            if both.any():
                moves.append(np.linalg.norm(new.pos[both] - old.pos[both], axis=1))
            new.em_moves = old.em_moves + [float(np.median(moves[-1])) if moves and both.any() else 0.0]
            floors[fname] = new
        med = float(np.median(np.concatenate(moves))) if moves else 0.0
        if med < cfg.em_stop_m and not (cfg.em_while_anchoring and any(anchored_more(prev[f], floors[f]) for f in floors)):
            break
    labels, label_walk = _all_labels(floors, walk_of)
    if progress:
        progress("done", "", total, total)
    return SlamResult(walks, names, floors, labels, label_walk, time.monotonic() - t0)

"""Crowd SLAM live (issue #21): one site's crowd-SLAM state, driven walk by walk and re-solved per floor.

A pure library: no network, no database. The server worker loads stored walks and tracks into a
:class:`CrowdSlam` (:meth:`~CrowdSlam.hold`), gives it every finished walk (:meth:`~CrowdSlam.add_walk`),
re-solves floors in batch now and then (:meth:`~CrowdSlam.rebuild_floor`) and stores what they return.
Two paths (slam.md 4.9):

* **incremental** (:meth:`~CrowdSlam.add_walk`, about a second): the walk's pieces (:mod:`.walkgraph`),
  loop candidates of its scans against the held walks of its floor
  (:meth:`.frontend.LoopDetector.detect_incremental`: the floor's similarity -> distance model and its
  fingerprint vectors are kept between calls; only the old scans a new scan lists get their own top-k
  scored), beacon co-passes, fixes from the served map (:meth:`~CrowdSlam.set_map`), then a solve of
  ITS variables only - its nodes, its per-segment (scale, bias), the positions of the beacons it passed
  - with the nodes of the walks it links to held at their current solution (:func:`.solve.solve`'s
  held variables: a system of one walk's size). A held walk never moves.
* **batch** (:meth:`~CrowdSlam.rebuild_floor`, about half a minute per 100 walks): :func:`.pipeline.run_slam`
  on the held walks of the floor (loops, anchoring by marks / map fixes / plan search, robust solve, EM
  with the crowd map of the floor's labels), which replaces the floor's held solution.

**Anchoring of an added walk** follows the batch's rules for one piece: its own survey marks
(``marks``), else map fixes that agree on one placement (``map``, :func:`.register.register_walk`), else
accepted loops or beacon co-passes to held walks: ``loops`` when one of those is tied to the site frame
by marks, fixes or loops, ``plan`` when all are plan-placed; a walk linked only to "relative" walks
joins their frame (the group's own, never an absolute position); a walk linked to nothing is placed by
the plan search alone when that is unambiguous (:func:`.anchoring.anchor_points`; a single walk rarely
is), else stays relative. Links into another frame than the walk's are dropped from its solve (audit
reason ``other-frame``): an absolute walk cannot be tied to coordinates of an unplaced group. Grouping
relative walks into a placeable component, or re-placing held walks, is the batch's job.

**The floor of a walk** is the one it names, except that with ``SlamConfig.floor_vote`` (the default; the
figures there) a crowd walk on one floor without survey marks is taken as a claim (a phone's floor
estimate), and it is held on the floor its own scans name through the served map, or the vote map when
one is set (:meth:`~CrowdSlam.set_vote_map`; :meth:`~CrowdSlam.vote_floor`: at least
``floor_vote_min_fixes`` fixes past the mapped-distance gate, a ``floor_vote_share`` majority), or on the
floor of its stored absolute track (where a solve put it). On ILC site1 (eval crowd, F = 0.1) 32 of the 77 walks a batch left relative had most of
their gated fixes on another floor than the recording's folder, about 2-4 m from the truth in the plane
for those with enough gated fixes: without the vote they could link to nothing on the floor they named.

**Covariance of an added walk.** The held neighbours are held, so the marginal of the walk's nodes
(H^-1 of its own system) would be conditional on their positions being exact. Each loop to a held node
j therefore carries that node's own uncertainty: its variance is sigma_in^2 + tr(Cov_j)/2 per axis
(marginalising p_j ~ N(p_j*, Cov_j) out of p_i - p_j ~ N(0, sigma_in^2 I), correlations between
neighbours ignored).

**The corrected track** (:class:`hybridloc.types.CorrectedTrack`): a point at every step (its time) and
every scan of the walk (its label time: a WiFi scan's node time, the median last-seen time of its fresh
readings, :func:`.walkgraph.scan_node_time`; other scans their time - the times :func:`.pipeline._labels`
labels them at, so labels read from a stored track equal the solver's). Positions:
:meth:`.pipeline.FloorSolution.track` (the dead-reckoned shape mapped by the segment's (a, b) and closed
through both nodes). Covariance between nodes i and j at time fraction u:

    Cov(t) = (1 - u) C_i + u C_j + u (1 - u) S_ij

C the nodes' marginals; the linear blend bounds Var((1 - u) p_i + u p_j) from above whatever their
correlation (their difference has a non-negative variance), and u (1 - u) S_ij is the Brownian bridge of
the edge's white dead-reckoning error S_ij = C(t_j) - C(t_i) (walkgraph) pinned at both nodes. A walk
cut into floor pieces gives one track, each point with its piece's floor (a step or scan outside every
piece - on the stairs - takes the nearest piece in time). Scale and heading bias: the median over the
walk's segments of a and of atan2(b, a).

**Quarantine** (issue #21 point 5: counted, not fatal). A walk is quarantined, never held, when
(:func:`check_track` and the solve's own diagnostics):

* *diverged*: a non-finite position or covariance; the solve stopped unsettled with a last step above
  ``MAX_UNSETTLED_STEP_M`` (10 m: beyond the widest sd of any factor - loops' sigma_in reach ~8 m - an
  iterate has left what the factors support; below it the solve is in a bounded cycle: Gauss-Newton on
  the walkable factor's kink at its margin can cycle between states a few metres apart, site1 F1: 2.5 m,
  each a valid answer within the labels' sds); a segment's step-length scale |s - 1| > ``MAX_SCALE_DEV`` (the prior is
  N(1, 0.1^2): 5 sd, no phone's step model is that wrong); an absolute position sd above ``MAX_SD_M``
  (a tenth of the solver's 1 km gauge sd: the walk is not constrained at all); or a corrected step
  longer than ``MAX_STEP_M`` (a walking step is under ~1 m, at the scale bound 1.5 m);
* *off-walkable*: more than ``MAX_OUTSIDE_SHARE`` of an absolute track's points farther than
  ``OUTSIDE_MARGIN_M`` outside its floor's walkable area. The margin: the walkable factor is flat to
  0.3 m and has sd 0.5 m, so a solved point beyond 0.3 + 3 x 0.5 = 1.8 m (rounded to 2 m) is a 3-sigma
  residual of that factor, and it is also beyond what a label sd of metres explains. The share: where
  the plan itself is wrong (an undrawn door or shop) a correct walk spends a few of its seconds outside;
  a quarter of its points means the walk as a whole is in the wrong place (site1 batch tracks: see
  tests/test_slam_online.py);
* *error*: an exception while adding or solving that walk (logged with its traceback).

In a batch, walks that fail these checks after its first solve are dropped and the floor solved
again without them (``MAX_BATCH_RESOLVES``: once); later failures get no other solve. The joint solve
is what failed for them - on site1 it does not settle within its 30 iterations and leaves a few walks
linked by loops at scales of 0.2-0.5 or 1.6, walks that were fine when added alone - so each then takes
the incremental path against the floor's new solution, and is quarantined only if it fails there too.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from ..radio.survey import LabelledScan, label_scans
from ..sim.building import graph_components
from ..types import TRACK_ANCHORS, CorrectedTrack, FloorPlan, RfScan, Walk, Waypoints
from .frontend import FloorVectors, FrontendConfig, Loop, LoopDetector, WalkScans, floor_vectors, offsets_from_reference
from .pipeline import (
    GATE_K,
    LOOPS,
    MAP,
    MARKS,
    PLAN,
    RELATIVE,
    FloorSlam,
    FloorSolution,
    LoopRecord,
    SlamConfig,
    _labels,
    _similarity_fit,
    _walkable_points,
    anchored_more,
    locate_pieces,
    mapped_distance_gate,
    set_em_fixes,
)
from .walkgraph import KIND_SCAN, WalkPiece, scan_node_time, walk_pieces

log = logging.getLogger(__name__)

#: quarantine thresholds (module docstring, "Quarantine")
MAX_SCALE_DEV = 0.5
MAX_STEP_M = 2.0
MAX_SD_M = 100.0
MAX_UNSETTLED_STEP_M = 10.0
OUTSIDE_MARGIN_M = 2.0
MAX_OUTSIDE_SHARE = 0.25
#: a batch drops the walks that fail its checks and solves again at most this many times (each costs a
#: loop detection and a solve: ~12 s on a site1 floor; later failures take the incremental path directly)
MAX_BATCH_RESOLVES = 1
#: the sd given to a label whose covariance is unknown, m (as pipeline._labels)
UNKNOWN_LABEL_SD_M = 5.0

_RANK = {a: i for i, a in enumerate(TRACK_ANCHORS)}  # marks first: the best anchoring of a walk's pieces


# ------------------------------------------------------------------------------------------ outcomes
@dataclass
class WalkOutcome:
    """What adding (or re-solving) one walk gave.

    ``track``: a point at every step and scan of the walk (None when the walk gave no track: fewer than
    two steps, no floor, or no finite solution); ``loops``: every loop candidate touching the walk,
    accepted and rejected, with its weight (``walk_a``/``walk_b`` are ``str(walk_id)``; ``node_a``/``node_b``
    the node's index in its walk's piece); ``quarantined``: "" or the reason (module docstring); a
    quarantined walk is not held, its track (if finite) is returned for inspection only."""

    walk_id: int
    track: CorrectedTrack | None
    loops: list[LoopRecord]
    quarantined: str = ""
    seconds: float = 0.0


@dataclass
class FloorOutcome:
    """One floor of a batch re-solve (the server checkpoints per floor): every walk of the floor,
    the floor's loop audit and its figures (``stats``: walks, pieces, anchored counts by status,
    quarantined, readded (walks the joint solve could not fit, placed on their own), loop candidates /
    accepted, em_rounds and em_moves (median label move per round, m), converged and last_step (m),
    resolves, seconds)."""

    floor: str
    walks: dict[int, WalkOutcome]
    loops: list[LoopRecord]
    stats: dict


class _Token:
    """A named singleton that stays itself through pickling (it pickles as a reference to the module's
    global of its name)."""

    def __init__(self, name: str):
        self.name = name

    def __reduce__(self) -> str:
        return self.name

    def __repr__(self) -> str:
        return self.name


_ABSENT = _Token("_ABSENT")  # a walk without an entry in one of the site's per-walk dictionaries (FloorsMark)
_SAME_WALK = _Token("_SAME_WALK")  # FloorsDelta: the walk's own Walk object (not sent back)


@dataclass
class FloorsMark:
    """References to a group of floors' state and to their walks' entries at one moment
    (:meth:`CrowdSlam.mark_floors`)."""

    names: frozenset[str]
    walks: set[int]
    held: dict[str, dict]
    solutions: dict[str, dict]
    detectors: dict[str, Any]
    rows: dict[str, dict]
    walk_values: dict[str, dict[int, Any]]
    outside: dict[str, frozenset]
    memo_keys: set[int]
    next_frame: int


@dataclass
class FloorsDelta:
    """What re-solving a mark's floors changed (:meth:`CrowdSlam.floors_delta`): per floor, per walk
    dictionary, the walks dropped, the served map's new search rows, the next frame id."""

    floors: dict[str, dict]
    walks: dict[str, dict]
    dropped: set[int]
    memo: dict[int, tuple]
    next_frame: int


# ------------------------------------------------------------------------------------------ held state
@dataclass
class _Held:
    """One piece of a held walk on its floor and its current solution (None: held without one)."""

    walk_id: int
    j: int  # index of the piece among its walk's pieces
    piece: WalkPiece  # node0 = 0, nuisance = 0..n_segments-1
    pos: np.ndarray | None = None  # (n, 2)
    cov: np.ndarray | None = None  # (n, 2, 2), NaN where not computed
    nuisance: np.ndarray | None = None  # (n_segments, 2)
    status: str = RELATIVE
    frame: int = 0  # 0: the site frame (anchored); else the id of the relative group's own frame

    def solution(self) -> FloorSolution:
        """The piece as a one-piece :class:`FloorSolution` (for its track)."""
        assert self.pos is not None and self.cov is not None and self.nuisance is not None
        return FloorSolution(self.piece.floor, [self.piece], self.pos, self.cov, self.nuisance, [self.status], [])


def _fresh(pc: WalkPiece) -> WalkPiece:
    """A copy of the piece numbered on its own (node0 0, nuisances 0..): graphs renumber their copies."""
    return dataclasses.replace(pc, node0=0, nuisance=np.arange(pc.n_segments, dtype=np.int64))


def _walk_scans(pc: WalkPiece, serial: int) -> WalkScans | None:
    """The front end's view of a piece (as FloorSlam._walk_scans): its WiFi scan nodes, numbered within the piece."""
    sel = np.array(
        [i for i in np.flatnonzero((pc.kind == KIND_SCAN) & (pc.scan >= 0)) if pc.scans[int(pc.scan[i])].technology.value == "wifi"], dtype=np.int64
    )
    if len(sel) == 0:
        return None
    return WalkScans(serial, pc.floor, sel, pc.t[sel], pc.q[sel], pc.C[sel], [pc.scans[int(pc.scan[i])] for i in sel])


class _Floor:
    """The held state of one floor: its pieces and their solution, the field, the front end's model and
    the fingerprint rows of every held piece (kept so that an added walk costs its own rows only)."""

    def __init__(self, name: str, plan: FloorPlan | None, cfg: SlamConfig):
        from .floorplan import WalkableField

        self.name = name
        self.cfg = cfg
        self.fcfg: FrontendConfig = cfg.frontend if isinstance(cfg.frontend, FrontendConfig) else FrontendConfig()
        self.field = None
        self.points: np.ndarray | None = None
        if plan is not None and name in plan.floor_names:
            self.field = WalkableField.from_floor(plan.floor(name))
            self.points = _walkable_points(plan.floor(name), 2000, np.random.default_rng(0))
        self.held: dict[tuple[int, int], _Held] = {}
        self.scans: dict[tuple[int, int], WalkScans] = {}  # the front end's view of each held piece
        self.serial = 0
        self.detector: LoopDetector | None = None
        self.fit_pieces = 0  # pieces held when the detector's model was fitted
        self.loops: list[LoopRecord] = []  # the floor's loop audit: the last batch's, then each add's
        # fingerprint rows: key -> (non-zeros per row, column ids, values); columns shared by the floor
        self._col: dict[str, int] = {}
        self._rows: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    # -------------------------------------------------------------- pieces
    def put(self, h: _Held) -> None:
        key = (h.walk_id, h.j)
        self.held[key] = h
        ws = _walk_scans(h.piece, self.serial)
        self.serial += 1
        if ws is not None:
            self.scans[key] = ws
        else:
            self.scans.pop(key, None)

    def drop_walk(self, walk_id: int) -> None:
        for key in [k for k in self.held if k[0] == walk_id]:
            del self.held[key]
            self.scans.pop(key, None)
        for key in [k for k in self._rows if k[0] == walk_id]:
            del self._rows[key]
        name = str(walk_id)
        self.loops = [lp for lp in self.loops if lp.walk_a != name and lp.walk_b != name]

    # -------------------------------------------------------------- front end
    def model(self, extra: WalkScans | None = None) -> LoopDetector | None:
        """The fitted front end: the last batch's, refitted here on the held pieces (and ``extra``) when
        none exists or the floor has doubled since the fit (amortised: a fit reads the whole floor)."""
        n = len(self.scans) + (extra is not None)
        if self.detector is not None and self.detector.model is not None and n < 2 * max(self.fit_pieces, 1):
            return self.detector
        ws = list(self.scans.values()) + ([extra] if extra is not None else [])
        det = LoopDetector(self.cfg.frontend, walkable={self.name: self.points} if self.points is not None else None)  # type: ignore[arg-type]
        try:
            det.fit(ws)
        except ValueError as exc:  # too few pairs inside walks to learn the similarity model
            log.info("floor %s: no similarity model yet (%s)", self.name, exc)
            return self.detector if self.detector is not None and self.detector.model is not None else None
        self.set_detector(det, n)
        return det

    def set_detector(self, det: LoopDetector, n_pieces: int) -> None:
        self.detector, self.fit_pieces = det, n_pieces
        if self.fcfg.remove_offset:  # the rows depend on the model's references
            self._rows.clear()

    def _row_block(self, key, ws: WalkScans) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if key not in self._rows:
            off = None
            det = self.detector
            if self.fcfg.remove_offset and det is not None and det.model is not None and self.name in det.model.refs:
                off = offsets_from_reference([ws], det.model.refs[self.name], self.fcfg.max_age_s)
            fv = floor_vectors([ws], self.fcfg, off)
            cols = np.array([self._col.setdefault(t, len(self._col)) for t in fv.tx], dtype=np.int64)
            R = fv.R.tocsr()
            self._rows[key] = (np.diff(R.indptr), cols[R.indices] if len(cols) else R.indices.astype(np.int64), R.data.copy())
        return self._rows[key]

    def vectors(self, order: list[tuple[tuple[int, int], WalkScans]]) -> FloorVectors:
        """The floor vectors (frontend.floor_vectors) of the given pieces in this order, from the kept rows."""
        import scipy.sparse as sp

        blocks = [self._row_block(k, ws) for k, ws in order]
        nnz = np.concatenate([b[0] for b in blocks]) if blocks else np.zeros(0, np.int64)
        indptr = np.r_[0, np.cumsum(nnz)].astype(np.int64)
        idx = np.concatenate([b[1] for b in blocks]) if blocks else np.zeros(0, np.int64)
        val = np.concatenate([b[2] for b in blocks]) if blocks else np.zeros(0)
        R = sp.csr_matrix((val, idx, indptr), shape=(len(nnz), len(self._col)))
        R.sort_indices()
        n_rows = [len(ws.scans) for _, ws in order]
        walk_row = np.repeat(np.arange(len(order)), n_rows)
        scan_row = np.concatenate([np.arange(n) for n in n_rows]) if n_rows else np.zeros(0, np.int64)
        return FloorVectors(R, walk_row.astype(int), scan_row.astype(int), list(self._col))


# ------------------------------------------------------------------------------------------ the site
class CrowdSlam:
    """The crowd SLAM of one site, live (module docstring). ``plan``: the site's floor plan (walkable
    fields, plan anchoring, the off-walkable check); ``config``: :class:`.pipeline.SlamConfig`."""

    def __init__(self, site: str, plan: FloorPlan | None, config: SlamConfig | None = None):
        self.site = site
        self.plan = plan
        self.cfg = config or SlamConfig()
        #: every walk held (by walk_id)
        self.walks: dict[int, Walk] = {}
        #: the current track of each held walk (None: held without a solution)
        self.tracks: dict[int, CorrectedTrack | None] = {}
        #: walks quarantined by add_walk or a batch, with the reason (not held; counted in coverage)
        self.quarantined: dict[int, str] = {}
        self._quarantined_walks: dict[int, Walk] = {}
        self._pieces: dict[int, list[WalkPiece]] = {}
        self._scan_floor: dict[int, list[str]] = {}  # floor of each scan of each walk (coverage)
        self._floors: dict[str, _Floor] = {}
        self._next_frame = 1
        self._map = None  # RadioMap | None
        self._locator: Any = None  # KnnLocator of the map
        #: walk id -> (the floor it names, the floor it is held on): single-floor walks without marks
        #: moved by their own fingerprints (:meth:`_walk_pieces`)
        self.floor_moves: dict[int, tuple[str, str]] = {}
        self._gate = math.inf
        #: the map the floor vote reads (set_vote_map), when not the served one: (locator, gate, technology)
        self._vote: tuple[Any, float, str] | None = None
        #: walks dropped since :meth:`mark_floors` (None: not counted)
        self._dropped: set[int] | None = None

    # -------------------------------------------------------------- map
    def set_map(self, radio_map) -> None:
        """The map the server serves (survey + crowd): its fixes place added walks (as run_slam's
        ``radio_map``). A batch leaves out the references whose ``source`` is a crowd walk of the floor
        it solves (``str(walk_id)``, as :meth:`labels` names them; :meth:`_fed_back`): a walk is not
        fixed to its own labels."""
        self._map = radio_map if radio_map is not None and radio_map.references else None
        self._locator, self._gate = self._knn(self._map.references) if self._map is not None else (None, math.inf)

    def _knn(self, refs: list[LabelledScan]) -> tuple[Any, float]:
        """The kNN locator of ``refs`` (the server's settings) and its mapped-distance gate."""
        from ..radio.locate import KnnLocator

        # memo on: the served map's locator places every walk's scans again in each batch (and the vote
        # map's asks the same walks' floors), the same answers each time
        loc = KnnLocator(refs, k=self.cfg.knn_k, max_age_s=self.cfg.knn_max_age_s, memo=True)
        return loc, mapped_distance_gate(refs, self.cfg, locator=loc.with_k(GATE_K))

    def set_vote_map(self, radio_map) -> None:
        """The map :meth:`vote_floor` reads, when it is not the one that places walks (:meth:`set_map`):
        the server's newest crowd map. Its labels cover where the survey's do not, so it names more walks'
        floors, while its fixes, fed back, place walks worse than the survey's (server/slam_child.py). A
        walk voted is one without an absolute track, so it has no label of its own in the map."""
        self._vote = (*self._knn(radio_map.references), radio_map.technology) if radio_map is not None and radio_map.references else None

    def _fed_back(self, walk_ids) -> set[str]:
        """The map sources (``str(walk_id)``) a solve of ``walk_ids`` must not be fixed to: the labels of
        its crowd walks, which are its own previous solution fed back. A survey walk's labels stay: they
        come from its marks (sd 0.5 m), the survey map's references are the same scans labelled by the
        same marks (server/rebuild.py, sourced by device), and leaving them out left a batch on a crowd
        map - a restarted server's, or ``slam rebuild``'s - with no fix from the survey on the floor it
        solved. The other floors' crowd labels stay: leaving out every crowd walk's (a survey-only view,
        as the live SLAM child's survey map) measured worse on a re-solve of site1's eval crowd database
        (coverage 66.2 -> 71.8 % but corrected mean 6.61 -> 8.43 m)."""
        return {str(w) for w in walk_ids if not self.walks[w].marks}

    def _map_fixes(self, pieces: list[WalkPiece], exclude: set[str] | None = None) -> dict[int, list]:
        if self._map is None:
            return {}
        loc, gate = self._locator, self._gate
        if exclude and any(r.source in exclude for r in self._map.references):
            refs = [r for r in self._map.references if r.source not in exclude]
            if not refs:
                return {}
            loc, gate = self._knn(refs)
        assert loc is not None
        return locate_pieces(pieces, partial(loc.locate_many, regions=False), self.cfg, self._map.technology, loc.nearest, gate)

    # -------------------------------------------------------------- state
    def _floor(self, name: str) -> _Floor:
        if name not in self._floors:
            self._floors[name] = _Floor(name, self.plan, self.cfg)
        return self._floors[name]

    def floors(self) -> list[str]:
        """Floors with held walks."""
        return sorted(n for n, f in self._floors.items() if f.held)

    def _new_frame(self) -> int:
        self._next_frame += 1
        return self._next_frame - 1

    def _walk_pieces(self, walk: Walk, track: CorrectedTrack | None = None) -> list[WalkPiece]:
        """The walk's pieces, each on its floor: the floor the walk names, except for a single-floor walk
        without survey marks, whose floor is the server's - the floor of its absolute ``track`` (where a
        solve put it before), else the one its fingerprints name (:meth:`vote_floor`)."""
        if walk.walk_id is None:
            raise ValueError("CrowdSlam: a walk needs an integer walk_id")
        wid = int(walk.walk_id)
        pieces = walk_pieces(walk, wid, self.cfg.walk, name=str(wid))
        if not self.cfg.floor_vote or len(pieces) != 1 or (pieces[0].mark >= 0).any():
            return pieces
        pc = pieces[0]
        if track is not None and track.anchored != RELATIVE:
            held_on = set(track.floor)
            moved = held_on.pop() if len(held_on) == 1 else None
        else:
            moved = self.vote_floor(pc)
        if moved is None or moved == pc.floor:
            self.floor_moves.pop(wid, None)
            return pieces
        if self.floor_moves.get(wid) != (pc.floor, moved):
            log.info("walk %s: on floor %s by its fingerprints (it names %s)", wid, moved, pc.floor)
        self.floor_moves[wid] = (pc.floor, moved)
        return [dataclasses.replace(pc, floor=moved)]

    def held_floors(self, walk: Walk, track: CorrectedTrack | None = None) -> list[str]:
        """The floors ``walk`` would be held on (with its stored ``track``): those of its pieces
        (:meth:`_walk_pieces`: the floors it names where it has a piece, or with ``floor_vote`` the
        server's choice; without the vote no map is read), else the floors it names."""
        return sorted({pc.floor for pc in self._walk_pieces(walk, track)} or set(walk.floors))

    def revote_floors(self) -> list[int]:
        """Ask every held walk that is not absolutely placed (no track, or a relative one) for its floor
        again with the map served now (:meth:`_walk_pieces`), and hold again, with its track, each walk
        whose floor changes; a batch starts with this (a map grown since a walk was added may name its
        floor now). Returns the walks moved."""
        moved: list[int] = []
        if not self.cfg.floor_vote:  # every walk is on the floor it names: nothing to ask
            return moved
        for wid, walk in list(self.walks.items()):
            track = self.tracks.get(wid)
            if track is not None and track.anchored != RELATIVE:
                continue
            now = {pc.floor for pc in self._pieces.get(wid, [])}
            if {pc.floor for pc in self._walk_pieces(walk, track)} != now:
                self.hold(walk, track)
                moved.append(wid)
        return moved

    def vote_floor(self, piece: WalkPiece) -> str | None:
        """The floor the piece's own scans name through the served map, or None when they do not name
        one clearly (:class:`.pipeline.SlamConfig` ``floor_vote_*``): scans past the mapped-distance gate
        or with a floor probability below ``fix_min_floor_prob`` do not vote."""
        if self._vote is not None:
            loc, gate, tech = self._vote
        elif self._locator is not None and self._map is not None:
            loc, gate, tech = self._locator, self._gate, self._map.technology
        else:
            return None
        cfg = self.cfg
        scans = [s for s in piece.scans if s.technology.value == tech]
        if len(scans) < cfg.floor_vote_min_fixes:
            return None
        near = loc.nearest(scans)[0][:, 0] <= gate
        votes = Counter(
            r.fix.floor
            for r, ok in zip(loc.locate_many(scans, regions=False), near)
            if ok and r.fix is not None and r.fix.floor and r.fix.floor_prob >= cfg.fix_min_floor_prob
        )
        n = sum(votes.values())
        if n < cfg.floor_vote_min_fixes:
            return None
        floor, top = votes.most_common(1)[0]
        return floor if top >= cfg.floor_vote_share * n else None

    def _drop(self, walk_id: int) -> None:
        if self._dropped is not None:
            self._dropped.add(walk_id)
        for f in self._floors.values():
            f.drop_walk(walk_id)
        self.walks.pop(walk_id, None)
        self.tracks.pop(walk_id, None)
        self._pieces.pop(walk_id, None)

    def _remember_floors(self, walk: Walk, pieces: list[WalkPiece]) -> None:
        self._scan_floor[int(walk.walk_id)] = _scan_floors(walk, pieces, self.cfg)  # type: ignore[arg-type]

    def remove_walk(self, walk_id: int) -> None:
        """Forget a walk (held or quarantined). The others keep their solution until the next batch."""
        self._drop(int(walk_id))
        self.floor_moves.pop(int(walk_id), None)
        self.quarantined.pop(int(walk_id), None)
        self._quarantined_walks.pop(int(walk_id), None)
        self._scan_floor.pop(int(walk_id), None)

    def _quarantine(self, walk: Walk, reason: str) -> None:
        wid = int(walk.walk_id)  # type: ignore[arg-type]
        self._drop(wid)
        self.quarantined[wid] = reason
        self._quarantined_walks[wid] = walk

    def hold(self, walk: Walk, track: CorrectedTrack | None, quarantined: str = "") -> None:
        """Take a stored walk with its stored track as the current solution, without solving (a server
        restart). The nodes of each piece are read from the track's points on the piece's floor: a
        WiFi scan or beacon node, what loops and co-passes attach to, is a scan point of the track (the
        solver's position exactly); other nodes are interpolated in time between the points around them.
        ``quarantined``: the stored reason of a quarantined walk - it is then only counted (coverage),
        not held."""
        wid = int(walk.walk_id)  # type: ignore[arg-type]
        self.remove_walk(wid)
        pieces = self._walk_pieces(walk, track)
        if quarantined:
            self._remember_floors(walk, pieces)
            self.quarantined[wid] = quarantined
            self._quarantined_walks[wid] = walk
            return
        self.walks[wid] = walk
        self._pieces[wid] = pieces
        self._remember_floors(walk, pieces)
        self.tracks[wid] = track
        frame = 0 if track is None or track.anchored != RELATIVE else self._new_frame()
        for j, pc in enumerate(pieces):
            h = _Held(wid, j, _fresh(pc))
            if track is not None:
                on = np.array([f == pc.floor for f in track.floor], bool)
                if on.any():
                    tt, xy, cv = track.t[on], track.pos_enu[on], track.cov[on]
                    h.pos = np.column_stack([np.interp(pc.t, tt, xy[:, 0]), np.interp(pc.t, tt, xy[:, 1])])
                    nxt = np.clip(np.searchsorted(tt, pc.t), 0, len(tt) - 1)
                    prv = np.maximum(nxt - 1, 0)
                    near = np.where(np.abs(tt[prv] - pc.t) <= np.abs(tt[nxt] - pc.t), prv, nxt)
                    h.cov = cv[near].copy()
                    # (a, b) = s (cos beta, sin beta): the track's scale s and bias beta (types.CorrectedTrack)
                    ab = track.scale * np.array([math.cos(track.heading_bias), math.sin(track.heading_bias)])
                    h.nuisance = np.tile(ab, (pc.n_segments, 1))
                    h.status, h.frame = track.anchored, frame
            self._floor(pc.floor).put(h)

    # -------------------------------------------------------------- incremental
    def add_walk(self, walk: Walk) -> WalkOutcome:
        """Add one walk (module docstring, incremental path); on success it is held. Any error while
        adding it quarantines the walk ("error: ...") instead of propagating; the held walks are left
        exactly as they were."""
        t0 = time.monotonic()
        if walk.walk_id is None:
            raise ValueError("CrowdSlam.add_walk: the walk needs an integer walk_id")
        wid = int(walk.walk_id)
        self.remove_walk(wid)
        loops: list[LoopRecord] = []
        try:
            pieces = self._walk_pieces(walk)
            self.walks[wid] = walk
            self._pieces[wid] = pieces
            self._remember_floors(walk, pieces)
            reason = ""
            for j, pc in enumerate(pieces):
                h, recs, reason = self._add_piece(wid, j, pc)
                loops += recs
                self._floor(pc.floor).put(h)
                if reason:
                    break
            track = None
            if pieces:  # built even for a failed walk when it can be (returned for inspection)
                track, why = self._track(wid)
                reason = reason or why
            if track is not None and not reason:
                reason = check_track(track, self.plan, {n: f.field for n, f in self._floors.items() if f.field is not None})
        except Exception as exc:  # noqa: BLE001 - one walk's failure is that walk's outcome, never the worker's
            log.exception("walk %s: adding it failed", wid)
            reason, track = f"error: {type(exc).__name__}: {exc}", None
        if reason:
            self._quarantine(walk, reason)
            return WalkOutcome(wid, track, loops, reason, time.monotonic() - t0)
        self.tracks[wid] = track
        for fname in {pc.floor for pc in self._pieces[wid]}:
            self._floor(fname).loops += [lp for lp in loops if lp.floor == fname]
        return WalkOutcome(wid, track, loops, "", time.monotonic() - t0)

    def _add_piece(self, wid: int, j: int, piece: WalkPiece) -> tuple[_Held, list[LoopRecord], str]:
        """Solve one new piece against the held pieces of its floor: (its held state, its loop
        records, a quarantine reason or "")."""
        from .anchoring import anchor_points
        from .solve import solve

        cfg = self.cfg
        fl = self._floor(piece.floor)
        pc = _fresh(piece)
        key = (wid, j)
        # ---------------------------------------------------------- front end: loops against the floor
        ws_new = _walk_scans(pc, fl.serial)
        old = [(k, ws) for k, ws in fl.scans.items() if k[0] != wid or k[1] < j]
        cands: list[Loop] = []
        by_serial = {ws.walk: k for k, ws in old}
        if ws_new is not None and old:
            det = fl.model(ws_new)
            if det is not None:
                V = fl.vectors(old + [(key, ws_new)])
                cands = det.detect_incremental([ws_new], [ws for _, ws in old], V)
        # each candidate: (the held piece, its node, the new piece's node); the held piece is always A
        # (its serial is smaller)
        links = []
        for n, lp in enumerate(cands):
            if lp.accepted:
                hk = by_serial[lp.walk_a]
                links.append(("wifi", n, hk, int(lp.node_a), int(lp.node_b), float(lp.sigma_in)))
        passes = []  # beacon co-passes: (beacon, held key, held node, new node, dBm held, dBm new)
        for bi, b in enumerate(pc.beacons):
            i_new = int(np.flatnonzero(pc.beacon == bi)[0])
            for hk, h in fl.held.items():
                if h.pos is None or hk == key or b not in h.piece.beacons:
                    continue
                hb = h.piece.beacons.index(b)
                passes.append((b, hk, int(np.flatnonzero(h.piece.beacon == hb)[0]), i_new, float(h.piece.beacon_dbm[hb]), float(pc.beacon_dbm[bi])))
        # ---------------------------------------------------------- anchors of the new piece
        fsl = FloorSlam(fl.name, [pc], fl.field, cfg)
        fsl.map_fixes = self._map_fixes([pc])
        anchors = fsl.anchors([0])
        own_abs = 0 in anchors.marks or 0 in anchors.fixes
        linked = [fl.held[lk[2]] for lk in links if fl.held[lk[2]].pos is not None] + [fl.held[p[1]] for p in passes]
        anchored_nb = [h for h in linked if h.frame == 0]
        if own_abs or anchored_nb:
            frame = 0
        else:
            frames = Counter(h.frame for h in linked)
            frame = frames.most_common(1)[0][0] if frames else -1  # -1: no neighbour (own frame)
        keep = {(h.walk_id, h.j) for h in linked if h.frame == frame}
        nb_keys = sorted(keep)
        # ---------------------------------------------------------- the graph: the new piece + held neighbours
        nb = [fl.held[k] for k in nb_keys]
        fsl.pieces = [pc] + [_fresh(h.piece) for h in nb]
        fsl._number()
        idx_of = {k: 1 + n for n, k in enumerate(nb_keys)}
        loops_in: list[Loop] = []
        loop_of: dict[int, int] = {}  # candidate index -> index in fsl.loops
        for _, n, hk, i_old, i_new, sig in [lk for lk in links if lk[2] in keep]:
            h = fl.held[hk]
            c = h.cov[i_old] if h.cov is not None else np.full((2, 2), np.nan)
            extra = 0.5 * float(np.trace(c)) if np.all(np.isfinite(c)) else 0.0
            lp = cands[n]
            loop_of[n] = len(loops_in)
            loops_in.append(
                Loop(
                    0,
                    int(fsl.pieces[idx_of[hk]].node0 + i_old),
                    lp.t_a,
                    1,
                    int(i_new),
                    lp.t_b,
                    lp.similarity,
                    lp.p_inlier,
                    math.sqrt(sig**2 + extra),
                    True,
                )
            )
        fsl.loops = loops_in
        fsl.beacons = {}
        for b, hk, i_old, i_new, d_old, d_new in passes:
            if hk in keep:
                obs = fsl.beacons.setdefault(b, [(0, i_new, d_new)])
                obs.append((idx_of[hk], i_old, d_old))
        status, init, plan_prior = RELATIVE, pc.q.copy(), {}
        if 0 in anchors.marks:
            pts = anchors.marks[0]
            T, t = _similarity_fit(np.asarray([pc.q[i] for i, _ in pts]), np.asarray([z for _, z in pts]))
            status, init = MARKS, pc.q @ T.T + t
        elif 0 in anchors.fixes:
            reg = fsl.registrations[0]
            status, init = MAP, pc.q @ reg.T.T + reg.t
        elif nb:
            # placed along its links (as FloorSlam._relative_layout): the median offset to the neighbours
            offs = [fl.held[hk].pos[i_old] - pc.q[i_new] for _, _, hk, i_old, i_new, _ in links if hk in keep]  # type: ignore[index]
            offs += [fl.held[hk].pos[i_old] - pc.q[i_new] for _, hk, i_old, i_new, _, _ in passes if hk in keep]  # type: ignore[index]
            init = pc.q + np.median(np.asarray(offs), axis=0)
            if frame == 0:
                status = LOOPS if any(h.status in (MARKS, MAP, LOOPS) for h in nb) else PLAN
        elif fl.field is not None:
            an = anchor_points(pc.q, fl.field, min_log_ratio=cfg.anchor_min_log_ratio)
            if not an.ambiguous:
                init = pc.q @ an.T.T + an.t
                plan_prior[0] = (init, cfg.plan_anchor_sd_m * math.sqrt(pc.n))
                status, frame = PLAN, 0
        if status == RELATIVE and frame <= 0:
            frame = self._new_frame()
        absolute = status != RELATIVE
        inits: dict[int, Any] = {0: init}
        for k in nb_keys:
            inits[idx_of[k]] = fl.held[k].pos
        all_idx = list(range(len(fsl.pieces)))
        g, local0, nuis, loop_ids = fsl._graph(all_idx, inits, anchors, plan_prior, with_field=False)
        n_piece_nodes = sum(p.n for p in fsl.pieces)
        free_nodes = np.r_[np.arange(pc.n), np.arange(n_piece_nodes, g.n_nodes)]
        sol = solve(g, cfg.solve, free_nodes=free_nodes, free_nuisances=nuis[0])  # type: ignore[arg-type]
        if absolute and fl.field is not None:
            inits[0] = sol.pos[: pc.n]
            g, local0, nuis, loop_ids = fsl._graph(all_idx, inits, anchors, plan_prior, with_field=True)
            sol = solve(g, cfg.solve, x0=sol, free_nodes=free_nodes, free_nuisances=nuis[0])  # type: ignore[arg-type]
        pos = sol.pos[: pc.n].copy()
        nuisance = sol.nuisance[nuis[0]].copy()
        cov = sol.marginals(np.arange(pc.n)) if absolute else np.full((pc.n, 2, 2), np.nan)
        reason = _solution_verdict(pos, cov, nuisance, absolute, sol.converged, sol.last_step, sol.iterations)
        h_new = _Held(wid, j, pc, pos, cov, nuisance, status, frame if not absolute else 0)
        # ---------------------------------------------------------- the audit trail of this piece
        w_loop = {li: float(sol.loop_weight[gid]) for li, gid in loop_ids}
        w_beacon = {(b, k): float(sol.loop_weight[gid]) for b, k, gid in fsl._beacon_loop_ids}
        recs = []
        name_new = str(wid)
        for n, lp in enumerate(cands):
            hk = by_serial[lp.walk_a]
            if lp.accepted and n in loop_of:
                w = w_loop.get(loop_of[n], 0.0)
                acc, why = w >= 0.5, "" if w >= 0.5 else "robust-weight"
            else:
                w, acc, why = 0.0, False, (lp.reason if not lp.accepted else "other-frame")
            recs.append(
                LoopRecord(
                    str(hk[0]),
                    float(lp.t_a),
                    name_new,
                    float(lp.t_b),
                    float(lp.similarity),
                    w,
                    acc,
                    fl.name,
                    float(lp.p_inlier),
                    why,
                    int(lp.node_a),
                    int(lp.node_b),
                )
            )
        for b, hk, i_old, i_new, d_old, d_new in passes:
            if hk in keep:
                w = min(w_beacon.get((b, 0), 0.0), w_beacon.get((b, idx_of[hk]), 0.0))
                why = "" if w >= 0.5 else "robust-weight"
            else:
                w, why = 0.0, "other-frame"
            h = fl.held[hk]
            recs.append(
                LoopRecord(
                    str(hk[0]),
                    float(h.piece.t[i_old]),
                    name_new,
                    float(pc.t[i_new]),
                    min(d_old, d_new),
                    w,
                    w >= 0.5,
                    fl.name,
                    reason=why,
                    node_a=i_old,
                    node_b=i_new,
                    kind="ble",
                )
            )
        return h_new, recs, reason

    # -------------------------------------------------------------- tracks
    def _track(self, wid: int) -> tuple[CorrectedTrack | None, str]:
        """The walk's corrected track from its held pieces (module docstring), or (None, reason)."""
        helds = []
        for j, pc in enumerate(self._pieces.get(wid, [])):
            h = self._floors[pc.floor].held.get((wid, j))
            if h is None or h.pos is None:
                return None, ""
            helds.append(h)
        if not helds:
            return None, ""
        return corrected_track(self.walks[wid], helds, self.cfg)

    # -------------------------------------------------------------- batch
    def rebuild_floor(
        self, floor: str, progress: Callable[[str, str, int, int], None] | None = None, fold_walks: list[int] | None = None
    ) -> FloorOutcome:
        """Re-solve one floor in batch over its held walks (module docstring); replaces their held
        solution. ``progress(stage, floor, done, total)`` as run_slam calls it (stages "loops",
        "solve", "em N", "done"). An error that cannot be pinned on one walk (inside the floor's loop
        detection or solve) propagates; the held state is then unchanged.

        ``fold_walks``: the walk ids whose rank sets each walk's EM fold (default: every walk held now).
        A batch over several floors passes the walks held when it began, so a floor's folds do not
        depend on which walks an earlier floor quarantined: floors that share no walk then solve alike
        in any order or process (server/slam_batch.py, server/dask_batch.py)."""
        t0 = time.monotonic()
        cfg = self.cfg
        fl = self._floor(floor)
        keys = sorted(fl.held)
        stats: dict = {"walks": 0, "pieces": 0, "anchored": {}, "quarantined": 0, "loops_candidates": 0, "loops_accepted": 0}
        outcomes: dict[int, WalkOutcome] = {}
        if not keys:
            stats.update(seconds=time.monotonic() - t0, em_rounds=0, em_moves=[], converged=True, resolves=0)
            return FloorOutcome(floor, {}, [], stats)
        total = 2 + cfg.em_rounds

        def say(stage: str, done: int) -> None:
            if progress:
                progress(stage, floor, done, total)

        # a walk's fold in EM: its rank among every held walk of the site
        fold = {w: r % max(cfg.em_folds, 2) for r, w in enumerate(sorted(self.walks if fold_walks is None else fold_walks))}
        bad: dict[int, tuple[str, CorrectedTrack | None]] = {}
        resolves = 0
        while True:
            use = [k for k in keys if k[0] not in bad]
            if not use:
                break
            pieces = [dataclasses.replace(fl.held[k].piece, walk=k[0], name=str(k[0])) for k in use]
            fsl = FloorSlam(floor, pieces, fl.field, cfg, fl.points)
            fsl._number()
            say("loops", 0)
            fsl.detect_loops()
            fsl.map_fixes = self._map_fixes(pieces, exclude=self._fed_back({k[0] for k in use}))
            say("solve", 1)
            sol = fsl.solve()
            found = self._batch_verdicts(fsl, sol, use)
            bad.update(found)
            if not found or resolves >= MAX_BATCH_RESOLVES:
                break
            resolves += 1
        records: list[LoopRecord] = []
        if use:
            # EM (pipeline.run_slam) with the crowd map of this floor's labels: the walks' floor is known,
            # so other floors' labels would only add a floor vote that drops fixes, at three times the
            # cost of the fold maps (site1: 33 of 54 s per floor)
            em_cache: dict = {}
            for rnd in range(cfg.em_rounds):
                lab, lab_walk = _labels(sol, [pc.walk for pc in fsl.pieces])
                if not set_em_fixes([fsl], lab, lab_walk, lambda w: fold.get(w, 0), cfg, em_cache):
                    break
                say(f"em {rnd + 1}", 2 + rnd)
                new = fsl.solve()
                both = np.isfinite(sol.pos[:, 0]) & np.isfinite(new.pos[:, 0]) & (fsl.node_status(sol.status) != RELATIVE)
                med = float(np.median(np.linalg.norm(new.pos[both] - sol.pos[both], axis=1))) if both.any() else 0.0
                new.em_moves = sol.em_moves + [med]
                grew = cfg.em_while_anchoring and anchored_more(sol, new)
                sol = new
                if med < cfg.em_stop_m and not grew:
                    break
            if sol.em_moves:  # a walk that fails only after EM: quarantined, no other solve
                bad.update(self._batch_verdicts(fsl, sol, use))
            # the floor's new state: every solved piece replaces its held solution
            frames: dict[int, int] = {}
            comp = graph_components(len(fsl.pieces), [(a, b) for a, _, b, _ in fsl._links()])
            for k, pc in enumerate(fsl.pieces):
                key = use[k]
                if key[0] in bad:
                    continue
                st = sol.status[k]
                h = fl.held[key]
                h.pos, h.cov, h.nuisance = sol.pos[pc.nodes].copy(), sol.cov[pc.nodes].copy(), sol.nuisance[pc.nuisance].copy()
                h.status, h.frame = st, (frames.setdefault(int(comp[k]), self._new_frame()) if st == RELATIVE else 0)
            for lp, ka, kb in zip(sol.loops, *fsl._pieces_of_loops(sol.loops)):
                records.append(dataclasses.replace(lp, node_a=lp.node_a - fsl.pieces[ka].node0, node_b=lp.node_b - fsl.pieces[kb].node0))
            if fsl.detector.model is not None:
                fl.set_detector(fsl.detector, len(fsl.pieces))
            stats.update(
                em_rounds=len(sol.em_moves),
                em_moves=list(sol.em_moves),
                converged=bool(sol.converged),
                last_step=float(sol.last_step),
            )
            if not sol.converged:
                log.warning("floor %s: the batch solve did not settle (last step %.2f m)", floor, sol.last_step)
        fl.loops = records
        readded = 0
        for wid in sorted({k[0] for k in keys}):
            name = str(wid)
            mine = [lp for lp in records if lp.walk_a == name or lp.walk_b == name]
            if wid in bad:
                # the joint solve could not fit this walk: it gets the incremental path against the new
                # solution of the others, and is quarantined only if it fails there too
                why, tr = bad[wid]
                walk = self.walks[wid]
                self._drop(wid)
                o = self.add_walk(walk)
                log.info("walk %s: the batch gave %r; added on its own: %r", wid, why, o.quarantined or "held")
                readded += not o.quarantined
                outcomes[wid] = WalkOutcome(wid, o.track if o.track is not None else tr, o.loops, o.quarantined, o.seconds)
                continue
            try:
                track, why = self._track(wid)
            except Exception as exc:  # noqa: BLE001 - the walk's own failure
                log.exception("walk %s: its track failed", wid)
                track, why = None, f"error: {type(exc).__name__}: {exc}"
            if why:
                self._quarantine(self.walks[wid], why)
            else:
                self.tracks[wid] = track
            outcomes[wid] = WalkOutcome(wid, track, mine, why)
        records = fl.loops  # with the loops of the walks added on their own
        stats.update(
            anchored=dict(Counter(h.status for k, h in fl.held.items() if k[0] in outcomes)),
            walks=len({k[0] for k in keys}),
            pieces=len(keys),
            quarantined=sum(1 for o in outcomes.values() if o.quarantined),
            readded=readded,
            loops_candidates=len(records),
            loops_accepted=sum(lp.accepted for lp in records),
            resolves=resolves,
            seconds=time.monotonic() - t0,
        )
        stats.setdefault("em_rounds", 0)
        stats.setdefault("em_moves", [])
        stats.setdefault("converged", True)
        say("done", total)
        return FloorOutcome(floor, outcomes, records, stats)

    def _batch_verdicts(self, fsl: FloorSlam, sol: FloorSolution, use: list[tuple[int, int]]) -> dict[int, tuple[str, CorrectedTrack | None]]:
        """Quarantine verdicts of the walks of a batch solution: {walk_id: (reason, track or None)} of
        the bad ones (each track built from this floor's new pieces and the walk's other held ones)."""
        fields = {n: f.field for n, f in self._floors.items() if f.field is not None}
        row = {key: k for k, key in enumerate(use)}
        out: dict[int, tuple[str, CorrectedTrack | None]] = {}
        for wid in sorted({key[0] for key in use}):
            try:
                helds, why = [], ""
                for j, pc in enumerate(self._pieces[wid]):
                    if (wid, j) in row:
                        k = row[(wid, j)]
                        p = fsl.pieces[k]
                        absolute = sol.status[k] != RELATIVE
                        pos, cov, nu = sol.pos[p.nodes], sol.cov[p.nodes], sol.nuisance[p.nuisance]
                        why = why or _solution_verdict(pos, cov, nu, absolute)
                        helds.append(_Held(wid, j, _fresh(p), pos, cov, nu, sol.status[k]))
                    else:
                        h = self._floors[pc.floor].held.get((wid, j))
                        if h is None or h.pos is None:  # another floor not solved yet: nothing to check there
                            continue
                        helds.append(h)
                track = None
                if helds:  # built even for a failed walk when it can be (returned for inspection)
                    track, why_track = corrected_track(self.walks[wid], helds, self.cfg)
                    why = why or why_track
                    if not why and track is not None:
                        why = check_track(track, self.plan, fields)
                if why:
                    out[wid] = (why, track)
            except Exception as exc:  # noqa: BLE001 - the walk's own failure
                log.exception("walk %s: checking its batch solution failed", wid)
                out[wid] = (f"error: {type(exc).__name__}: {exc}", None)
        return out

    # -------------------------------------------------------------- floors solved in another process
    def mark_floors(self, names) -> FloorsMark:
        """References to the state of floors ``names`` and of the walks held on them, now (no copy).

        With it, floors that share no walk are re-solved in a process forked from this one and only what
        the solves changed comes back (:meth:`floors_delta` there, :meth:`adopt_floors` here): a fork
        shares the site's state copy-on-write, and nothing but the floor's walks and their scans' search
        rows changes in :meth:`rebuild_floor` of a closed group of floors (a walk held on one of them has
        every piece on one of them; the EM folds come from ``fold_walks``). The mark is taken before the
        fork, so both processes hold it."""
        names = frozenset(names)
        self._dropped = set()  # the walks dropped from now on (both processes count their own)
        floors = {n: self._floors[n] for n in names if n in self._floors}
        wids = {k[0] for fl in floors.values() for k in fl.held}
        dicts = self._walk_dicts()
        return FloorsMark(
            names=names,
            walks=wids,
            held={n: dict(fl.held) for n, fl in floors.items()},
            solutions={n: {k: (h.pos, h.cov, h.nuisance, h.status, h.frame) for k, h in fl.held.items()} for n, fl in floors.items()},
            detectors={n: fl.detector for n, fl in floors.items()},
            rows={n: dict(fl._rows) for n, fl in floors.items()},
            walk_values={name: {w: d.get(w, _ABSENT) for w in wids} for name, d in dicts.items()},
            outside={n: frozenset(fl.held) for n, fl in self._floors.items() if n not in names},
            memo_keys=self._locator.memo_keys() if self._locator is not None else set(),
            next_frame=self._next_frame,
        )

    def _walk_dicts(self) -> dict[str, dict]:
        """The site's per-walk dictionaries a batch re-solve changes, by name."""
        return {
            "walks": self.walks,
            "tracks": self.tracks,
            "quarantined": self.quarantined,
            "_quarantined_walks": self._quarantined_walks,
            "_pieces": self._pieces,
            "_scan_floor": self._scan_floor,
            "floor_moves": self.floor_moves,
        }

    def held_walk_floors(self) -> dict[int, set[str]]:
        """The floors each held walk has a piece on."""
        out: dict[int, set[str]] = {}
        for n, fl in self._floors.items():
            for k in fl.held:
                out.setdefault(k[0], set()).add(n)
        return out

    def _pieces_changed(self, names, before: dict[str, Any]) -> list[str]:
        """Those of floors ``names`` whose held pieces (keys) are not the keys of ``before[floor]``."""
        return sorted(n for n in names if frozenset(self._floors[n].held if n in self._floors else ()) != frozenset(before.get(n, ())))

    def touched(self, mark: FloorsMark) -> list[str]:
        """The mark's floors whose held pieces are not those of the mark (something else than their own
        re-solve put a walk on them or took one off)."""
        return self._pieces_changed(mark.names, mark.held)

    def outside_changed(self, mark: FloorsMark) -> list[str]:
        """The floors outside ``mark``'s whose held pieces are not those of the mark (a walk the batch
        could not fit was re-added onto one of them by its fingerprints): a process that solved the
        mark's floors then also changed floors it does not own, and its delta must not be adopted."""
        return self._pieces_changed((set(self._floors) | set(mark.outside)) - mark.names, mark.outside)

    def floors_delta(self, mark: FloorsMark) -> FloorsDelta:
        """What re-solving the mark's floors changed since the mark (in the process that solved them),
        picklable and without what did not change: the held solutions by piece (a piece put again, by a
        walk dropped and re-added, whole), each floor's order of pieces, loop audit, front end and
        fingerprint rows, the walks' per-walk entries, the served map's new search rows, and the frame
        ids taken."""
        floors: dict[str, dict] = {}
        for n in mark.names:
            fl = self._floors.get(n)
            if fl is None:
                continue
            before, sols = mark.held.get(n, {}), mark.solutions.get(n, {})
            solved, new = {}, {}
            for k, h in fl.held.items():
                if before.get(k) is h:
                    now = (h.pos, h.cov, h.nuisance, h.status, h.frame)
                    if any(a is not b for a, b in zip(now, sols[k])):
                        solved[k] = now
                else:
                    new[k] = (h, fl.scans.get(k))
            rows0 = mark.rows.get(n, {})
            floors[n] = {
                "order": list(fl.held),
                "scans_order": list(fl.scans),
                "solved": solved,
                "new": new,
                "serial": fl.serial,
                "loops": fl.loops,
                "detector": (fl.detector, fl.fit_pieces) if fl.detector is not mark.detectors.get(n) else None,
                "rows": {k: v for k, v in fl._rows.items() if rows0.get(k) is not v},
                "rows_order": list(fl._rows),
                "col": dict(fl._col),
            }
        walks: dict[str, dict] = {}
        for name, d in self._walk_dicts().items():
            was = mark.walk_values[name]
            changed = {}
            for w in mark.walks:
                v = d.get(w, _ABSENT)
                if v is not was[w]:
                    changed[w] = _SAME_WALK if name == "_quarantined_walks" and v is mark.walk_values["walks"][w] else v
            # the order of the mark's walks in the dictionary: a walk dropped and added again moved to its end
            walks[name] = {"changed": changed, "order": [w for w in d if w in mark.walks]}
        memo = self._locator.memo_since(mark.memo_keys) if self._locator is not None else {}
        return FloorsDelta(floors, walks, set(self._dropped or ()) & mark.walks, memo, self._next_frame)

    def adopt_floors(self, mark: FloorsMark, delta: FloorsDelta) -> None:
        """Take the delta of the mark's floors solved in another process (:meth:`floors_delta`) as this
        process's state, as if they had been solved here after whatever was solved here since the mark:
        frame ids the other process took are moved past the ones taken here (a frame id is only ever
        compared for equality), and walks dropped and added again there go to the end of the per-walk
        dictionaries here, in their order there."""
        shift = self._next_frame - mark.next_frame

        def moved(frame: int) -> int:
            return frame + shift if frame >= mark.next_frame else frame

        for n, fd in delta.floors.items():
            fl = self._floor(n)
            old = fl.held
            held: dict = {}
            for k in fd["order"]:
                if k in fd["new"]:
                    h = fd["new"][k][0]
                    h.frame = moved(h.frame)
                else:
                    h = old[k]
                    if k in fd["solved"]:
                        h.pos, h.cov, h.nuisance, h.status, fr = fd["solved"][k]
                        h.frame = moved(fr)
                held[k] = h
            fl.held = held
            fl.scans = {k: fd["new"][k][1] if k in fd["new"] else fl.scans[k] for k in fd["scans_order"]}
            fl.serial, fl.loops = fd["serial"], fd["loops"]
            if fd["detector"] is not None:
                fl.detector, fl.fit_pieces = fd["detector"]
            fl._rows = {k: fd["rows"][k] if k in fd["rows"] else fl._rows[k] for k in fd["rows_order"]}
            fl._col = fd["col"]
        dicts = self._walk_dicts()
        for name, wd in delta.walks.items():
            d, was, changed = dicts[name], mark.walk_values[name], wd["changed"]

            def value(w: int, d=d, was=was, changed=changed):
                v = changed.get(w, was[w])
                return mark.walk_values["walks"][w] if v is _SAME_WALK else v

            # a walk dropped there (and maybe added again) went to the end of the dictionary there
            for w in delta.dropped:
                d.pop(w, None)
            for w in mark.walks:
                if w in delta.dropped:
                    continue
                v = value(w)
                if v is _ABSENT:
                    d.pop(w, None)
                else:
                    d[w] = v
            for w in wd["order"]:
                if w in delta.dropped and (v := value(w)) is not _ABSENT:
                    d[w] = v
        if self._locator is not None and delta.memo:
            self._locator.memo_adopt(delta.memo, (s for w in mark.walks if w in self.walks for s in self.walks[w].scans))
        self._next_frame = max(self._next_frame, delta.next_frame + shift)
        self.end_mark()

    def end_mark(self) -> None:
        """Stop counting the walks dropped (:meth:`mark_floors`)."""
        self._dropped = None

    # -------------------------------------------------------------- products
    def labels(self, floors=None) -> list[LabelledScan]:
        """Every scan of every absolutely anchored held walk with its corrected position and sd (source
        ``str(walk_id)``), from the held tracks (:func:`labels_from_tracks`); ``floors``: only these."""
        want = None if floors is None else set(floors)
        held = [w for wid, w in sorted(self.walks.items()) if self.tracks.get(wid) is not None]
        out = labels_from_tracks(held, {wid: t for wid, t in self.tracks.items() if t is not None}, self.cfg)
        return [ls for ls in out if want is None or ls.floor in want]

    def coverage(self, floors=None) -> float:
        """Share of the scans (with readings) of the unmarked (crowd) walks - held or quarantined - that
        have an absolute label: not relative, not quarantined. NaN when there is no such scan."""
        want = None if floors is None else set(floors)
        labelled = {(int(ls.source), id(ls.scan)) for ls in self.labels(floors)}
        num = den = 0
        for wid, walk in list(self.walks.items()) + list(self._quarantined_walks.items()):
            if walk.marks:
                continue
            fl = self._scan_floor.get(wid) or [walk.floors[0] if walk.floors else ""] * len(walk.scans)
            for s, f in zip(walk.scans, fl):
                if not len(s) or (want is not None and f not in want):
                    continue
                den += 1
                num += (wid, id(s)) in labelled
        return num / den if den else float("nan")


# ------------------------------------------------------------------------------------------ functions
def label_time(scan: RfScan, cfg: SlamConfig | None = None) -> float:
    """The time a scan is labelled at (module docstring): a node technology's (WiFi) node time, else its time."""
    cfg = cfg or SlamConfig()
    if scan.technology.value in cfg.walk.node_technologies:
        return scan_node_time(scan, cfg.walk.max_age_s)
    return float(scan.t)


def _piece_of_times(pieces: list[WalkPiece], t: np.ndarray) -> np.ndarray:
    """Index of the piece each time belongs to: the one whose span holds it, else the nearest in time."""
    if not pieces or not len(t):
        return np.zeros(len(t), np.int64)
    lo = np.array([pc.step_t[0] for pc in pieces])
    hi = np.array([max(pc.t[-1], pc.step_t[-1]) for pc in pieces])
    gap = np.maximum(lo[None, :] - t[:, None], 0.0) + np.maximum(t[:, None] - hi[None, :], 0.0)
    return np.argmin(gap, axis=1)


def _scan_floors(walk: Walk, pieces: list[WalkPiece], cfg: SlamConfig | None = None) -> list[str]:
    """The floor of each scan of the walk (its piece's; the walk's first floor when it has no piece)."""
    if not pieces:
        return [walk.floors[0] if walk.floors else ""] * len(walk.scans)
    cfg = cfg or SlamConfig()
    t = np.array([label_time(s, cfg) for s in walk.scans], float)
    return [pieces[k].floor for k in _piece_of_times(pieces, t)]


def _track_cov(pc: WalkPiece, C: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Covariance (len(t), 2, 2) of the corrected track between the piece's nodes (module docstring)."""
    n = pc.n
    if n < 2:
        return np.repeat(C[:1], len(t), axis=0)
    j = np.clip(np.searchsorted(pc.t, t, side="right"), 1, n - 1)
    i = j - 1
    dt = pc.t[j] - pc.t[i]
    u = np.clip(np.where(dt > 0, (t - pc.t[i]) / np.where(dt > 0, dt, 1.0), 0.0), 0.0, 1.0)[:, None, None]
    S = pc.C[j] - pc.C[i]  # white dead-reckoning covariance of the edge i -> j
    return (1.0 - u) * C[i] + u * C[j] + u * (1.0 - u) * S


def corrected_track(walk: Walk, helds: list[_Held], cfg: SlamConfig | None = None) -> tuple[CorrectedTrack | None, str]:
    """The walk's :class:`CorrectedTrack` from its solved pieces (module docstring), or (None, reason)
    when a position is not finite."""
    cfg = cfg or SlamConfig()
    pieces = [h.piece for h in helds]
    st = np.array(sorted(s.t for s in walk.steps), float)
    sc = np.array([label_time(s, cfg) for s in walk.scans], float)
    t = np.r_[st, sc]
    kind = np.r_[np.zeros(len(st), np.int8), np.ones(len(sc), np.int8)]
    order = np.lexsort((kind, t))
    t, kind = t[order], kind[order]
    which = _piece_of_times(pieces, t)
    pos = np.full((len(t), 2), np.nan)
    cov = np.full((len(t), 2, 2), np.nan)
    for k, h in enumerate(helds):
        sel = which == k
        if sel.any():
            pos[sel] = h.solution().track(0, t[sel])
            assert h.cov is not None
            cov[sel] = _track_cov(h.piece, h.cov, t[sel])
    if not np.all(np.isfinite(pos)):
        return None, "diverged: non-finite corrected position"
    nu = np.concatenate([h.nuisance for h in helds if h.nuisance is not None])
    # a D + b D_perp = s R(beta) D: the step-length factor s = |(a, b)|, the bias beta = atan2(b, a)
    scale = float(np.median(np.hypot(nu[:, 0], nu[:, 1])))
    bias = float(np.median(np.arctan2(nu[:, 1], nu[:, 0])))
    if not (math.isfinite(scale) and math.isfinite(bias)):
        return None, "diverged: non-finite step-length scale or heading bias"
    anchored = min((h.status for h in helds), key=lambda a: _RANK[a])
    tr = CorrectedTrack(
        walk.walk_id,
        t,
        pos,
        cov,
        tuple(pieces[k].floor for k in which),
        tuple("step" if x == 0 else "scan" for x in kind),
        anchored,
        scale,
        bias,
    )
    return tr, ""


def _solution_verdict(
    pos: np.ndarray, cov: np.ndarray, nuisance: np.ndarray, absolute: bool, converged: bool = True, last_step: float = 0.0, iterations: int = 0
) -> str:
    """The solve-side quarantine checks of one piece (module docstring): "" when fine."""
    if not np.all(np.isfinite(pos)):
        return "diverged: non-finite node positions"
    if absolute and not np.all(np.isfinite(cov)):
        return "diverged: non-finite covariance"
    if not converged and math.isfinite(last_step) and last_step > MAX_UNSETTLED_STEP_M:
        return f"diverged: the solve did not settle (last step {last_step:.1f} m after {iterations} iterations)"
    s = np.hypot(nuisance[:, 0], nuisance[:, 1])
    if not np.all(np.isfinite(s)):
        return "diverged: non-finite step-length scale"
    worst = float(s[np.argmax(np.abs(s - 1.0))])
    if abs(worst - 1.0) > MAX_SCALE_DEV:
        return f"diverged: step-length scale {worst:.2f} outside [{1 - MAX_SCALE_DEV:g}, {1 + MAX_SCALE_DEV:g}]"
    return ""


def check_track(
    track: CorrectedTrack,
    plan: FloorPlan | None,
    fields: dict | None = None,
    *,
    margin_m: float = OUTSIDE_MARGIN_M,
    max_outside_share: float = MAX_OUTSIDE_SHARE,
    max_step_m: float = MAX_STEP_M,
    max_scale_dev: float = MAX_SCALE_DEV,
    max_sd_m: float = MAX_SD_M,
) -> str:
    """The quarantine verdict of a corrected track (module docstring, "Quarantine"): "" when fine, else
    "diverged: ..." or "off-walkable: N % of the track outside the walkable area". ``fields``: floor ->
    :class:`.floorplan.WalkableField` (the distance the walkable factor uses); without one a floor's
    distance is shapely's to its walkable area. Relative tracks are checked for their shape only."""
    n = len(track)
    if n == 0:
        return ""
    if abs(track.scale - 1.0) > max_scale_dev:
        return f"diverged: step-length scale {track.scale:.2f} outside [{1 - max_scale_dev:g}, {1 + max_scale_dev:g}]"
    absolute = track.anchored != RELATIVE
    if absolute:
        cov = track.cov
        if not np.all(np.isfinite(cov)):
            return "diverged: non-finite covariance"
        var = np.maximum(cov[:, 0, 0], cov[:, 1, 1])
        if float(var.max()) > max_sd_m**2:
            return f"diverged: position sd {math.sqrt(float(var.max())):.0f} m (the walk is not constrained)"
    kinds = np.array(track.kind)
    floors = np.array(track.floor, dtype=object)
    st = np.flatnonzero(kinds == "step")
    if len(st) > 1:
        same = floors[st[1:]] == floors[st[:-1]]
        d = np.linalg.norm(np.diff(track.pos_enu[st], axis=0), axis=1)[same]
        if d.size and float(d.max()) > max_step_m:
            return f"diverged: a corrected step of {float(d.max()):.2f} m (a walking step is under {max_step_m:g} m)"
    if absolute and plan is not None:
        import shapely

        outside = checked = 0
        for f in sorted(set(track.floor)):
            if f not in plan.floor_names:
                continue
            sel = floors == f
            p = track.pos_enu[sel]
            fld = (fields or {}).get(f)
            if fld is not None:
                d, _ = fld(p)
            else:
                d = shapely.distance(plan.floor(f).walkable, shapely.points(p))
            outside += int((np.asarray(d) > margin_m).sum())
            checked += int(sel.sum())
        if checked and outside / checked > max_outside_share:
            return f"off-walkable: {round(100 * outside / checked)} % of the track outside the walkable area"
    return ""


def labels_from_tracks(walks: list[Walk], tracks: dict[int, CorrectedTrack], config: SlamConfig | None = None) -> list[LabelledScan]:
    """Every scan (with readings) of the walks whose track is absolute, labelled from the track at its
    label time (:func:`label_time`: the track's own scan point), sd sqrt(tr(Cov) / 2) (5 m when unknown,
    as pipeline._labels); source ``str(walk_id)``. Relative tracks are skipped; pass no quarantined one."""
    cfg = config or SlamConfig()
    out = []
    for w in walks:
        tr = tracks.get(w.walk_id) if w.walk_id is not None else None
        if tr is None or tr.anchored == RELATIVE:
            continue
        for s in w.scans:
            if not len(s):
                continue
            got = tr.at(label_time(s, cfg))
            if got is None:
                continue
            pos, c, floor = got
            sig = math.sqrt(max(0.5 * float(c[0, 0] + c[1, 1]), 0.0)) if np.all(np.isfinite(c)) else UNKNOWN_LABEL_SD_M
            out.append(LabelledScan(s, np.asarray(pos, float).copy(), sig, floor, str(w.walk_id)))
    return out


def labels_from_marks(walks: list[Walk], tracks: dict[int, CorrectedTrack]) -> list[LabelledScan]:
    """The scans of the survey walks (with marks) that have no absolute track in ``tracks``, labelled as a
    survey map labels them (:func:`hybridloc.radio.survey.label_scans`: the walk's PDR bridged between
    consecutive marks of one floor; none between marks on two floors); source ``str(walk_id)``.

    A crowd map is built from the tracks of a batch run, which holds the walks ended when it began: a
    survey that ended while it ran has no track yet, and without these labels the crowd map would serve
    fewer survey labels than the survey map it replaces (the demo's client fused 27 m off, about one run
    in fifteen, on such a map)."""
    out: list[LabelledScan] = []
    for w in walks:
        tr = tracks.get(w.walk_id) if w.walk_id is not None else None
        if not w.marks or len(w.marks) < 2 or len(w.steps) < 2 or (tr is not None and tr.anchored != RELATIVE):
            continue
        marks = sorted(w.marks, key=lambda k: k.t)
        wp = Waypoints(
            np.array([k.t for k in marks]),
            np.array([[k.x, k.y] for k in marks]),
            marks[0].floor or None,
            tuple(k.floor or None for k in marks),
        )
        out.extend(label_scans([s for s in w.scans if len(s)], list(w.steps), wp, float(w.t_start), source=str(w.walk_id)))
    return out


def build_crowd_maps(labels: list[LabelledScan], site: str, plan: FloorPlan | None) -> dict:
    """The crowd radio map of each technology among ``labels`` (as SlamResult.crowd_map: the label
    uncertainty weighs each scan, BuildParams.label_weight); a technology too thin to map is left out."""
    from ..radio.radiomap import BuildParams, build_radio_map

    out = {}
    for tech in sorted({ls.scan.technology.value for ls in labels}):
        try:
            out[tech] = build_radio_map(labels, site=site, plan=plan, params=BuildParams(label_weight=True), technology=tech)
        except ValueError as exc:  # too few readings of this technology to map
            log.info("crowd map %s: not built (%s)", tech, exc)
    return out


__all__ = [
    "MAX_OUTSIDE_SHARE",
    "MAX_SCALE_DEV",
    "MAX_SD_M",
    "MAX_STEP_M",
    "OUTSIDE_MARGIN_M",
    "CrowdSlam",
    "FloorOutcome",
    "WalkOutcome",
    "build_crowd_maps",
    "check_track",
    "corrected_track",
    "label_time",
    "labels_from_marks",
    "labels_from_tracks",
]

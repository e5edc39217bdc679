"""The names the server's SLAM worker uses from the library and the wire, in one place.

The worker (:mod:`.slam_worker`, :mod:`.slam_child`, :mod:`.slam_batch`) depends on these names only:

* the online crowd SLAM (issue #21, ``hybridloc.slam.online``): :class:`CrowdSlam` (``walks``,
  ``set_map``, ``hold``, ``add_walk``, ``remove_walk``, ``floors``, ``rebuild_floor``, ``labels``,
  ``coverage``), :class:`WalkOutcome`, :class:`FloorOutcome`, :func:`build_crowd_maps`,
  :func:`labels_from_tracks`, :func:`check_track`;
* the wire's track, map-version and progress messages (``hybridloc.wire``): ``key_track``,
  ``key_map_version``, ``key_progress``, ``Track``, ``MapVersion``, ``Progress``, ``TRACK``,
  ``MAP_VERSION``, ``PROGRESS``.

Until those land in the library, this module holds an interim implementation of each on top of what
the library already has (:func:`hybridloc.slam.pipeline.run_slam`, whose per-floor solve is the batch
re-solve; an "incremental" add re-solves the walk's floors with the held walks and keeps only the new
walk's solution), so the worker runs, and is tested, end to end. :data:`LIBRARY` says which is in use.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridloc.radio.survey import LabelledScan
from hybridloc.types import CorrectedTrack, FloorPlan, Walk

# ------------------------------------------------------------------------------------------ the library
try:  # pragma: no cover - exercised once hybridloc.slam.online is merged
    from hybridloc.slam.online import (  # type: ignore[import-not-found]
        CrowdSlam,
        FloorOutcome,
        WalkOutcome,
        build_crowd_maps,
        check_track,
        labels_from_tracks,
    )

    LIBRARY = "hybridloc.slam.online"
except ImportError:
    LIBRARY = "interim"

    #: a corrected point this far outside the walkable area, m, is off the plan: the solver's walkable
    #: factor (pipeline.SlamConfig: margin 0.3 m, sigma 0.5 m) leaves a consistent track at most about
    #: margin + 3 sigma = 1.8 m out, so 2 m is past what the solve tolerates
    OFF_WALKABLE_M = 2.0
    #: a track with more than this share of its points off the plan left the walkable area (doors and
    #: passages the plan does not draw put a few points of good tracks outside)
    OFF_WALKABLE_SHARE = 0.2
    #: anchoring strength of a walk's pieces, best first (CorrectedTrack.anchored: the best piece's)
    _ANCHOR_ORDER = ("marks", "map", "loops", "plan", "relative")

    @dataclass
    class WalkOutcome:  # type: ignore[no-redef]
        """One walk's solve: its track (None when it has nothing to place), its loop candidates (walk_a /
        walk_b are str(walk_id)), why it is quarantined ("" when it is not) and the solve's time, s."""

        walk_id: int
        track: CorrectedTrack | None
        loops: list = field(default_factory=list)
        quarantined: str = ""
        seconds: float = 0.0

    @dataclass
    class FloorOutcome:  # type: ignore[no-redef]
        floor: str
        walks: dict[int, WalkOutcome]
        loops: list
        stats: dict = field(default_factory=dict)

    def _field(plan: FloorPlan | None, floor: str):
        if plan is None or floor not in plan.floor_names:
            return None
        from hybridloc.slam.floorplan import WalkableField

        return WalkableField.from_floor(plan.floor(floor))

    #: the solved step-length scale of a walk lies within this many prior sd of 1 (WalkGraphConfig.scale_sd
    #: = 0.1, slam.md 3.1); beyond, the solve forced the walk into a shape its steps do not have
    SCALE_MAX_SD = 5.0

    def check_track(track: CorrectedTrack | None, plan: FloorPlan | None) -> str:  # type: ignore[no-redef]
        """Why ``track`` cannot be used ("" when it can): the solve diverged (its step-length scale is
        more than :data:`SCALE_MAX_SD` prior sd from 1: steps no person takes, or a wrong anchor), or it
        left the walkable area (more than :data:`OFF_WALKABLE_SHARE` of its points over
        :data:`OFF_WALKABLE_M` outside). A relative track has no place on the plan to check."""
        if track is None or len(track) == 0 or track.anchored == "relative":
            return ""
        from hybridloc.slam.walkgraph import WalkGraphConfig

        sd = WalkGraphConfig().scale_sd
        if abs(track.scale - 1.0) > SCALE_MAX_SD * sd:
            return f"diverged: step-length scale {track.scale:.2f} is more than {SCALE_MAX_SD:g} sd ({sd:g}) from 1"
        if plan is None:
            return ""
        floors = np.asarray(track.floor)
        off = n = 0
        for f in sorted(set(track.floor)):
            fld = _field(plan, f)
            if fld is None:
                continue
            sel = floors == f
            d, _ = fld(track.pos_enu[sel])
            off += int(np.count_nonzero(np.asarray(d) > OFF_WALKABLE_M))
            n += int(sel.sum())
        if n and off / n > OFF_WALKABLE_SHARE:
            return f"off-walkable: {off / n:.0%} of the corrected points more than {OFF_WALKABLE_M:g} m outside the walkable area"
        return ""

    def _tracks_of(res, walk_ids: list[int]) -> dict[int, CorrectedTrack]:
        """CorrectedTracks of a :class:`~hybridloc.slam.pipeline.SlamResult` (walk index i is walk_ids[i]):
        a point at every step and every scan of each piece, the anchored pieces only when a walk has one."""
        parts: dict[int, list] = {}
        for fs in res.floors.values():
            for k, pc in enumerate(fs.pieces):
                parts.setdefault(pc.walk, []).append((fs, k, pc))
        out = {}
        for wi, ps in parts.items():
            anchored = [p for p in ps if p[0].status[p[1]] != "relative"]
            ps = anchored or ps
            ts, pos, cov, fl, kinds, ab = [], [], [], [], [], []
            for fs, k, pc in ps:
                t = np.concatenate([pc.step_t, [s.t for s in pc.scans]])
                kind = ["step"] * len(pc.step_t) + ["scan"] * len(pc.scans)
                order = np.argsort(t, kind="stable")
                t = t[order]
                xy = fs.track(k, t)
                sd = fs.track_sigma(k, t) if fs.status[k] != "relative" else np.full((len(t), 2), np.nan)
                ts.append(t)
                pos.append(xy)
                c = np.zeros((len(t), 2, 2))
                c[:, 0, 0], c[:, 1, 1] = sd[:, 0] ** 2, sd[:, 1] ** 2
                cov.append(c)
                fl += [fs.floor] * len(t)
                kinds += [kind[i] for i in order]
                ab.append(fs.nuisance[pc.nuisance])
            t = np.concatenate(ts)
            order = np.argsort(t, kind="stable")
            a, b = np.concatenate(ab)[:, 0], np.concatenate(ab)[:, 1]
            best = min((fs.status[k] for fs, k, _ in ps), key=_ANCHOR_ORDER.index)
            out[walk_ids[wi]] = CorrectedTrack(
                walk_ids[wi],
                t[order],
                np.concatenate(pos)[order],
                np.concatenate(cov)[order],
                tuple(fl[i] for i in order),
                tuple(kinds[i] for i in order),
                best,
                float(np.median(np.hypot(a, b))),
                float(math.atan2(float(np.median(b)), float(np.median(a)))),
            )
        return out

    class CrowdSlam:  # type: ignore[no-redef]
        """A site's crowd SLAM kept in memory between calls (interim: see the module docstring)."""

        def __init__(self, site: str, plan: FloorPlan | None, config=None):
            from hybridloc.slam.pipeline import SlamConfig

            self.site = site
            self.plan = plan
            self.config = config or SlamConfig()
            self.walks: dict[int, Walk] = {}
            self.tracks: dict[int, CorrectedTrack | None] = {}
            self.radio_map = None

        def set_map(self, radio_map) -> None:
            self.radio_map = radio_map

        def hold(self, walk: Walk, track: CorrectedTrack | None) -> None:
            """Keep ``walk`` with ``track`` as its current solution (None: in the graph, not solved yet)."""
            assert walk.walk_id is not None
            self.walks[int(walk.walk_id)] = walk
            self.tracks[int(walk.walk_id)] = track

        def remove_walk(self, walk_id: int) -> None:
            self.walks.pop(int(walk_id), None)
            self.tracks.pop(int(walk_id), None)

        def floors(self) -> list[str]:
            return sorted({f for w in self.walks.values() for f in w.floors})

        def _solve(self, walks: list[Walk], progress=None):
            from hybridloc.slam.pipeline import run_slam

            ids = [int(w.walk_id) for w in walks]  # type: ignore[arg-type]
            res = run_slam(walks, self.plan, self.radio_map, self.config, names=[str(i) for i in ids], progress=progress)
            return res, _tracks_of(res, ids)

        def add_walk(self, walk: Walk) -> WalkOutcome:
            t0 = time.monotonic()
            wid = int(walk.walk_id)  # type: ignore[arg-type]
            near = [w for i, w in self.walks.items() if i != wid and set(w.floors) & set(walk.floors)]
            res, tracks = self._solve(near + [walk])
            tr = tracks.get(wid)
            loops = [lp for lp in res.loops if str(wid) in (lp.walk_a, lp.walk_b)]
            why = check_track(tr, self.plan)
            if not why and tr is not None:
                self.hold(walk, tr)
            return WalkOutcome(wid, tr, loops, why, time.monotonic() - t0)

        def rebuild_floor(self, floor: str, progress: Callable[[str, str, int, int], None] | None = None) -> FloorOutcome:
            t0 = time.monotonic()
            walks = [w for w in self.walks.values() if floor in w.floors]
            res, tracks = self._solve(walks, progress)
            fs = res.floors.get(floor)
            loops = list(fs.loops) if fs is not None else []
            out = {}
            for w in walks:
                wid = int(w.walk_id)  # type: ignore[arg-type]
                tr = tracks.get(wid)
                why = check_track(tr, self.plan)
                out[wid] = WalkOutcome(wid, tr, [lp for lp in loops if str(wid) in (lp.walk_a, lp.walk_b)], why)
                if why:
                    self.remove_walk(wid)
                else:
                    self.tracks[wid] = tr
            return FloorOutcome(floor, out, loops, {"walks": len(walks), "seconds": time.monotonic() - t0})

        def labels(self, floors: Iterable[str] | None = None) -> list[LabelledScan]:
            keep = None if floors is None else set(floors)
            return [ls for ls in labels_from_tracks(list(self.walks.values()), self.tracks) if keep is None or ls.floor in keep]

        def coverage(self, floors: Iterable[str] | None = None) -> float | None:
            crowd = [w for w in self.walks.values() if not w.marks and (floors is None or set(w.floors) & set(floors))]
            n = sum(len(w.scans) for w in crowd)
            if not n:
                return None
            lab = labels_from_tracks(crowd, self.tracks)
            return len(lab) / n

    def labels_from_tracks(walks: list[Walk], tracks: Mapping[int, CorrectedTrack | None]) -> list[LabelledScan]:  # type: ignore[no-redef]
        """Every scan of the walks with an absolute track, labelled with the track's position at its time
        and the sd of the covariance there (5 m where the solve gave none); source ``str(walk_id)``."""
        out = []
        for w in walks:
            wid = int(w.walk_id)  # type: ignore[arg-type]
            tr = tracks.get(wid)
            if tr is None or tr.anchored == "relative":
                continue
            for sc in w.scans:
                got = tr.at(sc.t)
                if got is None:
                    continue
                pos, cov, floor = got
                sig = math.sqrt(max(0.5 * float(cov[0, 0] + cov[1, 1]), 0.0)) if np.all(np.isfinite(cov)) else 5.0
                out.append(LabelledScan(sc, np.asarray(pos, float), sig, floor, str(wid)))
        return out

    def build_crowd_maps(labels: list[LabelledScan], site: str, plan: FloorPlan | None) -> dict:  # type: ignore[no-redef]
        """{technology: RadioMap} of the technologies the labels have enough readings of."""
        from hybridloc.radio.radiomap import BuildParams, build_radio_map

        out = {}
        for tech in ("wifi", "ble"):
            refs = [ls for ls in labels if ls.scan.technology.value == tech]
            if not refs:
                continue
            try:
                out[tech] = build_radio_map(refs, site=site, plan=plan, params=BuildParams(label_weight=True), technology=tech)
            except ValueError:  # too few readings of this technology to map
                continue
        return out


# ------------------------------------------------------------------------------------------ the wire
from hybridloc.wire import codecs as _C  # noqa: E402
from hybridloc.wire import messages as _M  # noqa: E402
from hybridloc.wire import protocol as _P  # noqa: E402

if hasattr(_P, "key_track") and hasattr(_C, "TRACK"):  # pragma: no cover - once the wire change is merged
    key_track, key_map_version, key_progress = _P.key_track, _P.key_map_version, _P.key_progress
    Track, MapVersion, Progress = _M.Track, _M.MapVersion, _M.Progress
    TRACK, MAP_VERSION, PROGRESS = _C.TRACK, _C.MAP_VERSION, _C.PROGRESS
    WIRE = "hybridloc.wire"
else:
    WIRE = "interim"

    def key_track(site: str, device: str) -> str:
        return f"{_P.PREFIX}/{site}/{device}/track"

    def key_map_version(site: str) -> str:
        return f"{_P.PREFIX}/{site}/map/version"

    def key_progress(site: str) -> str:
        return f"{_P.PREFIX}/{site}/progress"

    @dataclass(frozen=True, eq=False)
    class Track:  # type: ignore[no-redef]
        site: str
        device: str
        walk_id: int
        map_version: int | None
        run: int | None
        track: CorrectedTrack
        sent_at: float = 0.0

    @dataclass(frozen=True)
    class MapVersion:  # type: ignore[no-redef]
        site: str
        version: int
        source: str
        created_at: float
        walks: int
        coverage: float | None

    @dataclass(frozen=True)
    class Progress:  # type: ignore[no-redef]
        site: str
        stage: str
        floor: str
        done: int
        total: int
        t: float

    def _nan(v: float) -> float | None:
        return float(v) if math.isfinite(v) else None

    class _Json:
        def __init__(self, schema: str, enc: Callable[[Any], dict], dec: Callable[[dict], Any]):
            self.schema, self._enc, self._dec = schema, enc, dec
            self.encoding = _P.encoding(schema)

        def encode(self, rec) -> bytes:
            return json.dumps({"schema": self.schema, **self._enc(rec)}).encode()

        def decode(self, payload: bytes):
            return self._dec(json.loads(bytes(payload).decode()))

    def _track_enc(m: Track) -> dict:
        tr = m.track
        return {
            "site": m.site,
            "device": m.device,
            "walk_id": m.walk_id,
            "map_version": m.map_version,
            "run": m.run,
            "sent_at": m.sent_at,
            "anchored": tr.anchored,
            "scale": tr.scale,
            "heading_bias": tr.heading_bias,
            "t": tr.t.tolist(),
            "pos": tr.pos_enu.tolist(),
            "cov": [[_nan(c[0, 0]), _nan(c[0, 1]), _nan(c[1, 1])] for c in tr.cov],
            "floor": list(tr.floor),
            "kind": list(tr.kind),
        }

    def _track_dec(d: dict) -> Track:
        nan = float("nan")
        cov = np.array(
            [[[nan if a is None else a, nan if b is None else b], [nan if b is None else b, nan if c is None else c]] for a, b, c in d["cov"]]
        )
        tr = CorrectedTrack(
            d["walk_id"], np.array(d["t"], float), np.array(d["pos"], float).reshape(-1, 2), cov.reshape(-1, 2, 2), d["floor"], d["kind"],
            d["anchored"], d["scale"], d["heading_bias"],
        )  # fmt: skip
        return Track(d["site"], d["device"], d["walk_id"], d["map_version"], d["run"], tr, d["sent_at"])

    _fields_of = lambda cls: lambda m: {k: getattr(m, k) for k in cls.__dataclass_fields__}  # noqa: E731
    TRACK = _Json("hybridloc.track/1", _track_enc, _track_dec)
    MAP_VERSION = _Json("hybridloc.map_version/1", _fields_of(MapVersion), lambda d: MapVersion(**{k: d[k] for k in MapVersion.__dataclass_fields__}))
    PROGRESS = _Json("hybridloc.progress/1", _fields_of(Progress), lambda d: Progress(**{k: d[k] for k in Progress.__dataclass_fields__}))


def status_with_slam(online, counts, db, maps_loaded, slam: Mapping[str, Any]):
    """The status message with its per-site SLAM figures (``Status.slam``; before the wire has the field,
    they travel in ``db["slam"]``)."""
    Status = _M.Status
    if "slam" in getattr(Status, "__dataclass_fields__", {}):
        return Status(online, counts, db, maps_loaded, slam=slam)  # type: ignore[call-arg]
    return Status(online, counts, dict(db, slam=dict(slam)), maps_loaded)

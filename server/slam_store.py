"""What the crowd SLAM stores: runs, per-floor checkpoints, walk states, corrected tracks, the loop audit.

Reached as :attr:`hybridloc.server.store.Store.slam`. Two ways results arrive:

* **one walk added** (:meth:`SlamStore.save_walk`): a ``slam_run`` of kind "walk", its track points,
  its loop candidates and the walk's ``walk_slam`` row, in one transaction;
* **a batch re-solve** of some floors: :meth:`begin_run`, then per floor :meth:`write_floor` (points,
  loops and the floor's checkpoint in one transaction: a run killed midway resumes after the floors
  it finished, :meth:`unfinished_runs` / :meth:`floors_done`), then :meth:`finish_run`, which in one
  transaction points every solved walk's ``walk_slam`` row at the run, stores the new radio map
  version with its provenance, marks the run complete and drops the points no walk references any
  more. Until then readers see the previous tracks and map: the swap is atomic.

A walk's current track is the points of the run its ``walk_slam.run_id`` names. Statuses:
"corrected" (an absolute track), "relative" (a shape in the walk's own frame: never an absolute
position), "quarantined" (the solve diverged or the track left the walkable area; kept out of the map,
counted), "failed" (an error while solving it; the next batch run tries again).
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from sqlalchemy import delete, func, insert, select, update
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session

from hybridloc.errors import ComputationFailed
from hybridloc.types import CorrectedTrack, WalkEnd

from . import db as m

CORRECTED, RELATIVE, QUARANTINED, FAILED = "corrected", "relative", "quarantined", "failed"
WALK_STATUSES = (CORRECTED, RELATIVE, QUARANTINED, FAILED)
RUNNING, COMPLETE, RUN_FAILED = "running", "complete", "failed"


class SlamBusy(ComputationFailed):
    """Another process holds a live lease on a batch run of the site (:meth:`SlamStore.claim_batch`)."""

    def __init__(self, site: str, run_id: int, lease: dict):
        self.site, self.run_id, self.lease = site, run_id, dict(lease)
        super().__init__(
            f"site {site}: batch run {run_id} is being solved by process {lease.get('pid')} on {lease.get('host')} "
            f"(heartbeat {lease.get('heartbeat')}); try again when it ends"
        )


@dataclass(frozen=True)
class WalkState:
    """A walk's SLAM state (its ``walk_slam`` row)."""

    walk_id: int
    status: str
    anchored: str
    reason: str
    run_id: int | None
    scale: float | None
    heading_bias: float | None
    n_points: int
    attempts: int
    updated_at: dt.datetime


@dataclass(frozen=True)
class RunInfo:
    run_id: int
    site: str
    kind: str
    status: str
    floors: tuple[str, ...] | None
    started_at: dt.datetime
    finished_at: dt.datetime | None
    map_version: int | None
    stats: dict
    error: str
    floors_done: tuple[str, ...]


@dataclass(frozen=True)
class LoopRow:
    """A stored loop candidate (walk ids, times on the walks' clocks, similarity, robust weight)."""

    run_id: int
    floor: str
    walk_a: int
    t_a: float
    walk_b: int
    t_b: float
    similarity: float
    weight: float
    p_inlier: float | None
    accepted: bool
    reason: str
    kind: str


@dataclass(frozen=True)
class WalkResult:
    """One walk's outcome of a solve, as :meth:`SlamStore.write_floor` and :meth:`SlamStore.save_walk` take it.

    ``status`` one of :data:`WALK_STATUSES`; ``track`` may be None (no track: failed, or nothing to place);
    a quarantined walk's track is kept for inspection but never labels a map."""

    walk_id: int
    status: str
    track: CorrectedTrack | None = None
    reason: str = ""

    def __post_init__(self) -> None:
        if self.status not in WALK_STATUSES:
            raise ValueError(f"walk status {self.status!r} is not one of {WALK_STATUSES}")


def _num(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


class SlamStore:
    def __init__(self, engine: Engine):
        self.engine = engine

    # ------------------------------------------------------------------ work queue
    def pending_walks(self, site: str, limit: int | None = None) -> list[int]:
        """Ended walks of ``site`` that no solve has seen yet (no ``walk_slam`` row), oldest end first."""
        q = (
            select(m.Walk.id)
            .outerjoin(m.WalkSlam, m.WalkSlam.walk_id == m.Walk.id)
            .where(m.Walk.site_id == site, m.Walk.end_reason != WalkEnd.OPEN.value, m.WalkSlam.walk_id.is_(None))
            .order_by(m.Walk.t_end, m.Walk.id)
        )
        if limit is not None:
            q = q.limit(limit)
        with Session(self.engine) as s:
            return [int(r) for r in s.execute(q).scalars()]

    def solvable_walks(self, site: str, floor: str | None = None) -> list[int]:
        """Ended walks of ``site`` (naming ``floor``) that a batch re-solve takes: all but the quarantined ones."""
        cond = [m.Walk.site_id == site, m.Walk.end_reason != WalkEnd.OPEN.value]
        if floor is not None:
            cond.append(m.Walk.id.in_(select(m.WalkFloor.walk_id).where(m.WalkFloor.floor == floor)))
        q = (
            select(m.Walk.id)
            .outerjoin(m.WalkSlam, m.WalkSlam.walk_id == m.Walk.id)
            .where(*cond, (m.WalkSlam.status.is_(None)) | (m.WalkSlam.status != QUARANTINED))
            .order_by(m.Walk.t_start, m.Walk.id)
        )
        with Session(self.engine) as s:
            return [int(r) for r in s.execute(q).scalars()]

    # ------------------------------------------------------------------ writing
    @staticmethod
    def _points(s: Session, run_id: int, walk_id: int, track: CorrectedTrack) -> int:
        if len(track) == 0:
            return 0
        cov = np.asarray(track.cov, float)
        s.execute(
            insert(m.TrackPoint),
            [
                {
                    "run_id": run_id,
                    "walk_id": walk_id,
                    "t": float(track.t[i]),
                    "kind": track.kind[i],
                    "floor": track.floor[i],
                    "x": float(track.pos_enu[i, 0]),
                    "y": float(track.pos_enu[i, 1]),
                    "cov_xx": _num(cov[i, 0, 0]),
                    "cov_xy": _num(cov[i, 0, 1]),
                    "cov_yy": _num(cov[i, 1, 1]),
                }
                for i in range(len(track))
            ],
        )
        return len(track)

    @staticmethod
    def _loops(s: Session, run_id: int, site: str, loops: Iterable) -> int:
        """Loop records (``hybridloc.slam.pipeline.LoopRecord``-like: walk_a/walk_b are walk ids, as int or str)."""
        rows = [
            {
                "run_id": run_id,
                "site_id": site,
                "floor": lp.floor,
                "walk_a": int(lp.walk_a),
                "t_a": float(lp.t_a),
                "walk_b": int(lp.walk_b),
                "t_b": float(lp.t_b),
                "similarity": float(lp.similarity) if math.isfinite(float(lp.similarity)) else 0.0,
                "weight": float(lp.weight) if math.isfinite(float(lp.weight)) else 0.0,
                "p_inlier": _num(lp.p_inlier) if lp.p_inlier is not None else None,
                "accepted": bool(lp.accepted),
                "reason": str(lp.reason or "")[:32],
                "kind": str(getattr(lp, "kind", "wifi") or "wifi")[:8],
            }
            for lp in loops
        ]
        if rows:
            s.execute(insert(m.LoopClosure), rows)
        return len(rows)

    @staticmethod
    def _set_walk(s: Session, site: str, res: WalkResult, run_id: int | None, n_points: int, attempt: bool) -> None:
        row = s.get(m.WalkSlam, res.walk_id)
        tr = res.track
        values = {
            "status": res.status,
            "anchored": tr.anchored if tr is not None else "relative",
            "reason": res.reason,
            "run_id": run_id if tr is not None else None,
            "scale": tr.scale if tr is not None else None,
            "heading_bias": tr.heading_bias if tr is not None else None,
            "n_points": n_points,
            "updated_at": m.utcnow(),
        }
        if row is None:
            s.add(m.WalkSlam(walk_id=res.walk_id, site_id=site, attempts=1 if attempt else 0, **values))
        else:
            for k, v in values.items():
                setattr(row, k, v)
            if attempt:
                row.attempts += 1

    def save_walk(self, site: str, result: WalkResult, loops: Sequence = (), stats: dict | None = None) -> int:
        """One walk added incrementally: its run (kind "walk", complete at once), its track, its loop
        candidates and its state, in one transaction; returns the run id."""
        with Session(self.engine) as s, s.begin():
            run = m.SlamRun(
                site_id=site, kind="walk", status=COMPLETE, floors=None, stats=dict(stats or {}, walk=result.walk_id), finished_at=m.utcnow()
            )
            s.add(run)
            s.flush()
            n = self._points(s, run.id, result.walk_id, result.track) if result.track is not None else 0
            self._loops(s, run.id, site, loops)
            self._set_walk(s, site, result, run.id, n, attempt=True)
            return int(run.id)

    def live_run(self, site: str, walk_id: int) -> int:
        """A run id for a provisional correction of an open walk (kind "live", complete, no points: the
        track is sent, not stored). Run ids only grow, so a device takes each newer correction of its
        walk, and the walk's final run (:meth:`save_walk`, later) supersedes them all."""
        with Session(self.engine) as s, s.begin():
            run = m.SlamRun(site_id=site, kind="live", status=COMPLETE, floors=None, stats={"walk": int(walk_id)}, finished_at=m.utcnow())
            s.add(run)
            s.flush()
            return int(run.id)

    def drop_live_runs(self, walk_id: int, before: int) -> int:
        """Forget the provisional runs of a walk older than run ``before`` (its final run: the newest id
        stays, so ids are never reused); the number dropped."""
        with Session(self.engine) as s, s.begin():
            ids = [
                r.id
                for r in s.execute(select(m.SlamRun).where(m.SlamRun.kind == "live", m.SlamRun.id < before)).scalars()
                if (r.stats or {}).get("walk") == int(walk_id)
            ]
            if ids:
                s.execute(delete(m.SlamRun).where(m.SlamRun.id.in_(ids)))
            return len(ids)

    def mark_walk(self, site: str, walk_id: int, status: str, reason: str = "") -> None:
        """Set a walk's state without a track (quarantined or failed outside a solve: its previous track is kept)."""
        if status not in WALK_STATUSES:
            raise ValueError(f"walk status {status!r} is not one of {WALK_STATUSES}")
        with Session(self.engine) as s, s.begin():
            row = s.get(m.WalkSlam, walk_id)
            if row is None:
                s.add(m.WalkSlam(walk_id=walk_id, site_id=site, status=status, anchored="relative", reason=reason[:500], n_points=0, attempts=1))
            else:
                row.status, row.reason, row.updated_at = status, reason[:500], m.utcnow()
                row.attempts += 1

    def begin_run(self, site: str, floors: Sequence[str] | None = None, stats: dict | None = None) -> int:
        """A new batch run of ``floors`` (None: all) in state "running"; returns its id."""
        return m.retry_unique(lambda: self._begin_run(site, floors, stats))  # the site's row may be created beside us

    def _begin_run(self, site: str, floors: Sequence[str] | None, stats: dict | None) -> int:
        with Session(self.engine) as s, s.begin():
            m.lock_site(s, site)
            run = m.SlamRun(site_id=site, kind="batch", status=RUNNING, floors=list(floors) if floors is not None else None, stats=dict(stats or {}))
            s.add(run)
            s.flush()
            return int(run.id)

    # ------------------------------------------------------------------ one batch run at a time
    def claim_batch(self, site: str, floors: Sequence[str] | None, lease: dict, is_stale: Callable[[dict], bool]) -> tuple[int, bool, dict | None]:
        """The batch run the caller may work on, under its ``lease`` ({"token", "host", "pid",
        "heartbeat"}, kept in the run's stats): (run id, resumed, the lease taken over or None).

        In one transaction that first writes the site's row, so two processes deciding at once are
        serialised (SQLite's write lock, PostgreSQL's row lock): a running batch run of the site whose
        lease is live (``is_stale(lease)`` False) refuses the claim (:class:`SlamBusy`); a stale one -
        killed midway - is resumed when it solves the same ``floors`` (None: all), else ended as failed
        (superseded); without one a new run begins."""
        return m.retry_unique(lambda: self._claim_batch(site, floors, lease, is_stale))  # the site's row may be created beside us

    def _claim_batch(self, site: str, floors: Sequence[str] | None, lease: dict, is_stale: Callable[[dict], bool]) -> tuple[int, bool, dict | None]:
        with Session(self.engine) as s, s.begin():
            m.lock_site(s, site)
            runs = (
                s.execute(
                    select(m.SlamRun).where(m.SlamRun.site_id == site, m.SlamRun.kind == "batch", m.SlamRun.status == RUNNING).order_by(m.SlamRun.id)
                )
                .scalars()
                .all()
            )
            for r in runs:
                held = (r.stats or {}).get("lease")
                if held and not is_stale(held):
                    raise SlamBusy(site, r.id, held)
            want = sorted(floors) if floors is not None else None
            mine, taken = None, None
            for r in runs:
                if mine is None and (sorted(r.floors) if r.floors is not None else None) == want:
                    mine, taken = r, (r.stats or {}).get("lease")
                    continue
                r.status, r.finished_at = RUN_FAILED, m.utcnow()
                r.error = f"superseded by a batch run of floors {want if want is not None else 'all'}"
                s.execute(delete(m.TrackPoint).where(m.TrackPoint.run_id == r.id))
            resumed = mine is not None
            if mine is None:
                mine = m.SlamRun(site_id=site, kind="batch", status=RUNNING, floors=want, stats={})
                s.add(mine)
                s.flush()
            st = dict(mine.stats or {})
            st["lease"] = dict(lease)
            if resumed:
                st["resumes"] = int(st.get("resumes", 0)) + 1
            mine.stats = st
            return int(mine.id), resumed, taken

    def renew_lease(self, run_id: int, token: str, heartbeat: float) -> bool:
        """Refresh the lease of a running batch run; False when it is not the caller's any more (taken
        over as stale, or the run ended)."""
        with Session(self.engine) as s, s.begin():
            run = s.get(m.SlamRun, run_id)
            if run is None or run.status != RUNNING:
                return False
            held = (run.stats or {}).get("lease") or {}
            if held.get("token") != token:
                return False
            return self._set_running_stats(s, run_id, dict(run.stats or {}, lease=dict(held, heartbeat=heartbeat)))

    @staticmethod
    def _set_running_stats(s: Session, run_id: int, stats: dict) -> bool:
        """Write a run's stats only while it is still running, in one statement: the stats were read before
        (outside a write lock: SQLite's driver begins its transaction at the first write), and
        :meth:`finish_run` may have ended the run since, writing its own. A plain write of the object
        then put the old stats back over them (seen: a complete batch run whose stats held only its
        lease, so the worker's schedule read it as solving no walk)."""
        done = s.execute(update(m.SlamRun).where(m.SlamRun.id == run_id, m.SlamRun.status == RUNNING).values(stats=stats))
        return done.rowcount == 1

    def release_lease(self, run_id: int, token: str) -> None:
        """Give a running run up for someone else to resume at once (an interrupted ``slam rebuild``)."""
        with Session(self.engine) as s, s.begin():
            run = s.get(m.SlamRun, run_id)
            if run is not None and run.status == RUNNING and ((run.stats or {}).get("lease") or {}).get("token") == token:
                st = dict(run.stats or {})
                st.pop("lease", None)
                self._set_running_stats(s, run_id, st)

    def write_floor(self, run_id: int, floor: str, results: Sequence[WalkResult], loops: Sequence = (), stats: dict | None = None) -> None:
        """A floor of a running batch run: its walks' points, its loops and its checkpoint, in one transaction
        (a floor already written is refused: ValueError)."""
        with Session(self.engine) as s, s.begin():
            run = s.get(m.SlamRun, run_id)
            if run is None or run.status != RUNNING:
                raise ValueError(f"SLAM run {run_id} is not running")
            if s.get(m.SlamFloorDone, (run_id, floor)) is not None:
                raise ValueError(f"floor {floor!r} of SLAM run {run_id} is already written")
            walks = {}
            for r in results:
                n = self._points(s, run_id, r.walk_id, r.track) if r.track is not None else 0
                tr = r.track
                walks[str(r.walk_id)] = {
                    "status": r.status,
                    "reason": r.reason[:500],
                    "anchored": tr.anchored if tr is not None else "relative",
                    "scale": tr.scale if tr is not None else None,
                    "heading_bias": tr.heading_bias if tr is not None else None,
                    "n_points": n,
                }
            self._loops(s, run_id, run.site_id, loops)
            s.add(m.SlamFloorDone(run_id=run_id, floor=floor, stats=dict(stats or {}, walks=walks)))

    def finish_run(
        self, run_id: int, map_data: bytes | None = None, n_scans: int = 0, provenance: dict | None = None, stats: dict | None = None
    ) -> int | None:
        """Complete a batch run atomically (module docstring); returns the new radio map version (None when
        no map was given). Safe beside another writer of map versions (:func:`~.db.lock_site`)."""
        return m.retry_unique(lambda: self._finish_run(run_id, map_data, n_scans, provenance, stats))

    def _finish_run(self, run_id: int, map_data: bytes | None, n_scans: int, provenance: dict | None, stats: dict | None) -> int | None:
        with Session(self.engine) as s, s.begin():
            run = s.get(m.SlamRun, run_id)
            if run is None or run.status != RUNNING:
                raise ValueError(f"SLAM run {run_id} is not running")
            site = run.site_id
            per_floor = s.execute(select(m.SlamFloorDone).where(m.SlamFloorDone.run_id == run_id).order_by(m.SlamFloorDone.floor)).scalars()
            for wid, w in _walks_over_floors([(fd.stats or {}).get("walks", {}) for fd in per_floor]).items():
                row = s.get(m.WalkSlam, wid)
                has_track = w["n_points"] > 0
                values = {
                    "status": w["status"],
                    "reason": w["reason"],
                    "anchored": w["anchored"],
                    "scale": w["scale"],
                    "heading_bias": w["heading_bias"],
                    "n_points": w["n_points"],
                    "updated_at": m.utcnow(),
                }
                if has_track:
                    values["run_id"] = run_id
                if row is None:
                    values.setdefault("run_id", None)
                    s.add(m.WalkSlam(walk_id=wid, site_id=site, attempts=1, **values))
                else:
                    for k, v in values.items():
                        setattr(row, k, v)
                    row.attempts += 1
            version = None
            if map_data is not None:
                m.lock_site(s, site)  # the next version is read after any other writer's commit
                last = s.execute(select(func.max(m.RadioMapVersion.version)).where(m.RadioMapVersion.site_id == site)).scalar_one()
                version = int(last or 0) + 1
                s.add(
                    m.RadioMapVersion(
                        site_id=site, version=version, n_scans=n_scans, data=map_data, source="slam", run_id=run_id, provenance=dict(provenance or {})
                    )
                )
            run.status = COMPLETE
            run.finished_at = m.utcnow()
            run.map_version = version
            run.stats = dict(run.stats or {}, **(stats or {}))
            s.flush()
            # the points no walk's current track uses any more (superseded runs), except running runs' own
            live = select(m.WalkSlam.run_id).where(m.WalkSlam.run_id.is_not(None))
            running = select(m.SlamRun.id).where(m.SlamRun.status == RUNNING)
            s.execute(
                delete(m.TrackPoint).where(
                    m.TrackPoint.walk_id.in_(select(m.Walk.id).where(m.Walk.site_id == site)),
                    m.TrackPoint.run_id.not_in(live),
                    m.TrackPoint.run_id.not_in(running),
                )
            )
            return version

    def fail_run(self, run_id: int, error: str) -> None:
        with Session(self.engine) as s, s.begin():
            run = s.get(m.SlamRun, run_id)
            if run is not None and run.status == RUNNING:
                run.status, run.error, run.finished_at = RUN_FAILED, error[:2000], m.utcnow()
                s.execute(delete(m.TrackPoint).where(m.TrackPoint.run_id == run_id))

    # ------------------------------------------------------------------ reading
    def _run_info(self, s: Session, r: m.SlamRun) -> RunInfo:
        done = tuple(sorted(s.execute(select(m.SlamFloorDone.floor).where(m.SlamFloorDone.run_id == r.id)).scalars()))
        return RunInfo(
            r.id,
            r.site_id,
            r.kind,
            r.status,
            tuple(r.floors) if r.floors is not None else None,
            r.started_at,
            r.finished_at,
            r.map_version,
            dict(r.stats or {}),
            r.error,
            done,
        )

    def unfinished_runs(self, site: str) -> list[RunInfo]:
        """Batch runs of ``site`` still "running" (killed midway: resume them), oldest first."""
        with Session(self.engine) as s:
            rows = s.execute(select(m.SlamRun).where(m.SlamRun.site_id == site, m.SlamRun.status == RUNNING).order_by(m.SlamRun.id)).scalars().all()
            return [self._run_info(s, r) for r in rows]

    def runs(self, site: str, kind: str | None = None, limit: int = 20) -> list[RunInfo]:
        """The newest runs of ``site`` first."""
        cond = [m.SlamRun.site_id == site] + ([m.SlamRun.kind == kind] if kind else [])
        with Session(self.engine) as s:
            rows = s.execute(select(m.SlamRun).where(*cond).order_by(m.SlamRun.id.desc()).limit(limit)).scalars().all()
            return [self._run_info(s, r) for r in rows]

    def floors_done(self, run_id: int) -> set[str]:
        with Session(self.engine) as s:
            return set(s.execute(select(m.SlamFloorDone.floor).where(m.SlamFloorDone.run_id == run_id)).scalars())

    def processed_walks(self, site: str) -> set[int]:
        """Ids of the site's walks that have a SLAM state (whatever it is): one column, cheap to poll."""
        with Session(self.engine) as s:
            return {int(w) for w in s.execute(select(m.WalkSlam.walk_id).where(m.WalkSlam.site_id == site)).scalars()}

    def walk_states(self, site: str) -> dict[int, WalkState]:
        with Session(self.engine) as s:
            return {
                r.walk_id: WalkState(
                    r.walk_id, r.status, r.anchored, r.reason, r.run_id, r.scale, r.heading_bias, r.n_points, r.attempts, r.updated_at
                )
                for r in s.execute(select(m.WalkSlam).where(m.WalkSlam.site_id == site)).scalars()
            }

    def tracks(self, site: str, floor: str | None = None, walk_ids: Iterable[int] | None = None) -> dict[int, CorrectedTrack]:
        """Current corrected tracks (walk id -> track) of ``site``'s walks: of those with a point on
        ``floor``, of ``walk_ids``. Quarantined walks' tracks are included (their state says so)."""
        cond = [m.WalkSlam.site_id == site, m.WalkSlam.run_id.is_not(None)]
        if walk_ids is not None:
            cond.append(m.WalkSlam.walk_id.in_([int(w) for w in walk_ids]))
        with Session(self.engine) as s:
            states = {r.walk_id: r for r in s.execute(select(m.WalkSlam).where(*cond)).scalars()}
            if not states:
                return {}
            pts: dict[int, list] = {}
            q = (
                select(
                    m.TrackPoint.walk_id, m.TrackPoint.t, m.TrackPoint.kind, m.TrackPoint.floor, m.TrackPoint.x, m.TrackPoint.y,
                    m.TrackPoint.cov_xx, m.TrackPoint.cov_xy, m.TrackPoint.cov_yy,
                )
                .join(m.WalkSlam, (m.WalkSlam.walk_id == m.TrackPoint.walk_id) & (m.WalkSlam.run_id == m.TrackPoint.run_id))
                .where(*cond)
                .order_by(m.TrackPoint.walk_id, m.TrackPoint.t, m.TrackPoint.id)
            )  # fmt: skip
            for row in s.execute(q):
                pts.setdefault(row[0], []).append(row[1:])
        out = {}
        for wid, rows in pts.items():
            if floor is not None and not any(r[2] == floor for r in rows):
                continue
            st = states[wid]
            out[wid] = _track_of(wid, rows, st.anchored, st.scale, st.heading_bias)
        return out

    def run_tracks(self, run_id: int, floors: Iterable[str] | None = None, statuses: Iterable[str] | None = None) -> dict[int, CorrectedTrack]:
        """The tracks a batch run wrote (walk id -> track), finished or still running: what its floors
        solved (``floors``: of those floors only; ``statuses``: of walks in those states), read from its
        checkpoints. A resumed run reads the
        floors it solved before it was killed through this."""
        keep = None if floors is None else set(floors)
        keep_st = None if statuses is None else set(statuses)
        with Session(self.engine) as s:
            meta: dict[int, dict] = {}
            for fd in s.execute(select(m.SlamFloorDone).where(m.SlamFloorDone.run_id == run_id)).scalars():
                if keep is not None and fd.floor not in keep:
                    continue
                for wid, w in (fd.stats or {}).get("walks", {}).items():
                    if w["n_points"] > 0 and (keep_st is None or w["status"] in keep_st):
                        meta[int(wid)] = w
            if not meta:
                return {}
            q = (
                select(
                    m.TrackPoint.walk_id, m.TrackPoint.t, m.TrackPoint.kind, m.TrackPoint.floor, m.TrackPoint.x, m.TrackPoint.y,
                    m.TrackPoint.cov_xx, m.TrackPoint.cov_xy, m.TrackPoint.cov_yy,
                )
                .where(m.TrackPoint.run_id == run_id, m.TrackPoint.walk_id.in_(list(meta)))
                .order_by(m.TrackPoint.walk_id, m.TrackPoint.t, m.TrackPoint.id)
            )  # fmt: skip
            pts: dict[int, list] = {}
            for row in s.execute(q):
                if keep is None or row[3] in keep:
                    pts.setdefault(row[0], []).append(row[1:])
        return {wid: _track_of(wid, rows, meta[wid]["anchored"], meta[wid]["scale"], meta[wid]["heading_bias"]) for wid, rows in pts.items()}

    def track(self, site: str, walk_id: int) -> CorrectedTrack | None:
        return self.tracks(site, walk_ids=[walk_id]).get(int(walk_id))

    @staticmethod
    def _audit_rule(s: Session, site: str) -> Callable[[int, str], bool]:
        """Which loop rows the current audit holds: per floor, those of the newest complete batch run that
        solved the floor, plus those of walks added one by one after it (never a running or failed
        run's). Returns ``in_audit(run_id, floor)``."""
        kind = dict(s.execute(select(m.SlamRun.id, m.SlamRun.kind).where(m.SlamRun.site_id == site, m.SlamRun.status == COMPLETE)).all())
        latest_batch: dict[str, int] = {}
        batch_ids = [rid for rid, k in kind.items() if k == "batch"]
        if batch_ids:
            q = select(m.SlamFloorDone.floor, func.max(m.SlamFloorDone.run_id)).where(m.SlamFloorDone.run_id.in_(batch_ids))
            latest_batch = {str(f): int(r) for f, r in s.execute(q.group_by(m.SlamFloorDone.floor)).all()}

        def in_audit(run_id: int, floor: str) -> bool:
            base = latest_batch.get(floor, 0)
            k = kind.get(run_id)
            return (k == "batch" and run_id == base) or (k == "walk" and run_id > base)

        return in_audit

    def loops(self, site: str, floor: str | None = None) -> list[LoopRow]:
        """The current loop audit of ``site`` (:meth:`_audit_rule`), of ``floor`` when given."""
        cond = [m.LoopClosure.site_id == site] + ([m.LoopClosure.floor == floor] if floor is not None else [])
        with Session(self.engine) as s:
            in_audit = self._audit_rule(s, site)
            rows = s.execute(select(m.LoopClosure).where(*cond).order_by(m.LoopClosure.id)).scalars().all()
            return [
                LoopRow(r.run_id, r.floor, r.walk_a, r.t_a, r.walk_b, r.t_b, r.similarity, r.weight, r.p_inlier, r.accepted, r.reason, r.kind)
                for r in rows
                if in_audit(r.run_id, r.floor)
            ]

    def loop_counts(self, site: str) -> tuple[int, int]:
        """(accepted, rejected) loops of the current audit (the rows :meth:`loops` returns), counted in
        the database: a site's audit grows to tens of thousands of rows, and the summary answers every
        status query."""
        q = (
            select(m.LoopClosure.run_id, m.LoopClosure.floor, m.LoopClosure.accepted, func.count())
            .where(m.LoopClosure.site_id == site)
            .group_by(m.LoopClosure.run_id, m.LoopClosure.floor, m.LoopClosure.accepted)
        )
        counts = [0, 0]  # rejected, accepted
        with Session(self.engine) as s:
            in_audit = self._audit_rule(s, site)
            for rid, floor, accepted, n in s.execute(q).all():
                if in_audit(rid, floor):
                    counts[bool(accepted)] += int(n)
        return counts[1], counts[0]

    def summary(self, site: str) -> dict:
        """Per-site SLAM figures (what ``hybridloc status`` shows): walks by state, pending walks, loops
        accepted and rejected, coverage (share of the scans of walks without survey marks that have an
        absolute corrected position), the newest radio map version and its source, the newest runs."""
        with Session(self.engine) as s:
            by = dict(s.execute(select(m.WalkSlam.status, func.count()).where(m.WalkSlam.site_id == site).group_by(m.WalkSlam.status)).all())
            ended = s.execute(
                select(func.count()).select_from(m.Walk).where(m.Walk.site_id == site, m.Walk.end_reason != WalkEnd.OPEN.value)
            ).scalar_one()
            crowd = s.execute(
                select(func.coalesce(func.sum(m.Walk.n_scans), 0)).where(
                    m.Walk.site_id == site, m.Walk.end_reason != WalkEnd.OPEN.value, m.Walk.n_marks == 0
                )
            ).scalar_one()
            covered = s.execute(
                select(func.coalesce(func.sum(m.Walk.n_scans), 0))
                .join(m.WalkSlam, m.WalkSlam.walk_id == m.Walk.id)
                .where(m.Walk.site_id == site, m.Walk.n_marks == 0, m.WalkSlam.status == CORRECTED, m.WalkSlam.anchored != "relative")
            ).scalar_one()
            newest = s.execute(
                select(m.RadioMapVersion.version, m.RadioMapVersion.source)
                .where(m.RadioMapVersion.site_id == site)
                .order_by(m.RadioMapVersion.version.desc())
                .limit(1)
            ).first()
            last_batch = s.execute(
                select(m.SlamRun).where(m.SlamRun.site_id == site, m.SlamRun.kind == "batch").order_by(m.SlamRun.id.desc()).limit(1)
            ).scalar_one_or_none()
            last_info = self._run_info(s, last_batch) if last_batch is not None else None
        loops_accepted, loops_rejected = self.loop_counts(site)
        seen = sum(by.values())
        return {
            "walks_ended": int(ended),
            "walks_corrected": int(by.get(CORRECTED, 0)),
            "walks_relative": int(by.get(RELATIVE, 0)),
            "walks_quarantined": int(by.get(QUARANTINED, 0)),
            "walks_failed": int(by.get(FAILED, 0)),
            "walks_pending": int(ended) - int(seen),
            "loops_accepted": loops_accepted,
            "loops_rejected": loops_rejected,
            "coverage": (float(covered) / float(crowd)) if crowd else None,
            "map_version": int(newest[0]) if newest else None,
            "map_source": str(newest[1]) if newest else None,
            "last_batch": None
            if last_info is None
            else {
                "run": last_info.run_id,
                "status": last_info.status,
                "floors_done": list(last_info.floors_done),
                "map_version": last_info.map_version,
            },
        }

    def quarantined(self, site: str) -> list[WalkState]:
        return [w for w in self.walk_states(site).values() if w.status == QUARANTINED]


def _track_of(walk_id: int, rows: list, anchored: str, scale: float | None, heading_bias: float | None) -> CorrectedTrack:
    """A CorrectedTrack from track_point rows (t, kind, floor, x, y, cov_xx, cov_xy, cov_yy) in time order."""
    nan = float("nan")

    def v(x):
        return nan if x is None else x

    cov = np.array([[[v(r[5]), v(r[6])], [v(r[6]), v(r[7])]] for r in rows]).reshape(-1, 2, 2)
    return CorrectedTrack(
        walk_id,
        np.array([r[0] for r in rows], float),
        np.array([[r[3], r[4]] for r in rows], float).reshape(-1, 2),
        cov,
        tuple(r[2] for r in rows),
        tuple(r[1] for r in rows),
        anchored,
        scale if scale is not None else 1.0,
        heading_bias if heading_bias is not None else 0.0,
    )


#: which state a walk solved on several floors takes: the most cautious first (quarantined on one floor
#: keeps it out of every solve), then corrected (an absolute piece anywhere is a correction)
_STATUS_RANK = {QUARANTINED: 0, CORRECTED: 1, RELATIVE: 2, FAILED: 3}


def _walks_over_floors(per_floor: Sequence[dict]) -> dict[int, dict]:
    """The walk states of a batch run's floor checkpoints, one per walk: a walk crossing floors has a
    checkpoint entry on each floor it walked, each with that floor's points only (none where it stayed
    relative there), and all of its points are kept: the counts add up, the state is the highest
    ranked of its floors' (:data:`_STATUS_RANK`; its reason and anchoring go with it, the first absolute
    anchoring where it has none), the scale and heading bias are those of the floor with most points
    (the longest piece estimated them). Floors in a fixed order, so ties resolve alike on every run."""
    out: dict[int, dict] = {}
    longest: dict[int, int] = {}  # points of the piece whose scale and heading bias a walk holds
    for walks in per_floor:
        for wid, w in walks.items():
            k = int(wid)
            a = out.get(k)
            if a is None:
                out[k], longest[k] = dict(w), w["n_points"]
                continue
            a["n_points"] += w["n_points"]
            if _STATUS_RANK.get(w["status"], len(_STATUS_RANK)) < _STATUS_RANK.get(a["status"], len(_STATUS_RANK)):
                a["status"], a["reason"], a["anchored"] = w["status"], w["reason"], w["anchored"]
            if a["anchored"] == "relative" and w["anchored"] != "relative" and w["n_points"] > 0:
                a["anchored"] = w["anchored"]
            if w["n_points"] > longest[k]:
                a["scale"], a["heading_bias"], longest[k] = w["scale"], w["heading_bias"], w["n_points"]
    return out

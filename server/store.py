"""Persisting batches: one transaction per group of batches, idempotent by (device, seq), go-back-N.

:meth:`Store.persist` takes decoded batches in arrival order and returns, per device, the highest
sequence number now persisted (what the server acknowledges). A batch is written only if it is the
next one of its device; duplicates and gaps are counted as rejections (reasons ``duplicate`` and
``out-of-order``) and change nothing. Validation failures before this point are passed in and stored
in the same transaction.

Walks. Each persisted batch joins its device's open walk or opens a new one: a batch whose records lie
more than :data:`WALK_IDLE_GAP_S` (device clock) from the open walk's span [t_start, t_end] starts a
new walk and the open one ends ``idle``; a batch carrying the end-of-walk marker is its walk's last
(``marker``). The span, not the previous batch alone, is what a batch is compared with: a client
sends a stretch's steps and its scans in separate batches whose times interleave. A batch without
records joins the open walk, if any. :meth:`Store.walks` lists stored walks (summaries) and
:meth:`Store.read_walk` returns one as a :class:`hybridloc.types.Walk`; the SLAM work reads walks
through these, never through raw rows.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from collections import Counter
from collections.abc import Collection
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass
from itertools import repeat
from typing import cast

import msgspec
from sqlalchemy import CursorResult, Table, func, insert, select, update
from sqlalchemy.engine import Engine
from sqlalchemy.orm import Session

from hybridloc.types import RfScan, StepEvent, SurveyMark, Walk, WalkEnd
from hybridloc.wire.codecs import step_times
from hybridloc.wire.messages import Batch, StepColumns

from . import db as m
from .migrate import upgrade

#: Device-clock silence, s, that ends a walk. Longer than any silence inside one: Android (9 and later)
#: lets a foreground app scan WiFi 4 times per 2 minutes, so a phone standing still (no steps) may
#: send nothing for up to 120 s and still be on its walk; the Indoor Location Competition's site1
#: walks never go more than 15.5 s between scans (60 of 305 walks read). 180 s keeps a margin over
#: 120 s and still splits a device's separate walks, which are minutes to days apart.
WALK_IDLE_GAP_S = 180.0


@dataclass(frozen=True)
class WalkInfo:
    """A stored walk without its data (what :meth:`Store.walks` lists).

    ``t_start``/``t_end`` in s on the device's clock; ``floors`` in order of first appearance;
    ``created_at``/``updated_at`` are the server's times (UTC) of its first and latest batch.
    """

    walk_id: int
    site: str
    device: str
    device_model: str
    t_start: float
    t_end: float
    floors: tuple[str, ...]
    end: WalkEnd
    n_batches: int
    n_steps: int
    n_scans: int
    n_marks: int
    created_at: dt.datetime
    updated_at: dt.datetime

    @property
    def duration(self) -> float:
        """s."""
        return self.t_end - self.t_start


def _span_gap(w: m.Walk, lo: float, hi: float) -> float:
    """Time between the record span [lo, hi] and the walk's [t_start, t_end], s (<= 0 when they overlap)."""
    return max(lo - w.t_end, w.t_start - hi)


def _newest_floor_plan(s: Session, site: str) -> m.FloorPlanVersion | None:
    """The site's newest ``floor_plan`` row (the highest id), or None."""
    return (
        s.execute(select(m.FloorPlanVersion).where(m.FloorPlanVersion.site_id == site).order_by(m.FloorPlanVersion.id.desc()).limit(1))
        .scalars()
        .first()
    )


class Store:
    def __init__(self, url: str, migrate: bool = True, wal_autocheckpoint: int | None = None):
        """The store on ``url`` (migrated to the newest revision unless ``migrate`` is false);
        ``wal_autocheckpoint``: SQLite's autocheckpoint in pages (:func:`~.db.make_engine`)."""
        self.engine: Engine = m.make_engine(url, wal_autocheckpoint)
        self._sqlite = self.engine.dialect.name == "sqlite"
        #: held around each ingest transaction (:meth:`persist`) when set: SQLite's ingest workers share one
        #: (:mod:`.ingest_pool`), so the writer after another starts at its commit instead of polling
        #: for SQLite's lock in sleeps of milliseconds
        self.write_lock: AbstractContextManager = nullcontext()
        if migrate:
            upgrade(self.engine)

    def close(self) -> None:
        self.engine.dispose()

    @property
    def slam(self):
        """The crowd SLAM's storage (:class:`hybridloc.server.slam_store.SlamStore`) on the same engine."""
        from .slam_store import SlamStore

        if getattr(self, "_slam", None) is None:
            self._slam = SlamStore(self.engine)
        return self._slam

    def persist(
        self,
        batches: list[Batch],
        invalid: Counter | None = None,
        end_of_walk: Collection[tuple[str, int]] = (),
        written_ids: list[tuple[str, int]] | None = None,
    ) -> tuple[dict[str, int], Counter, int]:
        """(highest persisted seq per device, rejections by (device, reason), batches written).

        ``written_ids``, when given, receives the (device, seq) of every batch written (not the
        duplicates and out-of-order ones), so the caller answers each stored batch once.

        ``invalid`` counts messages already refused by validation; they are stored in the same
        transaction (and included in the returned rejections). ``end_of_walk`` names the batches, as
        (device, seq), that carry the end-of-walk marker; a batch whose ``end_of_walk`` attribute is
        true counts too.

        A group costs a fixed number of statements, not a number per batch: the devices, their open
        walks and their rejection rows are read in one query each, the batch rows are inserted in one
        multi-row INSERT ... RETURNING id, and the steps, scans and marks of the whole group in one
        executemany each (a thousand devices sending a batch a second arrive as groups of hundreds
        of one-batch devices; per-batch statements made the database most of the ingest time).
        """
        acked: dict[str, int] = {}
        rejected: Counter = Counter(invalid or {})
        written = 0
        if not batches and not rejected:
            return acked, rejected, written
        ends = set(end_of_walk)
        # the scans' readings as JSON text before the transaction (no database in it): a writer holds
        # SQLite's lock for less time beside other writers
        readings = {id(b): [readings_json(_readings(sc)) for sc in b.scans] for b in batches}
        with self.write_lock, Session(self.engine) as s, s.begin():
            if self._sqlite:
                # SQLite's write lock taken now, not at the first write: another writer's commit between
                # our reads and our first write would otherwise fail it at once (a read snapshot
                # cannot become a write transaction, SQLITE_BUSY_SNAPSHOT: no busy timeout applies);
                # taken now, it waits for the other's commit (ingest workers, the SLAM child, fixes)
                s.connection().exec_driver_sql("BEGIN IMMEDIATE")
            ids = list(dict.fromkeys(b.device for b in batches))
            devices = {d.id: d for d in _chunked_in(s, select(m.Device), m.Device.id, ids)}
            new_devs = [b for b in {b.device: b for b in reversed(batches)}.values() if b.device not in devices]
            if new_devs:
                have = {x.id for x in _chunked_in(s, select(m.Site), m.Site.id, list({b.site for b in new_devs}))}
                s.add_all([m.Site(id=x, name=x) for x in dict.fromkeys(b.site for b in new_devs) if x not in have])
                s.flush()
                for b in sorted(new_devs, key=lambda b: ids.index(b.device)):
                    devices[b.device] = m.Device(id=b.device, site_id=b.site, model=b.device_model, last_seq=0)
                    s.add(devices[b.device])
                s.flush()
            # the newest open walk of each device (what _join_walk continues)
            open_walks: dict[str, m.Walk | None] = dict.fromkeys(ids)
            for w in _chunked_in(s, select(m.Walk).where(m.Walk.end_reason == WalkEnd.OPEN.value).order_by(m.Walk.id), m.Walk.device_id, ids):
                open_walks[w.device_id] = w
            rows: list[dict] = []
            kept: list[tuple[Batch, m.Walk | None]] = []
            floors_named: list[tuple[m.Walk, str, float]] = []
            now = m.utcnow()
            for b in batches:
                dev = devices[b.device]
                if b.seq <= dev.last_seq:
                    rejected[(b.device, "duplicate")] += 1
                    acked[b.device] = dev.last_seq
                    continue
                if b.seq != dev.last_seq + 1:
                    rejected[(b.device, "out-of-order")] += 1
                    acked[b.device] = dev.last_seq
                    continue
                w = self._join_walk(s, b, dev, open_walks, getattr(b, "end_of_walk", False) or (b.device, b.seq) in ends, floors_named)
                rows.append(
                    {
                        "device_id": b.device,
                        "seq": b.seq,
                        "received_at": now,
                        "n_steps": len(b.steps),
                        "n_scans": len(b.scans),
                        "n_marks": len(b.marks),
                    }
                )
                kept.append((b, w))
                dev.last_seq = b.seq
                dev.last_seen = now
                if b.device_model and not dev.model:
                    dev.model = b.device_model
                acked[b.device] = b.seq
                written += 1
                for reason, n in b.refused:  # counted once, with the batch that carried them (a resend is a duplicate)
                    rejected[(b.device, reason)] += n
                if written_ids is not None:
                    written_ids.append((b.device, b.seq))
            if kept:
                s.flush()  # new walks get their ids; the walks' and devices' changes are written
                _name_floors(s, [(w.id, floor, t) for w, floor, t in floors_named])
                for r, (_, w) in zip(rows, kept):
                    r["walk_id"] = None if w is None else w.id
                batch_ids = s.execute(insert(m.Batch).returning(m.Batch.id, sort_by_parameter_order=True), rows).scalars().all()
                self._insert_records(s, [(bid, b) for bid, (b, _) in zip(batch_ids, kept)], readings)
            self._add_rejections(s, rejected)
        return acked, rejected, written

    @staticmethod
    def _insert_records(s: Session, stored: list[tuple[int, Batch]], readings: dict[int, list[str]]) -> None:
        """The steps, scans and marks of the batches ``stored`` as (batch row id, batch): an executemany each.

        The steps, a thousand rows a large batch, and the scans go to the driver's executemany as plain
        tuples (the ORM's bulk INSERT built a parameter dict per row, and Core's a parameter dict and a
        JSON bind per scan: most of a large batch's storing time); a decoded batch's steps are read from
        their columns (:class:`~hybridloc.wire.messages.StepColumns`), never made into records. A scan's
        readings are JSON text by msgspec (:func:`readings_json`), given in ``readings`` (the texts of
        each batch's scans, by the batch's ``id()``). The marks, few, through Core."""
        steps: list[tuple] = []
        for bid, b in stored:
            if isinstance(b.steps, StepColumns):
                steps += zip(repeat(bid), repeat(b.device), *b.steps.columns)
            else:
                steps += [
                    (
                        bid, b.device, st.t, st.length, st.heading, st.sigma_length, st.sigma_heading, st.heading_change,
                        st.sigma_heading_change, st.height_change, st.sigma_height_change, st.floor_change, st.degraded,
                    )
                    for st in b.steps
                ]  # fmt: skip
        paramstyle = s.get_bind().dialect.paramstyle
        conn = s.connection()
        if steps:
            conn.exec_driver_sql(_insert_sql("step", _STEP_COLUMNS, paramstyle), steps)
        scans = [
            (bid, b.device, sc.t, sc.technology.value, text)
            for bid, b in stored
            for sc, text in zip(b.scans, readings[id(b)])
        ]  # fmt: skip
        if scans:
            conn.exec_driver_sql(_insert_sql("scan", _SCAN_COLUMNS, paramstyle), scans)
        marks = [{"batch_id": bid, "device_id": b.device, "t": mk.t, "x": mk.x, "y": mk.y, "floor": mk.floor} for bid, b in stored for mk in b.marks]
        if marks:
            s.execute(insert(cast(Table, m.SurveyMark.__table__)), marks)

    @staticmethod
    def _join_walk(
        s: Session, b: Batch, dev: m.Device, open_walks: dict[str, m.Walk | None], ends_walk: bool, floors_named: list[tuple[m.Walk, str, float]]
    ) -> m.Walk | None:
        """The walk the batch ``b`` joins: its device's open walk, or a new one after an idle gap (module
        docstring); None for a batch of nothing with no open walk. New walks are added to ``s`` (their
        ids come with the next flush); the floors their marks name are listed in ``floors_named``."""
        w = open_walks[b.device]
        times = step_times(b.steps) + [r.t for r in b.scans] + [r.t for r in b.marks]
        if times:
            lo, hi = min(times), max(times)
            if w is None or _span_gap(w, lo, hi) > WALK_IDLE_GAP_S:
                if w is not None:
                    w.end_reason = WalkEnd.IDLE.value
                w = m.Walk(
                    site_id=dev.site_id,
                    device_id=b.device,
                    t_start=lo,
                    t_end=hi,
                    device_model=b.device_model or dev.model,
                    end_reason=WalkEnd.OPEN.value,
                    n_batches=0,
                    n_steps=0,
                    n_scans=0,
                    n_marks=0,
                )
                s.add(w)
            w.t_start, w.t_end = min(w.t_start, lo), max(w.t_end, hi)
            floors_named += [(w, mk.floor, mk.t) for mk in b.marks if mk.floor]
        if w is None:
            return None  # no records and no open walk: a batch of nothing belongs to no walk
        joined = w
        w.n_batches += 1
        w.n_steps += len(b.steps)
        w.n_scans += len(b.scans)
        w.n_marks += len(b.marks)
        if b.device_model and not w.device_model:
            w.device_model = b.device_model
        w.updated_at = m.utcnow()
        if ends_walk:
            w.end_reason = WalkEnd.MARKER.value
            w = None
        open_walks[b.device] = w
        return joined

    @staticmethod
    def _add_rejections(s: Session, counts: Counter) -> None:
        if not counts:
            return
        have = {(r.device_id, r.reason): r for r in _chunked_in(s, select(m.Rejection), m.Rejection.device_id, list({d for d, _ in counts}))}
        for (device, reason), n in counts.items():
            row = have.get((device, reason))
            if row is None:
                have[(device, reason)] = row = m.Rejection(device_id=device, reason=reason, count=n)
                s.add(row)
            else:
                row.count += n

    def last_seq(self, device: str) -> int:
        with Session(self.engine) as s:
            dev = s.get(m.Device, device)
            return dev.last_seq if dev else 0

    def add_fix(self, device: str, fix) -> None:
        self.add_fixes([(device, fix)])

    def add_fixes(self, fixes: list) -> None:
        """Store (device, AbsoluteFix) pairs in one transaction; a fix's floor joins the floors of the
        device's latest walk whose span holds the fix's time. The fixes go in one executemany and the
        candidate walks are read in one query (a group's fixes are one per device)."""
        if not fixes:
            return
        with Session(self.engine) as s, s.begin():
            s.execute(
                insert(m.Fix),
                [
                    {
                        "device_id": d,
                        "t": f.t,
                        "x": float(f.pos_enu[0]),
                        "y": float(f.pos_enu[1]),
                        "floor": f.floor,
                        "cov": f.cov.tolist(),
                        "source": f.source.value,
                    }
                    for d, f in fixes
                ],
            )
            named = [(d, f) for d, f in fixes if f.floor]
            if not named:
                return
            lo, hi = min(f.t for _, f in named), max(f.t for _, f in named)
            spans: dict[str, list[tuple[int, float, float]]] = {}
            for wid, dev, t0, t1 in _chunked_in(
                s,
                select(m.Walk.id, m.Walk.device_id, m.Walk.t_start, m.Walk.t_end)
                .where(m.Walk.t_start <= hi, m.Walk.t_end >= lo)
                .order_by(m.Walk.id.desc()),
                m.Walk.device_id,
                list({d for d, _ in named}),
                scalars=False,
            ):
                spans.setdefault(dev, []).append((wid, t0, t1))
            named_walks = []
            for d, f in named:
                wid = next((w for w, t0, t1 in spans.get(d, ()) if t0 <= f.t <= t1), None)
                if wid is not None:
                    named_walks.append((wid, f.floor, f.t))
            _name_floors(s, named_walks)

    # -------------------------------------------------------------- walks
    def walks(
        self, site: str, device: str | None = None, floor: str | None = None, since: float | None = None, ended_only: bool = False
    ) -> list[WalkInfo]:
        """The site's stored walks, by start time: of ``device``, naming ``floor``, with records at or
        after ``since`` (device clock, s: t_end >= since), ended (by a marker or an idle gap) only."""
        cond = [m.Walk.site_id == site]
        if device is not None:
            cond.append(m.Walk.device_id == device)
        if since is not None:
            cond.append(m.Walk.t_end >= since)
        if ended_only:
            cond.append(m.Walk.end_reason != WalkEnd.OPEN.value)
        if floor is not None:
            cond.append(m.Walk.id.in_(select(m.WalkFloor.walk_id).where(m.WalkFloor.floor == floor)))
        with Session(self.engine) as s:
            rows = s.execute(select(m.Walk).where(*cond).order_by(m.Walk.t_start, m.Walk.id)).scalars().all()
            floors: dict[int, list[str]] = {}
            for wid, fl in s.execute(
                select(m.WalkFloor.walk_id, m.WalkFloor.floor)
                .join(m.Walk, m.Walk.id == m.WalkFloor.walk_id)
                .where(*cond)
                .order_by(m.WalkFloor.walk_id, m.WalkFloor.t_first, m.WalkFloor.floor)
            ):
                floors.setdefault(wid, []).append(fl)
            return [
                WalkInfo(
                    w.id,
                    w.site_id,
                    w.device_id,
                    w.device_model,
                    w.t_start,
                    w.t_end,
                    tuple(floors.get(w.id, ())),
                    WalkEnd(w.end_reason),
                    w.n_batches,
                    w.n_steps,
                    w.n_scans,
                    w.n_marks,
                    w.created_at,
                    w.updated_at,
                )
                for w in rows
            ]

    def read_walk(self, walk_id: int) -> Walk:
        """A stored walk with its data: every step field, every scan's RSSI, ages and frequencies, the
        survey marks, each sorted by time (ties in arrival order). KeyError for an unknown id.

        Scans and marks are selected by the walk's device and time span (``ix_scan_device_t``,
        ``ix_survey_mark_device_t``) and kept when their batch is the walk's (``ix_batch_walk_id``).
        SQLite's plan: SEARCH scan USING INDEX ix_scan_device_t (device_id=? AND t>? AND t<?), SEARCH
        batch USING COVERING INDEX ix_batch_walk_id (walk_id=? AND rowid=?), no sort (the index is in
        (t, id) order). Steps, the table ingest writes most, have no such index (it cost as much as the
        rows at ingest: migration 0004) and are read through the walk's batches: SEARCH batch USING
        COVERING INDEX ix_batch_walk_id (walk_id=?), SEARCH step USING INDEX ix_step_batch_id
        (batch_id=?), then a sort of the walk's steps by time. So the records themselves need no ``walk_id``.
        """
        with Session(self.engine) as s:
            w = s.get(m.Walk, walk_id)
            if w is None:
                raise KeyError(f"no stored walk {walk_id!r}")

            def records(model):
                return s.execute(
                    select(model)
                    .join(m.Batch, m.Batch.id == model.batch_id)
                    .where(model.device_id == w.device_id, model.t >= w.t_start, model.t <= w.t_end, m.Batch.walk_id == w.id)
                    .order_by(model.t, model.id)
                ).scalars()

            steps = [
                StepEvent(
                    r.t,
                    r.length,
                    r.heading,
                    r.sigma_length,
                    r.sigma_heading,
                    r.heading_change,
                    r.sigma_heading_change,
                    r.height_change,
                    r.sigma_height_change,
                    r.floor_change,
                    r.degraded,
                )
                for r in records(m.Step)
            ]
            scans = [
                RfScan(r.t, r.technology, r.readings["rssi"], r.readings.get("freq", {}), r.readings.get("age", {}), w.device_model)
                for r in records(m.Scan)
            ]
            marks = [SurveyMark(r.t, r.x, r.y, r.floor) for r in records(m.SurveyMark)]
            floors = (
                s.execute(select(m.WalkFloor.floor).where(m.WalkFloor.walk_id == w.id).order_by(m.WalkFloor.t_first, m.WalkFloor.floor))
                .scalars()
                .all()
            )
            return Walk(
                w.site_id,
                w.device_id,
                w.id,
                w.t_start,
                w.t_end,
                w.device_model,
                tuple(floors),
                tuple(steps),
                tuple(scans),
                tuple(marks),
                WalkEnd(w.end_reason),
            )

    def close_idle_walks(self, idle_s: float = WALK_IDLE_GAP_S, now: dt.datetime | None = None) -> int:
        """End (``idle``) the open walks whose latest batch arrived more than ``idle_s`` before ``now``
        (server clock); the number ended. For a live server, where no later batch may ever come."""
        cutoff = (now or m.utcnow()) - dt.timedelta(seconds=idle_s)
        with Session(self.engine) as s, s.begin():
            res = s.execute(
                update(m.Walk).where(m.Walk.end_reason == WalkEnd.OPEN.value, m.Walk.updated_at < cutoff).values(end_reason=WalkEnd.IDLE.value)
            )
            return int(cast(CursorResult, res).rowcount)

    # -------------------------------------------------------------- floor plans
    def save_floor_plan(self, site: str, plan) -> int:
        """Store a :class:`~hybridloc.types.FloorPlan` as the site's newest floor plan (one GeoJSON row of
        the ``floor_plan`` table, :mod:`hybridloc.io.floorplan_geojson`); returns the row id. The site's
        ``floor`` rows are added or updated (name, level). A plan the same as the newest one (the same
        GeoJSON) is not stored again: its row id is returned (an import run twice adds no version)."""
        from hybridloc.io.floorplan_geojson import floorplan_to_geojson

        text = floorplan_to_geojson(plan)
        with Session(self.engine) as s, s.begin():
            site_row = s.get(m.Site, site)
            if site_row is None:
                site_row = m.Site(id=site, name=site)
                s.add(site_row)
            if plan.origin is not None:
                site_row.origin_lat_deg = math.degrees(plan.origin.lat)
                site_row.origin_lon_deg = math.degrees(plan.origin.lon)
            s.flush()
            have = {f.name: f for f in s.execute(select(m.Floor).where(m.Floor.site_id == site)).scalars()}
            for f in plan.floors:
                if f.name in have:
                    have[f.name].level = int(f.level)
                else:
                    s.add(m.Floor(site_id=site, name=f.name, level=int(f.level)))
            last = _newest_floor_plan(s, site)
            if last is not None and last.geojson == text:
                return int(last.id)
            row = m.FloorPlanVersion(site_id=site, geojson=text)
            s.add(row)
            s.flush()
            return int(row.id)

    def floor_plan_version(self, site: str) -> int | None:
        """The row id of the site's newest floor plan, or None."""
        with Session(self.engine) as s:
            row = _newest_floor_plan(s, site)
            return None if row is None else int(row.id)

    def load_floor_plan(self, site: str):
        """The site's newest floor plan (:class:`~hybridloc.types.FloorPlan`), or None."""
        from hybridloc.io.floorplan_geojson import floorplan_from_geojson

        with Session(self.engine) as s:
            row = _newest_floor_plan(s, site)
            return None if row is None else floorplan_from_geojson(row.geojson, source=f"floor plan {row.id} of site {site!r}")

    # -------------------------------------------------------------- radio maps
    def save_map(self, site: str, data: bytes, n_scans: int = 0, source: str = "import", provenance: dict | None = None) -> int:
        """Store ``data`` as the site's next radio map version; ``source`` "import" / "survey" / "slam", and
        what built it (``provenance``: walk ids, survey walks, marks). Safe beside another writer of map
        versions (:func:`~.db.lock_site`)."""
        return m.retry_unique(lambda: self._save_map(site, data, n_scans, source, provenance))

    def _save_map(self, site: str, data: bytes, n_scans: int, source: str, provenance: dict | None) -> int:
        with Session(self.engine) as s, s.begin():
            m.lock_site(s, site)  # the next version is read after any other writer's commit
            last = s.execute(
                select(m.RadioMapVersion.version).where(m.RadioMapVersion.site_id == site).order_by(m.RadioMapVersion.version.desc())
            ).first()
            v = (last[0] if last else 0) + 1
            s.add(m.RadioMapVersion(site_id=site, version=v, n_scans=n_scans, data=data, source=source, provenance=provenance))
            return v

    def map_versions(self, site: str) -> list[tuple[int, str, bytes]]:
        """Every stored radio map of ``site``, oldest first: (version, source, file bytes)."""
        with Session(self.engine) as s:
            q = select(m.RadioMapVersion.version, m.RadioMapVersion.source, m.RadioMapVersion.data).where(m.RadioMapVersion.site_id == site)
            return [(int(v), str(src), bytes(d)) for v, src, d in s.execute(q.order_by(m.RadioMapVersion.version)).all()]

    def map_version(self, site: str, version: int) -> bytes | None:
        """The file bytes of one stored radio map version of ``site`` (None when it is not stored)."""
        with Session(self.engine) as s:
            row = s.execute(
                select(m.RadioMapVersion.data).where(m.RadioMapVersion.site_id == site, m.RadioMapVersion.version == int(version))
            ).first()
            return None if row is None else bytes(row[0])

    def load_map(self, site: str) -> tuple[int, bytes] | None:
        with Session(self.engine) as s:
            row = (
                s.execute(select(m.RadioMapVersion).where(m.RadioMapVersion.site_id == site).order_by(m.RadioMapVersion.version.desc()))
                .scalars()
                .first()
            )
            return (row.version, row.data) if row else None

    def rejections_by_device(self) -> dict[str, dict[str, int]]:
        """Stored rejections: device -> reason -> count (``?``: messages on keys naming no device)."""
        out: dict[str, dict[str, int]] = {}
        with Session(self.engine) as s:
            for r in s.execute(select(m.Rejection).order_by(m.Rejection.device_id, m.Rejection.reason)).scalars():
                out.setdefault(r.device_id, {})[r.reason] = int(r.count)
        return out

    def status(self) -> dict:
        with Session(self.engine) as s:
            return {
                "devices": s.execute(select(func.count()).select_from(m.Device)).scalar_one(),
                "batches": s.execute(select(func.count()).select_from(m.Batch)).scalar_one(),
                "steps": s.execute(select(func.count()).select_from(m.Step)).scalar_one(),
                "scans": s.execute(select(func.count()).select_from(m.Scan)).scalar_one(),
                "marks": s.execute(select(func.count()).select_from(m.SurveyMark)).scalar_one(),
                "fixes": s.execute(select(func.count()).select_from(m.Fix)).scalar_one(),
                "walks": s.execute(select(func.count()).select_from(m.Walk)).scalar_one(),
                "rejections": _rejections(s),
                "maps": {
                    site: v
                    for site, v in s.execute(
                        select(m.RadioMapVersion.site_id, func.max(m.RadioMapVersion.version)).group_by(m.RadioMapVersion.site_id)
                    ).all()
                },
            }


#: The step table's columns as :meth:`Store._insert_records` writes them (all but the id)
_STEP_COLUMNS = (
    "batch_id",
    "device_id",
    "t",
    "length",
    "heading",
    "sigma_length",
    "sigma_heading",
    "heading_change",
    "sigma_heading_change",
    "height_change",
    "sigma_height_change",
    "floor_change",
    "degraded",
)


#: The scan table's columns as :meth:`Store._insert_records` writes them (``readings``: JSON text)
_SCAN_COLUMNS = ("batch_id", "device_id", "t", "technology", "readings")


def _insert_sql(table: str, columns: tuple[str, ...], paramstyle: str) -> str:
    """INSERT INTO table (...) VALUES (...) in the driver's positional style (sqlite3 ``qmark``,
    psycopg ``format``/``pyformat``)."""
    mark = "?" if paramstyle == "qmark" else "%s"
    return f"INSERT INTO {table} ({', '.join(columns)}) VALUES ({', '.join([mark] * len(columns))})"


def _step_insert_sql(paramstyle: str) -> str:
    """INSERT INTO step (...) VALUES (...) in the driver's positional style."""
    return _insert_sql("step", _STEP_COLUMNS, paramstyle)


def readings_json(readings: dict) -> str:
    """The JSON text of a scan's ``readings`` column. msgspec's encoder: the same values as ``json.dumps``
    (SQLAlchemy's JSON type) gives, read back bit for bit (shortest round-trip floats; the readings are
    finite, checked on decoding), without the spaces after separators. 5.7x faster on site1's scans
    (349 transmitters with frequency and age: 1.08 -> 0.19 ms a scan), which was about a scan's
    locating time again at 1,000 live clients (tests/test_store.py holds the two to each other). Where
    msgspec would write something else - a non-finite number (``null``; json.dumps writes ``NaN``, which
    reads back) or a string UTF-8 cannot hold (a lone surrogate, which it refuses) - ``json.dumps``
    writes it as before: a refusal here would roll back the whole group of batches."""
    try:
        text = _JSON_ENCODE(readings).decode()
    except (UnicodeEncodeError, TypeError, ValueError, OverflowError):
        return json.dumps(readings)
    return json.dumps(readings) if "null" in text else text


_JSON_ENCODE = msgspec.json.Encoder().encode


def _readings(sc: RfScan) -> dict:
    """A scan's ``readings`` column: {"rssi": ..., "freq": ... when known, "age": ... when known}."""
    d: dict = {"rssi": dict(sc.rssi_dbm)}
    if sc.frequency_hz:
        d["freq"] = dict(sc.frequency_hz)
    if sc.age_s:
        d["age"] = dict(sc.age_s)
    return d


#: Largest IN list in one statement (SQLite allows 32,766 bound parameters since 3.32, PostgreSQL 65,535).
_IN_CHUNK = 900


def _chunked_in(s: Session, stmt, column, values: list, scalars: bool = True) -> list:
    """The rows of ``stmt`` with ``column IN values``, in chunks of :data:`_IN_CHUNK` values; ORM objects
    (``scalars``) or tuples. Rows of different chunks are concatenated (each chunk in ``stmt``'s order)."""
    out: list = []
    for i in range(0, len(values), _IN_CHUNK):
        res = s.execute(stmt.where(column.in_(values[i : i + _IN_CHUNK])))
        out += res.scalars().all() if scalars else res.all()
    return out


def _name_floors(s: Session, named: list[tuple[int, str, float]]) -> None:
    """Each (walk id, floor, t): the walk names ``floor`` at time ``t``; a floor's first time is kept (a
    walk's floors are ordered by it). One query reads the rows the walks have; new ones are added, older
    first times lowered (a group of fixes named a floor each: a lookup per fix cost a round trip each,
    13 % of the server's time under bench_load's 1,000 clients on PostgreSQL)."""
    first: dict[tuple[int, str], float] = {}
    for wid, floor, t in named:
        key = (int(wid), floor)
        if key not in first or t < first[key]:
            first[key] = t
    if not first:
        return
    have = {(r.walk_id, r.floor): r for r in _chunked_in(s, select(m.WalkFloor), m.WalkFloor.walk_id, sorted({w for w, _ in first}))}
    for (wid, floor), t in first.items():
        row = have.get((wid, floor))
        if row is None:
            s.add(m.WalkFloor(walk_id=wid, floor=floor, t_first=t))
        elif t < row.t_first:
            row.t_first = t


def _rejections(s: Session) -> dict:
    out: Counter = Counter()
    for r in s.execute(select(m.Rejection)).scalars():
        out[r.reason] += r.count
    return dict(out)

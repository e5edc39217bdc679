"""Server storage: SQLAlchemy 2 typed models (SQLite in WAL mode by default, PostgreSQL by URL).

Times are stored as float seconds on the devices' clocks (``t``) exactly as sent, plus a tz-aware
``received_at`` where the server stamps arrival. Every ingested batch is one row keyed by
(device, seq), unique: ingest is idempotent.

A device's batches are grouped into walks (:class:`Walk`): a run of batches between a start and an
end (an end-of-walk marker or an idle gap, see :mod:`hybridloc.server.store`). Each batch names its
walk; steps, scans and marks reach it through their batch (``walk_id`` is not repeated on them: the
walk's device and time span select scans and marks through ``ix_*_device_t``, its batches select its
steps through ``ix_step_batch_id``, see ``Store.read_walk``).
"""

from __future__ import annotations

import datetime as dt
import logging
import os
import sqlite3
import threading

from sqlalchemy import JSON, Boolean, DateTime, Float, ForeignKey, Index, Integer, LargeBinary, MetaData, String, UniqueConstraint, event, text
from sqlalchemy import create_engine as _create_engine
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

NAMING = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING)


def utcnow() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


class Site(Base):
    __tablename__ = "site"
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    name: Mapped[str] = mapped_column(String(200), default="")
    origin_lat_deg: Mapped[float | None] = mapped_column(Float)
    origin_lon_deg: Mapped[float | None] = mapped_column(Float)


class Floor(Base):
    __tablename__ = "floor"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id"))
    name: Mapped[str] = mapped_column(String(32))
    level: Mapped[int] = mapped_column(Integer, default=0)
    __table_args__ = (UniqueConstraint("site_id", "name"),)


class FloorPlanVersion(Base):
    __tablename__ = "floor_plan"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id"))
    geojson: Mapped[str] = mapped_column(String)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Device(Base):
    __tablename__ = "device"
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id"))
    model: Mapped[str] = mapped_column(String(64), default="")
    last_seq: Mapped[int] = mapped_column(Integer, default=0)
    last_seen: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))


class Batch(Base):
    __tablename__ = "batch"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    device_id: Mapped[str] = mapped_column(ForeignKey("device.id"))
    seq: Mapped[int] = mapped_column(Integer)
    received_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    n_steps: Mapped[int] = mapped_column(Integer, default=0)
    n_scans: Mapped[int] = mapped_column(Integer, default=0)
    n_marks: Mapped[int] = mapped_column(Integer, default=0)
    #: The walk the batch belongs to; None for a batch without records that found no open walk.
    walk_id: Mapped[int | None] = mapped_column(ForeignKey("walk.id"), index=True)
    __table_args__ = (UniqueConstraint("device_id", "seq"),)


class Walk(Base):
    """One device's run of batches between a start and an end (:class:`hybridloc.types.Walk` without the data).

    ``t_start``/``t_end`` are the first and last record times (device clock, s); ``end_reason`` is a
    :class:`hybridloc.types.WalkEnd` value; the counts add up the walk's batches.
    """

    __tablename__ = "walk"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id"))
    device_id: Mapped[str] = mapped_column(ForeignKey("device.id"))
    t_start: Mapped[float] = mapped_column(Float)
    t_end: Mapped[float] = mapped_column(Float)
    device_model: Mapped[str] = mapped_column(String(64), default="")
    end_reason: Mapped[str] = mapped_column(String(8), default="open")
    n_batches: Mapped[int] = mapped_column(Integer, default=0)
    n_steps: Mapped[int] = mapped_column(Integer, default=0)
    n_scans: Mapped[int] = mapped_column(Integer, default=0)
    n_marks: Mapped[int] = mapped_column(Integer, default=0)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    # "walks of a site since t" and "the device's latest walk": both range over t_end
    __table_args__ = (Index("ix_walk_site_t_end", "site_id", "t_end"), Index("ix_walk_device_t_end", "device_id", "t_end"))


class WalkFloor(Base):
    """A floor a walk's marks or fixes named, with the time it was first named (orders a walk's floors)."""

    __tablename__ = "walk_floor"
    walk_id: Mapped[int] = mapped_column(ForeignKey("walk.id"), primary_key=True)
    floor: Mapped[str] = mapped_column(String(32), primary_key=True)
    t_first: Mapped[float] = mapped_column(Float)
    # "walks of a floor": the primary key (walk_id, floor) cannot serve a lookup by floor
    __table_args__ = (Index("ix_walk_floor_floor", "floor", "walk_id"),)


class Step(Base):
    __tablename__ = "step"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    #: indexed: a walk's steps are read through its batches (``ix_step_batch_id``, a key that grows with
    #: every batch; a (device_id, t) index cost about as much as the rows at ingest, migration 0004)
    batch_id: Mapped[int] = mapped_column(ForeignKey("batch.id"), index=True)
    device_id: Mapped[str] = mapped_column(String(64))
    t: Mapped[float] = mapped_column(Float)
    length: Mapped[float] = mapped_column(Float)
    heading: Mapped[float] = mapped_column(Float)
    sigma_length: Mapped[float] = mapped_column(Float)
    sigma_heading: Mapped[float] = mapped_column(Float)
    heading_change: Mapped[float | None] = mapped_column(Float)
    sigma_heading_change: Mapped[float | None] = mapped_column(Float)
    height_change: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    sigma_height_change: Mapped[float] = mapped_column(Float, default=0.0, server_default=text("0"))
    floor_change: Mapped[int] = mapped_column(Integer, default=0)
    degraded: Mapped[str] = mapped_column(String(32), default="", server_default=text("''"))


class Scan(Base):
    __tablename__ = "scan"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    batch_id: Mapped[int] = mapped_column(ForeignKey("batch.id"))
    device_id: Mapped[str] = mapped_column(String(64))
    t: Mapped[float] = mapped_column(Float)
    technology: Mapped[str] = mapped_column(String(8))
    #: {"rssi": {transmitter: dBm}, "freq": {transmitter: Hz}, "age": {transmitter: s}}; "freq" and "age"
    #: only where the scan carried them (RfScan's rssi_dbm, frequency_hz, age_s)
    readings: Mapped[dict] = mapped_column(JSON)
    __table_args__ = (Index("ix_scan_device_t", "device_id", "t"),)


class SurveyMark(Base):
    __tablename__ = "survey_mark"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    batch_id: Mapped[int] = mapped_column(ForeignKey("batch.id"))
    device_id: Mapped[str] = mapped_column(String(64))
    t: Mapped[float] = mapped_column(Float)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    floor: Mapped[str] = mapped_column(String(32))
    __table_args__ = (Index("ix_survey_mark_device_t", "device_id", "t"),)


class Fix(Base):
    __tablename__ = "fix"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    device_id: Mapped[str] = mapped_column(String(64))
    t: Mapped[float] = mapped_column(Float)
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    floor: Mapped[str | None] = mapped_column(String(32))
    cov: Mapped[list] = mapped_column(JSON)
    source: Mapped[str] = mapped_column(String(8))


class RadioMapVersion(Base):
    __tablename__ = "radio_map"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id"))
    version: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    n_scans: Mapped[int] = mapped_column(Integer, default=0)
    data: Mapped[bytes] = mapped_column(LargeBinary)
    #: where the map came from: "import" (a file), "survey" (map rebuild from marks), "slam" (a crowd-SLAM run)
    source: Mapped[str] = mapped_column(String(16), default="import", server_default=text("'import'"))
    #: the SLAM run that built it (source "slam")
    run_id: Mapped[int | None] = mapped_column(ForeignKey("slam_run.id"))
    #: provenance: {"walks": [walk ids], "survey_walks": [walk ids with marks], "marks": n, "floors": [...], "coverage": c}
    provenance: Mapped[dict | None] = mapped_column(JSON)
    __table_args__ = (UniqueConstraint("site_id", "version"),)


class SlamRun(Base):
    """One crowd-SLAM solve of a site: a batch re-solve of some floors (``kind`` "batch", checkpointed per
    floor in :class:`SlamFloorDone`, resumable) or one walk added incrementally (``kind`` "walk").

    ``status``: "running" (its rows are written but nobody reads them), "complete" (its tracks are the
    walks' current ones), "failed". A batch run becomes complete in one transaction, so readers see the
    previous version until the new one is whole."""

    __tablename__ = "slam_run"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id"))
    kind: Mapped[str] = mapped_column(String(8))
    status: Mapped[str] = mapped_column(String(16), default="running")
    #: floors the run solves (None: every floor of the site's walks)
    floors: Mapped[list | None] = mapped_column(JSON)
    started_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    finished_at: Mapped[dt.datetime | None] = mapped_column(DateTime(timezone=True))
    #: the radio map version the run produced (batch runs that built one)
    map_version: Mapped[int | None] = mapped_column(Integer)
    stats: Mapped[dict | None] = mapped_column(JSON)
    error: Mapped[str] = mapped_column(String, default="", server_default=text("''"))
    __table_args__ = (Index("ix_slam_run_site_id_status", "site_id", "status"),)


class SlamFloorDone(Base):
    """A floor of a batch run whose results are written (its checkpoint: a resumed run skips it)."""

    __tablename__ = "slam_floor_done"
    run_id: Mapped[int] = mapped_column(ForeignKey("slam_run.id"), primary_key=True)
    floor: Mapped[str] = mapped_column(String(32), primary_key=True)
    finished_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    stats: Mapped[dict | None] = mapped_column(JSON)


class WalkSlam(Base):
    """A walk's SLAM state: its current corrected track (the points of run ``run_id``), or why it has none.

    ``status``: "corrected" (absolute track), "relative" (a shape in its own frame only), "quarantined"
    (the solver diverged or the track left the walkable area: kept out of the map, counted), "failed"
    (an error while solving it; retried by the next batch run). ``anchored`` is the track's
    :data:`hybridloc.types.TRACK_ANCHORS` value; ``scale``/``heading_bias`` (rad) the walk's PDR
    nuisances (slam.md 3.1)."""

    __tablename__ = "walk_slam"
    walk_id: Mapped[int] = mapped_column(ForeignKey("walk.id"), primary_key=True)
    site_id: Mapped[str] = mapped_column(ForeignKey("site.id"))
    status: Mapped[str] = mapped_column(String(16))
    anchored: Mapped[str] = mapped_column(String(16), default="relative")
    reason: Mapped[str] = mapped_column(String, default="", server_default=text("''"))
    run_id: Mapped[int | None] = mapped_column(ForeignKey("slam_run.id"))
    scale: Mapped[float | None] = mapped_column(Float)
    heading_bias: Mapped[float | None] = mapped_column(Float)
    n_points: Mapped[int] = mapped_column(Integer, default=0)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    updated_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    __table_args__ = (Index("ix_walk_slam_site_id_status", "site_id", "status"),)


class TrackPoint(Base):
    """A corrected position of a walk at one of its steps or scans (``kind``), written by SLAM run ``run_id``."""

    __tablename__ = "track_point"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("slam_run.id"))
    walk_id: Mapped[int] = mapped_column(ForeignKey("walk.id"))
    t: Mapped[float] = mapped_column(Float)
    kind: Mapped[str] = mapped_column(String(8))
    floor: Mapped[str] = mapped_column(String(32))
    x: Mapped[float] = mapped_column(Float)
    y: Mapped[float] = mapped_column(Float)
    #: the 2x2 covariance, m^2 (NULL where the solve gave none)
    cov_xx: Mapped[float | None] = mapped_column(Float)
    cov_xy: Mapped[float | None] = mapped_column(Float)
    cov_yy: Mapped[float | None] = mapped_column(Float)
    # "the walk's points of run r, by time"
    __table_args__ = (Index("ix_track_point_walk_id_run_id_t", "walk_id", "run_id", "t"), Index("ix_track_point_run_id", "run_id"))


class LoopClosure(Base):
    """One loop candidate of a SLAM run, accepted or rejected, with its robust weight (the loop audit).

    ``kind``: "wifi" (fingerprint similarity) or "ble" (both walks passed the same beacon); ``reason``
    says why a rejected one was (not mutual, below the similarity floor, PCM, robust-weight ...)."""

    __tablename__ = "loop_closure"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("slam_run.id"))
    site_id: Mapped[str] = mapped_column(String(64))
    floor: Mapped[str] = mapped_column(String(32))
    walk_a: Mapped[int] = mapped_column(ForeignKey("walk.id"))
    t_a: Mapped[float] = mapped_column(Float)
    walk_b: Mapped[int] = mapped_column(ForeignKey("walk.id"))
    t_b: Mapped[float] = mapped_column(Float)
    similarity: Mapped[float] = mapped_column(Float)
    weight: Mapped[float] = mapped_column(Float)
    p_inlier: Mapped[float | None] = mapped_column(Float)
    accepted: Mapped[bool] = mapped_column(Boolean)
    reason: Mapped[str] = mapped_column(String(32), default="", server_default=text("''"))
    kind: Mapped[str] = mapped_column(String(8), default="wifi")
    __table_args__ = (Index("ix_loop_closure_run_id", "run_id"), Index("ix_loop_closure_site_id_floor", "site_id", "floor"))


class Rejection(Base):
    __tablename__ = "rejection"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    device_id: Mapped[str] = mapped_column(String(64))
    reason: Mapped[str] = mapped_column(String(32))
    count: Mapped[int] = mapped_column(Integer, default=0)
    __table_args__ = (UniqueConstraint("device_id", "reason"),)


def lock_site(s, site: str) -> None:
    """Inside a transaction of session ``s``: the site's row, added when missing, then written, so that
    writers deciding something per site (the next radio map version, the batch run to work on) are
    serialised - SQLite's write lock, PostgreSQL's row lock - and each reads after the other's commit.
    Two writers adding a missing site at once collide on its key: :func:`retry_unique`."""
    from sqlalchemy import update

    if s.get(Site, site) is None:
        s.add(Site(id=site, name=site))
        s.flush()
    s.execute(update(Site).where(Site.id == site).values(name=Site.name))


def retry_unique(fn, attempts: int = 8):
    """``fn()`` (one whole transaction) again when it fails on a unique constraint: two writers that both
    added a missing site's row (:func:`lock_site`) collide on its key; the loser's transaction was rolled
    back, so running it again finds the row. Other errors, and the last attempt's, propagate."""
    from sqlalchemy.exc import IntegrityError

    for k in range(attempts):
        try:
            return fn()
        except IntegrityError:
            if k == attempts - 1:
                raise


def make_engine(url: str, wal_autocheckpoint: int | None = None) -> Engine:
    """An engine for a SQLite file path / URL (WAL, foreign keys, busy timeout) or any SQLAlchemy URL.
    ``wal_autocheckpoint``: SQLite's pages of WAL after which a commit checkpoints (None: SQLite's 1,000);
    larger where a :class:`WalCheckpointer` checkpoints beside the writers."""
    if "://" not in url:
        url = f"sqlite:///{url}"
    if url.startswith("sqlite"):
        eng = _create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})
        pragmas = ["journal_mode=WAL", "synchronous=NORMAL", "foreign_keys=ON", "busy_timeout=30000"]
        if wal_autocheckpoint is not None:
            pragmas.append(f"wal_autocheckpoint={int(wal_autocheckpoint)}")

        @event.listens_for(eng, "connect")
        def _pragmas(dbapi_conn, _rec):  # noqa: ANN001
            cur = dbapi_conn.cursor()
            for p in pragmas:
                cur.execute(f"PRAGMA {p}")
            cur.close()

        return eng
    return _create_engine(url, pool_pre_ping=True)


def sqlite_path(url: str) -> str | None:
    """The file of a SQLite path or ``sqlite:///`` URL; None for another database (or SQLite in memory)."""
    if "://" not in url:
        return url if url != ":memory:" else None
    if url.startswith("sqlite") and "///" in url:
        path = url.split("///", 1)[1].split("?", 1)[0]
        return path if path and path != ":memory:" else None
    return None


#: Pages of WAL after which an ingest commit checkpoints itself: the safety net behind the
#: :class:`WalCheckpointer` (about 40 MB of 4 KiB pages; SQLite's default is 1,000)
INGEST_WAL_AUTOCHECKPOINT = 10_000


class WalCheckpointer:
    """Checkpoints a SQLite database's WAL beside its writers, in a thread of its own with its own
    connection: ``PRAGMA wal_checkpoint(PASSIVE)`` every ``every_s`` seconds while the WAL holds at least
    ``min_bytes``. SQLite otherwise checkpoints in the commit that crosses 1,000 pages: inside the
    writer's transaction time, which under SQLite's one-writer lock is everyone's (a quarter of two
    ingest workers' throughput, benchmarks/bench_load.py --ceiling-only). A passive checkpoint takes
    no writer's lock and waits for none (it copies what no reader still needs); the sqlite3 module
    releases the interpreter lock while it runs, so the server's threads go on. The writers keep a
    larger autocheckpoint (:data:`INGEST_WAL_AUTOCHECKPOINT`) as the safety net should this thread
    fall behind or stop."""

    def __init__(self, path: str, every_s: float = 0.25, min_bytes: int = 4 << 20):
        self.path, self.every_s, self.min_bytes = path, every_s, min_bytes
        self.checkpoints = 0
        self.errors = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="hybridloc-wal-checkpoint", daemon=True)

    def start(self) -> WalCheckpointer:
        self._thread.start()
        return self

    def _run(self) -> None:
        log = logging.getLogger("hybridloc.server")
        con = sqlite3.connect(self.path, timeout=30, check_same_thread=False)
        try:
            while not self._stop.wait(self.every_s):
                try:
                    if os.path.getsize(self.path + "-wal") < self.min_bytes:
                        continue
                except OSError:
                    continue  # no WAL file (yet, or the database is being replaced)
                try:
                    con.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchall()
                    self.checkpoints += 1
                except sqlite3.Error as exc:  # busy or away: the writers' own autocheckpoint still holds
                    self.errors += 1
                    if self.errors in (1, 10, 100):
                        log.warning("WAL checkpoint failed (%d so far): %s", self.errors, exc)
        finally:
            con.close()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

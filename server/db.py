"""Server storage: SQLAlchemy 2 typed models (SQLite in WAL mode by default, PostgreSQL by URL).

Times are stored as float seconds on the devices' clocks (``t``) exactly as sent, plus a tz-aware
``received_at`` where the server stamps arrival. Every ingested batch is one row keyed by
(device, seq), unique: ingest is idempotent.

A device's batches are grouped into walks (:class:`Walk`): a run of batches between a start and an
end (an end-of-walk marker or an idle gap, see :mod:`hybridloc.server.store`). Each batch names its
walk; steps, scans and marks reach it through their batch (``walk_id`` is not repeated on them: the
walk's device and time span select them through ``ix_*_device_t``, see ``Store.read_walk``).
"""

from __future__ import annotations

import datetime as dt

from sqlalchemy import JSON, DateTime, Float, ForeignKey, Index, Integer, LargeBinary, MetaData, String, UniqueConstraint, event, text
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
    batch_id: Mapped[int] = mapped_column(ForeignKey("batch.id"))
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
    __table_args__ = (Index("ix_step_device_t", "device_id", "t"),)


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
    __table_args__ = (UniqueConstraint("site_id", "version"),)


class Rejection(Base):
    __tablename__ = "rejection"
    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    device_id: Mapped[str] = mapped_column(String(64))
    reason: Mapped[str] = mapped_column(String(32))
    count: Mapped[int] = mapped_column(Integer, default=0)
    __table_args__ = (UniqueConstraint("device_id", "reason"),)


def make_engine(url: str) -> Engine:
    """An engine for a SQLite file path / URL (WAL, foreign keys, busy timeout) or any SQLAlchemy URL."""
    if "://" not in url:
        url = f"sqlite:///{url}"
    if url.startswith("sqlite"):
        eng = _create_engine(url, connect_args={"timeout": 30, "check_same_thread": False})

        @event.listens_for(eng, "connect")
        def _pragmas(dbapi_conn, _rec):  # noqa: ANN001
            cur = dbapi_conn.cursor()
            for p in ("journal_mode=WAL", "synchronous=NORMAL", "foreign_keys=ON", "busy_timeout=30000"):
                cur.execute(f"PRAGMA {p}")
            cur.close()

        return eng
    return _create_engine(url, pool_pre_ping=True)

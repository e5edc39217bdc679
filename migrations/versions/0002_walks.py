"""walks, and the step fields 0001 dropped

Revision ID: 0002_walks
Revises: 0001_initial

* ``step`` gains ``sigma_heading_change``, ``height_change``, ``sigma_height_change`` and ``degraded``
  (the :class:`hybridloc.types.StepEvent` fields 0001 did not keep; a step's odometry noise needs
  them). Rows stored before have their defaults: unknown ``sigma_heading_change`` (NULL), no height
  change, not degraded.
* ``walk`` (a device's run of batches between a start and an end) and ``walk_floor`` (the floors a
  walk's marks or fixes named), ``batch.walk_id``, and an index on ``survey_mark (device_id, t)`` (a
  walk's marks are read by device and time span, like its steps and scans).
* Data: each device's stored batches, in sequence order, are split into walks by the idle-gap rule of
  :mod:`hybridloc.server.store` (a batch whose records lie more than ``IDLE_GAP_S`` from the open
  walk's span opens a new walk; the earlier one ended ``idle``); the device's last walk stays
  ``open``.

Downgrade drops the walks and the new columns; every row 0001 knew stays (the new step fields are
lost, as 0001 has nowhere to keep them). Portable SQL only; ``batch_alter_table`` for SQLite's ALTER.
"""

from __future__ import annotations

import datetime as dt

import sqlalchemy as sa
from alembic import op

revision = "0002_walks"
down_revision = "0001_initial"
branch_labels = None
depends_on = None

#: ``hybridloc.server.store.WALK_IDLE_GAP_S`` when this revision was written, frozen here so that
#: running the history again always splits the same walks whatever the store's value becomes.
IDLE_GAP_S = 180.0


def upgrade() -> None:
    with op.batch_alter_table("step", schema=None) as b:
        b.add_column(sa.Column("sigma_heading_change", sa.Float(), nullable=True))
        b.add_column(sa.Column("height_change", sa.Float(), server_default=sa.text("0"), nullable=False))
        b.add_column(sa.Column("sigma_height_change", sa.Float(), server_default=sa.text("0"), nullable=False))
        b.add_column(sa.Column("degraded", sa.String(length=32), server_default=sa.text("''"), nullable=False))

    op.create_table(
        "walk",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("device_id", sa.String(length=64), nullable=False),
        sa.Column("t_start", sa.Float(), nullable=False),
        sa.Column("t_end", sa.Float(), nullable=False),
        sa.Column("device_model", sa.String(length=64), nullable=False),
        sa.Column("end_reason", sa.String(length=8), nullable=False),
        sa.Column("n_batches", sa.Integer(), nullable=False),
        sa.Column("n_steps", sa.Integer(), nullable=False),
        sa.Column("n_scans", sa.Integer(), nullable=False),
        sa.Column("n_marks", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["device_id"], ["device.id"], name=op.f("fk_walk_device_id_device")),
        sa.ForeignKeyConstraint(["site_id"], ["site.id"], name=op.f("fk_walk_site_id_site")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_walk")),
    )
    with op.batch_alter_table("walk", schema=None) as b:
        b.create_index("ix_walk_device_t_end", ["device_id", "t_end"], unique=False)
        b.create_index("ix_walk_site_t_end", ["site_id", "t_end"], unique=False)

    op.create_table(
        "walk_floor",
        sa.Column("walk_id", sa.Integer(), nullable=False),
        sa.Column("floor", sa.String(length=32), nullable=False),
        sa.Column("t_first", sa.Float(), nullable=False),
        sa.ForeignKeyConstraint(["walk_id"], ["walk.id"], name=op.f("fk_walk_floor_walk_id_walk")),
        sa.PrimaryKeyConstraint("walk_id", "floor", name=op.f("pk_walk_floor")),
    )
    with op.batch_alter_table("walk_floor", schema=None) as b:
        b.create_index("ix_walk_floor_floor", ["floor", "walk_id"], unique=False)

    with op.batch_alter_table("batch", schema=None) as b:
        b.add_column(sa.Column("walk_id", sa.Integer(), nullable=True))
        b.create_index(b.f("ix_batch_walk_id"), ["walk_id"], unique=False)
        b.create_foreign_key(b.f("fk_batch_walk_id_walk"), "walk", ["walk_id"], ["id"])

    with op.batch_alter_table("survey_mark", schema=None) as b:
        b.create_index("ix_survey_mark_device_t", ["device_id", "t"], unique=False)

    _split_into_walks(op.get_bind())


def downgrade() -> None:
    with op.batch_alter_table("survey_mark", schema=None) as b:
        b.drop_index("ix_survey_mark_device_t")
    with op.batch_alter_table("batch", schema=None) as b:
        b.drop_constraint(b.f("fk_batch_walk_id_walk"), type_="foreignkey")
        b.drop_index(b.f("ix_batch_walk_id"))
        b.drop_column("walk_id")
    with op.batch_alter_table("walk_floor", schema=None) as b:
        b.drop_index("ix_walk_floor_floor")
    op.drop_table("walk_floor")
    with op.batch_alter_table("walk", schema=None) as b:
        b.drop_index("ix_walk_site_t_end")
        b.drop_index("ix_walk_device_t_end")
    op.drop_table("walk")
    with op.batch_alter_table("step", schema=None) as b:
        b.drop_column("degraded")
        b.drop_column("sigma_height_change")
        b.drop_column("height_change")
        b.drop_column("sigma_heading_change")


# ------------------------------------------------------------------------------------------------ data
def _split_into_walks(conn: sa.Connection) -> None:
    """Walks from the stored batches: the rule of ``Store.persist``, applied to each device's batches in
    sequence order (lightweight table stubs: a migration never imports the models, which move on)."""
    md = sa.MetaData()
    device = sa.Table("device", md, sa.Column("id"), sa.Column("site_id"), sa.Column("model"))
    batch = sa.Table(
        "batch",
        md,
        sa.Column("id"),
        sa.Column("device_id"),
        sa.Column("seq"),
        sa.Column("n_steps"),
        sa.Column("n_scans"),
        sa.Column("n_marks"),
        sa.Column("walk_id"),
    )
    step = sa.Table("step", md, sa.Column("batch_id"), sa.Column("t"))
    scan = sa.Table("scan", md, sa.Column("batch_id"), sa.Column("t"))
    mark = sa.Table("survey_mark", md, sa.Column("batch_id"), sa.Column("t"), sa.Column("floor"))
    fix = sa.Table("fix", md, sa.Column("device_id"), sa.Column("t"), sa.Column("floor"))
    walk = sa.Table(
        "walk",
        md,
        sa.Column("id", sa.Integer(), primary_key=True),
        sa.Column("created_at", sa.DateTime(timezone=True)),
        sa.Column("updated_at", sa.DateTime(timezone=True)),
        *(
            sa.Column(c)
            for c in ("site_id", "device_id", "t_start", "t_end", "device_model", "end_reason", "n_batches", "n_steps", "n_scans", "n_marks")
        ),
    )
    walk_floor = sa.Table("walk_floor", md, sa.Column("walk_id"), sa.Column("floor"), sa.Column("t_first"))

    # each batch's record time span, over its steps, scans and marks
    span: dict[int, tuple[float, float]] = {}
    for table in (step, scan, mark):
        for bid, lo, hi in conn.execute(sa.select(table.c.batch_id, sa.func.min(table.c.t), sa.func.max(table.c.t)).group_by(table.c.batch_id)):
            old = span.get(bid)
            span[bid] = (lo, hi) if old is None else (min(old[0], lo), max(old[1], hi))
    mark_floors: dict[int, list[tuple[float, str]]] = {}
    for bid, t, floor in conn.execute(sa.select(mark.c.batch_id, mark.c.t, mark.c.floor).where(mark.c.floor != "")):
        mark_floors.setdefault(bid, []).append((t, floor))
    fix_floors: dict[str, list[tuple[float, str]]] = {}
    for dev, t, floor in conn.execute(sa.select(fix.c.device_id, fix.c.t, fix.c.floor).where(fix.c.floor.is_not(None), fix.c.floor != "")):
        fix_floors.setdefault(dev, []).append((t, floor))

    now = dt.datetime.now(dt.UTC)
    for dev_id, site_id, model in conn.execute(sa.select(device.c.id, device.c.site_id, device.c.model).order_by(device.c.id)).all():
        walks: list[dict] = []  # in the order opened; the last one is the device's open walk
        members: list[list[int]] = []
        for bid, n_steps, n_scans, n_marks in conn.execute(
            sa.select(batch.c.id, batch.c.n_steps, batch.c.n_scans, batch.c.n_marks).where(batch.c.device_id == dev_id).order_by(batch.c.seq)
        ).all():
            sp = span.get(bid)
            if sp is None:  # no records: joins the open walk, if any
                if walks:
                    walks[-1]["n_batches"] += 1
                    members[-1].append(bid)
                continue
            w = walks[-1] if walks else None
            if w is None or max(sp[0] - w["t_end"], w["t_start"] - sp[1]) > IDLE_GAP_S:
                if w is not None:
                    w["end_reason"] = "idle"
                w = {
                    "site_id": site_id,
                    "device_id": dev_id,
                    "t_start": sp[0],
                    "t_end": sp[1],
                    "device_model": model or "",
                    "end_reason": "open",
                    "n_batches": 0,
                    "n_steps": 0,
                    "n_scans": 0,
                    "n_marks": 0,
                    "created_at": now,
                    "updated_at": now,
                    "floors": {},
                }
                walks.append(w)
                members.append([])
            w["t_start"], w["t_end"] = min(w["t_start"], sp[0]), max(w["t_end"], sp[1])
            w["n_batches"] += 1
            w["n_steps"] += n_steps
            w["n_scans"] += n_scans
            w["n_marks"] += n_marks
            for t, floor in mark_floors.get(bid, ()):
                w["floors"][floor] = min(t, w["floors"].get(floor, t))
            members[-1].append(bid)
        for t, floor in fix_floors.get(dev_id, ()):  # a fix names the floor of the device's latest walk spanning its time
            for w in reversed(walks):
                if w["t_start"] <= t <= w["t_end"]:
                    w["floors"][floor] = min(t, w["floors"].get(floor, t))
                    break
        for w, bids in zip(walks, members):
            floors = w.pop("floors")
            wid = conn.execute(sa.insert(walk).values(**w)).inserted_primary_key[0]
            if floors:
                conn.execute(sa.insert(walk_floor), [{"walk_id": wid, "floor": f, "t_first": t} for f, t in floors.items()])
            for k in range(0, len(bids), 500):  # well under any database's limit of bound parameters
                conn.execute(sa.update(batch).where(batch.c.id.in_(bids[k : k + 500])).values(walk_id=wid))

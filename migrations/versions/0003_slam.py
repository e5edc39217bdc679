"""crowd SLAM: runs, per-floor checkpoints, walk states, corrected tracks, the loop audit, map provenance

Revision ID: 0003_slam
Revises: 0002_walks

* ``slam_run``: one solve of a site (a batch re-solve of floors, or one walk added); ``slam_floor_done``:
  the floors of a batch run already written (a run killed midway resumes after them).
* ``walk_slam``: each walk's SLAM state (corrected / relative / quarantined / failed), its anchoring, its
  scale and heading bias, and the run whose points are its current track.
* ``track_point``: corrected position and 2x2 covariance at every step and scan of a walk, per run.
* ``loop_closure``: every loop candidate of a run, accepted or rejected, with its weight.
* ``radio_map`` gains ``source`` (import / survey / slam; rows stored before are "import"), ``run_id``
  and ``provenance`` (which walks and survey marks built it).

Downgrade drops them; every row 0002 knew stays. ``batch_alter_table`` for SQLite's ALTER.
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003_slam"
down_revision = "0002_walks"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "slam_run",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("kind", sa.String(length=8), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("floors", sa.JSON(), nullable=True),
        sa.Column("started_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=True),
        sa.Column("map_version", sa.Integer(), nullable=True),
        sa.Column("stats", sa.JSON(), nullable=True),
        sa.Column("error", sa.String(), server_default=sa.text("''"), nullable=False),
        sa.ForeignKeyConstraint(["site_id"], ["site.id"], name=op.f("fk_slam_run_site_id_site")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_slam_run")),
    )
    op.create_index("ix_slam_run_site_id_status", "slam_run", ["site_id", "status"], unique=False)
    op.create_table(
        "slam_floor_done",
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("floor", sa.String(length=32), nullable=False),
        sa.Column("finished_at", sa.DateTime(timezone=True), nullable=False),
        sa.Column("stats", sa.JSON(), nullable=True),
        sa.ForeignKeyConstraint(["run_id"], ["slam_run.id"], name=op.f("fk_slam_floor_done_run_id_slam_run")),
        sa.PrimaryKeyConstraint("run_id", "floor", name=op.f("pk_slam_floor_done")),
    )
    op.create_table(
        "walk_slam",
        sa.Column("walk_id", sa.Integer(), nullable=False),
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("status", sa.String(length=16), nullable=False),
        sa.Column("anchored", sa.String(length=16), nullable=False),
        sa.Column("reason", sa.String(), server_default=sa.text("''"), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=True),
        sa.Column("scale", sa.Float(), nullable=True),
        sa.Column("heading_bias", sa.Float(), nullable=True),
        sa.Column("n_points", sa.Integer(), nullable=False),
        sa.Column("attempts", sa.Integer(), nullable=False),
        sa.Column("updated_at", sa.DateTime(timezone=True), nullable=False),
        sa.ForeignKeyConstraint(["walk_id"], ["walk.id"], name=op.f("fk_walk_slam_walk_id_walk")),
        sa.ForeignKeyConstraint(["site_id"], ["site.id"], name=op.f("fk_walk_slam_site_id_site")),
        sa.ForeignKeyConstraint(["run_id"], ["slam_run.id"], name=op.f("fk_walk_slam_run_id_slam_run")),
        sa.PrimaryKeyConstraint("walk_id", name=op.f("pk_walk_slam")),
    )
    op.create_index("ix_walk_slam_site_id_status", "walk_slam", ["site_id", "status"], unique=False)
    op.create_table(
        "track_point",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("walk_id", sa.Integer(), nullable=False),
        sa.Column("t", sa.Float(), nullable=False),
        sa.Column("kind", sa.String(length=8), nullable=False),
        sa.Column("floor", sa.String(length=32), nullable=False),
        sa.Column("x", sa.Float(), nullable=False),
        sa.Column("y", sa.Float(), nullable=False),
        sa.Column("cov_xx", sa.Float(), nullable=True),
        sa.Column("cov_xy", sa.Float(), nullable=True),
        sa.Column("cov_yy", sa.Float(), nullable=True),
        sa.ForeignKeyConstraint(["run_id"], ["slam_run.id"], name=op.f("fk_track_point_run_id_slam_run")),
        sa.ForeignKeyConstraint(["walk_id"], ["walk.id"], name=op.f("fk_track_point_walk_id_walk")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_track_point")),
    )
    op.create_index("ix_track_point_walk_id_run_id_t", "track_point", ["walk_id", "run_id", "t"], unique=False)
    op.create_index("ix_track_point_run_id", "track_point", ["run_id"], unique=False)
    op.create_table(
        "loop_closure",
        sa.Column("id", sa.Integer(), nullable=False),
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("site_id", sa.String(length=64), nullable=False),
        sa.Column("floor", sa.String(length=32), nullable=False),
        sa.Column("walk_a", sa.Integer(), nullable=False),
        sa.Column("t_a", sa.Float(), nullable=False),
        sa.Column("walk_b", sa.Integer(), nullable=False),
        sa.Column("t_b", sa.Float(), nullable=False),
        sa.Column("similarity", sa.Float(), nullable=False),
        sa.Column("weight", sa.Float(), nullable=False),
        sa.Column("p_inlier", sa.Float(), nullable=True),
        sa.Column("accepted", sa.Boolean(), nullable=False),
        sa.Column("reason", sa.String(length=32), server_default=sa.text("''"), nullable=False),
        sa.Column("kind", sa.String(length=8), nullable=False),
        sa.ForeignKeyConstraint(["run_id"], ["slam_run.id"], name=op.f("fk_loop_closure_run_id_slam_run")),
        sa.ForeignKeyConstraint(["walk_a"], ["walk.id"], name=op.f("fk_loop_closure_walk_a_walk")),
        sa.ForeignKeyConstraint(["walk_b"], ["walk.id"], name=op.f("fk_loop_closure_walk_b_walk")),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_loop_closure")),
    )
    op.create_index("ix_loop_closure_run_id", "loop_closure", ["run_id"], unique=False)
    op.create_index("ix_loop_closure_site_id_floor", "loop_closure", ["site_id", "floor"], unique=False)
    with op.batch_alter_table("radio_map", schema=None) as b:
        b.add_column(sa.Column("source", sa.String(length=16), server_default=sa.text("'import'"), nullable=False))
        b.add_column(sa.Column("run_id", sa.Integer(), nullable=True))
        b.add_column(sa.Column("provenance", sa.JSON(), nullable=True))
        b.create_foreign_key(op.f("fk_radio_map_run_id_slam_run"), "slam_run", ["run_id"], ["id"])


def downgrade() -> None:
    with op.batch_alter_table("radio_map", schema=None) as b:
        b.drop_constraint(op.f("fk_radio_map_run_id_slam_run"), type_="foreignkey")
        b.drop_column("provenance")
        b.drop_column("run_id")
        b.drop_column("source")
    op.drop_index("ix_loop_closure_site_id_floor", table_name="loop_closure")
    op.drop_index("ix_loop_closure_run_id", table_name="loop_closure")
    op.drop_table("loop_closure")
    op.drop_index("ix_track_point_run_id", table_name="track_point")
    op.drop_index("ix_track_point_walk_id_run_id_t", table_name="track_point")
    op.drop_table("track_point")
    op.drop_index("ix_walk_slam_site_id_status", table_name="walk_slam")
    op.drop_table("walk_slam")
    op.drop_table("slam_floor_done")
    op.drop_index("ix_slam_run_site_id_status", table_name="slam_run")
    op.drop_table("slam_run")

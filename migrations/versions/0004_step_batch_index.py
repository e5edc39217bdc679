"""steps indexed by their batch, not by device and time

Revision ID: 0004_step_batch_index
Revises: 0003_slam

``step`` is the table ingest writes most (a thousand rows a large batch), and its ``(device_id, t)``
index cost about as much again as the rows themselves: two devices' steps interleave in it, each row a
text-and-float key put in the middle of the tree. A walk's steps are read through its batches instead
(``batch.walk_id``, then ``ix_step_batch_id``), an index on an integer that grows with every batch, so
each row's key goes at its end. Scans (a tenth of the rows) and marks keep their ``(device_id, t)``
indexes.

Downgrade restores ``ix_step_device_t``. No row changes either way.
"""

from __future__ import annotations

from alembic import op

revision = "0004_step_batch_index"
down_revision = "0003_slam"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.drop_index("ix_step_device_t", table_name="step")
    op.create_index("ix_step_batch_id", "step", ["batch_id"], unique=False)


def downgrade() -> None:
    op.drop_index("ix_step_batch_id", table_name="step")
    op.create_index("ix_step_device_t", "step", ["device_id", "t"], unique=False)

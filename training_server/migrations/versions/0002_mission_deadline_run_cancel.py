"""Missions time out (missions.deadline); a cancel request outlives a restart
(training_runs.cancel_requested); running missions are found by an index on missions.status.

Revision ID: 0002
Revises: 0001
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("missions", sa.Column("deadline", sa.Float, nullable=True))
    op.create_index("ix_missions_status", "missions", ["status"])
    op.add_column("training_runs", sa.Column("cancel_requested", sa.Float, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("training_runs") as batch:  # SQLite drops a column by copying the table
        batch.drop_column("cancel_requested")
    op.drop_index("ix_missions_status", "missions")
    with op.batch_alter_table("missions") as batch:
        batch.drop_column("deadline")

"""Robots that left a running mission because their backend failed (missions.withdrawn): they
are no longer busy, and a mission no robot is left flying ends.

Revision ID: 0004
Revises: 0003
Create Date: 2026-12-06
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0004"
down_revision = "0003"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.add_column("missions", sa.Column("withdrawn", sa.Text, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("missions") as batch:
        batch.drop_column("withdrawn")

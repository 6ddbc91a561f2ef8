"""Robots' detections and the operator's decisions on them (detections); episode records that
the fleet's sensor model cannot explain are kept but set aside from estimation (episodes.set_aside).

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-06
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0003"
down_revision = "0002"
branch_labels = None
depends_on = None

ROW_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "detections",
        sa.Column("id", ROW_ID, primary_key=True, autoincrement=True),
        sa.Column("fleet", sa.Text, nullable=False),
        sa.Column("mission_id", sa.Text, nullable=False),
        sa.Column("robot_id", sa.Text, nullable=False),
        sa.Column("t", sa.BigInteger, nullable=False),
        sa.Column("node", sa.BigInteger, nullable=False),
        sa.Column("received", sa.Float, nullable=False),
        sa.Column("status", sa.Text, nullable=False),
        sa.Column("decided", sa.Float),
        sa.Column("decided_by", sa.Text),
    )
    op.create_index("ix_detections_mission", "detections", ["mission_id"])
    op.create_index("ix_detections_status", "detections", ["status"])
    op.add_column("episodes", sa.Column("set_aside", sa.Text, nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("episodes") as batch:
        batch.drop_column("set_aside")
    op.drop_index("ix_detections_status", "detections")
    op.drop_index("ix_detections_mission", "detections")
    op.drop_table("detections")

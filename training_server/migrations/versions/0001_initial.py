"""The schema of release 0.1.0 (the SQLite database before SQLAlchemy and Alembic).

A database written by that release has these tables but no alembic_version: the server stamps it
with this revision and migrates it from here (training_server.store.migrate).

Revision ID: 0001
Revises:
Create Date: 2026-11-24
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None

ROW_ID = sa.BigInteger().with_variant(sa.Integer(), "sqlite")


def upgrade() -> None:
    op.create_table(
        "episodes",
        sa.Column("id", ROW_ID, primary_key=True, autoincrement=True),
        sa.Column("fleet", sa.Text, nullable=False),
        sa.Column("robot_id", sa.Text, nullable=False),
        sa.Column("mission_id", sa.Text, nullable=False),
        sa.Column("policy_version", sa.BigInteger),
        sa.Column("steps", sa.BigInteger, nullable=False),
        sa.Column("captured", sa.Integer, nullable=False),
        sa.Column("capture_time", sa.BigInteger),
        sa.Column("received", sa.Float, nullable=False),
        sa.Column("record", sa.Text, nullable=False),
        sa.UniqueConstraint("fleet", "robot_id", "mission_id"),
    )
    op.create_table(
        "rejections",
        sa.Column("reason", sa.Text, primary_key=True),
        sa.Column("count", sa.BigInteger, nullable=False),
    )
    op.create_table(
        "missions",
        sa.Column("id", sa.Text, primary_key=True),
        sa.Column("fleet", sa.Text, nullable=False),
        sa.Column("created", sa.Float, nullable=False),
        sa.Column("robots", sa.Text, nullable=False),
        sa.Column("params", sa.Text, nullable=False),
        sa.Column("status", sa.Text, nullable=False),
        sa.Column("policy_version", sa.BigInteger),
        sa.Column("event", sa.Text),
        sa.Column("ended", sa.Float),
    )
    op.create_table(
        "policies",
        sa.Column("version", sa.BigInteger, primary_key=True, autoincrement=False),
        sa.Column("created", sa.Float, nullable=False),
        sa.Column("sha256", sa.Text, nullable=False),
        sa.Column("bytes", sa.BigInteger, nullable=False),
        sa.Column("parent", sa.BigInteger),
        sa.Column("run_id", sa.Text),
        sa.Column("meta", sa.Text, nullable=False),
    )
    op.create_table(
        "training_runs",
        sa.Column("id", sa.Text, primary_key=True),
        sa.Column("created", sa.Float, nullable=False),
        sa.Column("started", sa.Float),
        sa.Column("finished", sa.Float),
        sa.Column("status", sa.Text, nullable=False),
        sa.Column("params", sa.Text, nullable=False),
        sa.Column("progress", sa.Text),
        sa.Column("metrics", sa.Text),
        sa.Column("version", sa.BigInteger),
        sa.Column("error", sa.Text),
    )
    op.create_table(
        "settings",
        sa.Column("key", sa.Text, primary_key=True),
        sa.Column("value", sa.Text, nullable=False),
    )


def downgrade() -> None:
    for name in ("settings", "training_runs", "policies", "missions", "rejections", "episodes"):
        op.drop_table(name)

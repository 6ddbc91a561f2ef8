"""The server's tables (SQLAlchemy Core), the one description of its database schema.

Alembic's migrations (training_server/migrations/versions/) build and change the database; this
module says what the newest revision looks like, for the queries in training_server/store.py.
JSON values (records, parameters, metrics) are stored as text: the same on SQLite and PostgreSQL.
Integers that come from outside (policy versions, ids) are 64-bit (records.MAX_INT bounds them).
"""

from __future__ import annotations

from sqlalchemy import BigInteger, Column, Float, Index, Integer, MetaData, Table, Text, UniqueConstraint

metadata = MetaData()

# SQLite's rowid alias must be spelled INTEGER PRIMARY KEY; PostgreSQL gets a 64-bit identity
ROW_ID = BigInteger().with_variant(Integer(), "sqlite")

episodes = Table(
    "episodes",
    metadata,
    Column("id", ROW_ID, primary_key=True, autoincrement=True),
    Column("fleet", Text, nullable=False),
    Column("robot_id", Text, nullable=False),
    Column("mission_id", Text, nullable=False),
    Column("policy_version", BigInteger),
    Column("steps", BigInteger, nullable=False),
    Column("captured", Integer, nullable=False),
    Column("capture_time", BigInteger),
    Column("received", Float, nullable=False),
    Column("record", Text, nullable=False),
    Column("set_aside", Text),  # revision 0003: why the fleet's model cannot explain it (None: usable)
    UniqueConstraint("fleet", "robot_id", "mission_id"),
)

rejections = Table(
    "rejections",
    metadata,
    Column("reason", Text, primary_key=True),
    Column("count", BigInteger, nullable=False),
)

missions = Table(
    "missions",
    metadata,
    Column("id", Text, primary_key=True),
    Column("fleet", Text, nullable=False),
    Column("created", Float, nullable=False),
    Column("robots", Text, nullable=False),
    Column("params", Text, nullable=False),
    Column("status", Text, nullable=False),
    Column("policy_version", BigInteger),
    Column("event", Text),
    Column("ended", Float),
    Column("deadline", Float),  # revision 0002: the mission times out then (None: never)
    # revision 0004: robots that left the mission, JSON {robot: {"steps", "reason", "at"}}
    Column("withdrawn", Text),
    Index("ix_missions_status", "status"),
)

# revision 0003: what robots reported seeing (z = 1) during missions, and what became of each:
# pending (awaiting an operator), confirmed (it ended the mission as captured; decided_by "auto" or
# "operator"), dismissed (a false alarm: the search went on), closed (the mission ended otherwise)
detections = Table(
    "detections",
    metadata,
    Column("id", ROW_ID, primary_key=True, autoincrement=True),
    Column("fleet", Text, nullable=False),
    Column("mission_id", Text, nullable=False),
    Column("robot_id", Text, nullable=False),
    Column("t", BigInteger, nullable=False),
    Column("node", BigInteger, nullable=False),
    Column("received", Float, nullable=False),
    Column("status", Text, nullable=False),
    Column("decided", Float),
    Column("decided_by", Text),
    Index("ix_detections_mission", "mission_id"),
    Index("ix_detections_status", "status"),
)

policies = Table(
    "policies",
    metadata,
    Column("version", BigInteger, primary_key=True, autoincrement=False),
    Column("created", Float, nullable=False),
    Column("sha256", Text, nullable=False),
    Column("bytes", BigInteger, nullable=False),
    Column("parent", BigInteger),
    Column("run_id", Text),
    Column("meta", Text, nullable=False),
)

training_runs = Table(
    "training_runs",
    metadata,
    Column("id", Text, primary_key=True),
    Column("created", Float, nullable=False),
    Column("started", Float),
    Column("finished", Float),
    Column("status", Text, nullable=False),
    Column("params", Text, nullable=False),
    Column("progress", Text),
    Column("metrics", Text),
    Column("version", BigInteger),
    Column("error", Text),
    Column("cancel_requested", Float),  # revision 0002: when an operator asked to cancel it
)

settings = Table(
    "settings",
    metadata,
    Column("key", Text, primary_key=True),
    Column("value", Text, nullable=False),
)

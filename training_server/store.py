"""The server's durable state, through SQLAlchemy: the embedded SQLite database (WAL) under the
data directory by default, or PostgreSQL (``training-server --database-url
postgresql+psycopg://USER@HOST:PORT/DB``).

Tables (training_server/tables.py): episodes (one row per (fleet, robot, mission), the record
reduced to the contract; ``set_aside`` says why the fleet's model cannot explain it, and such a
record is kept but never estimated from), rejections (counts by reason), missions, detections
(robots' z = 1 reports and the decisions on them), policies (immutable versions;
the artifacts live on disk in the data directory), training_runs, and settings (the current
version, the map). Alembic migrates the database at start (``migrate``); a database written by
release 0.1.0 (no alembic_version) is stamped with its revision first, so nothing is lost.

Every write commits before the caller acknowledges anything (SQLite: synchronous=FULL), so an
acknowledged episode survives a crash. All access goes through one lock: the Zenoh ingest
worker, the HTTP handlers and the training supervisor share the store; a training process reads
episodes through its own engine (``read_episode_records``).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Connection, Engine, case, create_engine, event, func, inspect, make_url, select, update
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.exc import (
    ArgumentError,
    InterfaceError,
    InternalError,
    NoSuchModuleError,
    OperationalError,
    StatementError,
)
from sqlalchemy.pool import StaticPool

from shared.core.records import SET_ASIDE_REASONS
from training_server.tables import detections, episodes, missions, policies, rejections, settings, training_runs

log = logging.getLogger("mures.server.store")

MIGRATIONS = Path(__file__).parent / "migrations"
DB_FILE = "mures.db"


def sqlite_url(data_dir: Path) -> str:
    """The default database: ``data_dir/mures.db``."""
    return f"sqlite:///{data_dir / DB_FILE}"


def make_engine(url: str, *, shared_connection: bool = True) -> Engine:
    """An engine for ``url`` (clear ValueError for a URL SQLAlchemy cannot use). SQLite: one
    connection (``shared_connection``; callers serialise) in WAL mode with synchronous=FULL, each
    transaction taking the write lock at BEGIN so that two writers never deadlock."""
    try:
        backend = make_url(url).get_backend_name()
    except ArgumentError:
        raise ValueError(
            f"--database-url {url!r} is not a database URL: sqlite:///FILE or postgresql+psycopg://USER@HOST:PORT/DB"
        ) from None
    if backend not in ("sqlite", "postgresql"):
        raise ValueError(f"--database-url {url!r}: only sqlite:/// and postgresql+psycopg:// databases are supported")
    try:
        if backend == "sqlite":
            engine = create_engine(
                url,
                connect_args={"check_same_thread": False, "timeout": 10},
                **({"poolclass": StaticPool} if shared_connection else {}),
            )
        else:
            engine = create_engine(url, pool_pre_ping=True)
    except (ArgumentError, NoSuchModuleError, ValueError) as exc:
        raise ValueError(f"--database-url {url!r}: {exc}") from None
    except ModuleNotFoundError as exc:
        raise ValueError(
            f"--database-url {url!r} needs the {exc.name} driver: write postgresql+psycopg:// (psycopg 3, "
            "installed with the server)"
        ) from None
    if engine.dialect.name == "sqlite":

        @event.listens_for(engine, "connect")
        def _sqlite_connect(dbapi_conn: Any, _rec: Any) -> None:
            dbapi_conn.isolation_level = None  # SQLAlchemy's BEGIN below, not the driver's own
            cur = dbapi_conn.cursor()
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute("PRAGMA synchronous=FULL")
            cur.execute("PRAGMA busy_timeout=10000")
            cur.close()

        @event.listens_for(engine, "begin")
        def _sqlite_begin(conn: Connection) -> None:
            conn.exec_driver_sql("BEGIN IMMEDIATE" if shared_connection else "BEGIN")

    return engine


def _alembic_config(conn: Connection | None = None) -> Any:
    """Alembic's configuration for training_server/migrations, running on ``conn`` if given."""
    from alembic.config import Config

    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS))
    if conn is not None:
        cfg.attributes["connection"] = conn
    return cfg


def head_revision() -> str:
    from alembic.script import ScriptDirectory

    head = ScriptDirectory.from_config(_alembic_config()).get_current_head()
    assert head is not None
    return head


def current_revision(engine: Engine) -> str | None:
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def migrate(engine: Engine) -> tuple[str | None, str]:
    """Bring the database to the newest schema; returns (revision before, revision now). A
    database of release 0.1.0 (its tables, no alembic_version) is stamped 0001 first."""
    from alembic import command
    from alembic.util.exc import CommandError

    head = head_revision()
    with engine.begin() as conn:
        tables = set(inspect(conn).get_table_names())
        cfg = _alembic_config(conn)
        before = None
        if "alembic_version" in tables:
            from alembic.runtime.migration import MigrationContext

            before = MigrationContext.configure(conn).get_current_revision()
        elif "episodes" in tables:
            command.stamp(cfg, "0001")
            before = "0001"
        if before != head:
            try:
                command.upgrade(cfg, "head")
            except CommandError as exc:
                raise ValueError(
                    f"the database is at schema revision {before!r}, which this server does not know "
                    f"(newest here: {head}): a newer release wrote it ({exc})"
                ) from None
    if before != head:
        log.info("database schema migrated from %s to %s", before or "empty", head)
    return before, head


def _storable(*texts: str | None) -> bool:
    """False when a text cannot be stored, so cannot be found either: PostgreSQL refuses NUL
    characters in text (SQLite does not); every id the server stores is checked against
    records.ID_RE, which has none. Lookups of such a text find nothing instead of failing."""
    return not any(t is not None and "\x00" in t for t in texts)


def _to_json(x: Any) -> str | None:
    """A JSON value as the text column stores it (None stays NULL)."""
    return None if x is None else json.dumps(x, separators=(",", ":"))


def _from_json(s: str | None) -> Any:
    """A text column's JSON value (NULL is None)."""
    return None if s is None else json.loads(s)


def read_episode_records(url: str, fleet: str, limit: int) -> list[str]:
    """The newest ``limit`` stored records of ``fleet`` (JSON text) that are not set aside, through
    a separate engine: what a training process reads."""
    engine = make_engine(url, shared_connection=False)
    try:
        with engine.connect() as conn:
            e = episodes.c
            q = select(e.record).where(e.fleet == fleet, e.set_aside.is_(None)).order_by(e.id.desc()).limit(limit)
            return [r for (r,) in conn.execute(q)]
    finally:
        engine.dispose()


# the errors that concern one row only (a value the database refuses; sqlite3 raises OverflowError
# itself for an integer beyond 64 bits); anything else (disk full, connection lost) fails the
# whole transaction and the caller's batch
_ROW_ERRORS = (StatementError, OverflowError)
_BATCH_ERRORS = (OperationalError, InterfaceError, InternalError)


class Store:
    def __init__(self, url: str) -> None:
        self.url = url
        self.engine = make_engine(url)
        self.dialect = self.engine.dialect.name
        self.lock = threading.Lock()
        try:
            migrate(self.engine)
        except OperationalError as exc:
            self.engine.dispose()
            raise ValueError(f"cannot open the database {self.safe_url}: {exc.orig}") from None
        except BaseException:
            self.engine.dispose()
            raise

    @property
    def safe_url(self) -> str:
        """The URL without its password (for logs and errors)."""
        return self.engine.url.render_as_string(hide_password=True)

    def close(self) -> None:
        with self.lock:
            self.engine.dispose()

    @contextmanager
    def _tx(self) -> Iterator[Connection]:
        with self.lock, self.engine.begin() as conn:
            yield conn

    def _insert(self, table: Any) -> Any:
        return (postgresql.insert if self.dialect == "postgresql" else sqlite.insert)(table)

    # ------------------------------------------------------------------ episodes
    def add_episodes(
        self, rows: Iterable[tuple[str, str, str, int | None, int, bool, int | None, str, str | None]]
    ) -> list[bool | None]:
        """Insert (fleet, robot, mission, policy_version, steps, captured, capture_time, record json,
        set_aside reason or None) rows in one transaction. Per row: True if stored, False if it was
        already there, None if the database refused that row (the others are stored all the same: each row is its own
        savepoint). A failure of the database itself raises, and nothing of the batch is kept."""
        out: list[bool | None] = []
        now = time.time()
        stmt = self._insert(episodes).on_conflict_do_nothing(index_elements=["fleet", "robot_id", "mission_id"])
        stmt = stmt.returning(episodes.c.id)  # a row back if stored (rowcount is not reliable on every driver)
        with self._tx() as conn:
            for fleet, robot, mission, pv, steps, captured, ct, rec, aside in rows:
                values = {
                    "fleet": fleet,
                    "robot_id": robot,
                    "mission_id": mission,
                    "policy_version": pv,
                    "steps": steps,
                    "captured": int(captured),
                    "capture_time": ct,
                    "received": now,
                    "record": rec,
                    "set_aside": aside,
                }
                try:
                    with conn.begin_nested():
                        new = conn.execute(stmt, values).first()
                    out.append(new is not None)
                except _ROW_ERRORS as exc:
                    if isinstance(exc, _BATCH_ERRORS):
                        raise
                    log.error("episode %s/%s refused by the database: %s", robot, mission, getattr(exc, "orig", exc))
                    out.append(None)
        return out

    def reject(self, reasons: Iterable[str]) -> None:
        stmt = self._insert(rejections)
        stmt = stmt.on_conflict_do_update(index_elements=["reason"], set_={"count": rejections.c.count + 1})
        with self._tx() as conn:
            for r in reasons:
                conn.execute(stmt, {"reason": r, "count": 1})

    def episode_stats(self, fleet: str) -> dict[str, Any]:
        e = episodes.c
        with self._tx() as conn:
            stored = conn.execute(select(func.count()).where(e.fleet == fleet)).scalar_one()
            n_missions = conn.execute(select(func.count(e.mission_id.distinct())).where(e.fleet == fleet)).scalar_one()
            rej = dict(
                conn.execute(select(rejections.c.reason, rejections.c.count).order_by(rejections.c.reason)).all()
            )
            byv = conn.execute(
                select(e.policy_version, func.count()).where(e.fleet == fleet).group_by(e.policy_version)
            ).all()
            by_reason = {  # "<code>: <why>": a count per code, not a row per message
                code: n
                for code in SET_ASIDE_REASONS
                if (
                    n := conn.execute(
                        select(func.count()).where(e.fleet == fleet, e.set_aside.like(f"{code}:%"))
                    ).scalar_one()
                )
            }
            usable = conn.execute(
                select(func.count(e.mission_id.distinct())).where(e.fleet == fleet, e.set_aside.is_(None))
            ).scalar_one()
        return {
            "stored": stored,
            "rejected": rej,
            "set_aside": dict(sorted(by_reason.items())),
            "usable_missions": usable,
            "missions": n_missions,
            "by_policy_version": {str(v): c for v, c in byv},
        }

    def list_episodes(
        self,
        fleet: str,
        limit: int,
        after: int,
        mission_id: str | None,
        robot_id: str | None,
        set_aside: bool | None = None,
    ) -> list[dict[str, Any]]:
        e = episodes.c
        if not _storable(fleet, mission_id, robot_id):
            return []
        keys = (
            "id",
            "robot_id",
            "mission_id",
            "policy_version",
            "steps",
            "captured",
            "capture_time",
            "received",
            "set_aside",
        )
        q = select(*(getattr(e, k) for k in keys)).where(e.fleet == fleet, e.id > after)
        if mission_id:
            q = q.where(e.mission_id == mission_id)
        if robot_id:
            q = q.where(e.robot_id == robot_id)
        if set_aside is not None:
            q = q.where(e.set_aside.is_not(None) if set_aside else e.set_aside.is_(None))
        with self._tx() as conn:
            rows = conn.execute(q.order_by(e.id).limit(limit)).all()
        return [{**dict(zip(keys, r, strict=True)), "captured": bool(r[5])} for r in rows]

    def get_record(self, fleet: str, robot_id: str, mission_id: str) -> dict[str, Any] | None:
        if not _storable(fleet, robot_id, mission_id):
            return None
        e = episodes.c
        with self._tx() as conn:
            rec = conn.execute(
                select(e.record).where(e.fleet == fleet, e.robot_id == robot_id, e.mission_id == mission_id)
            ).scalar_one_or_none()
        return None if rec is None else json.loads(rec)

    def mission_records(self, fleet: str, mission_id: str) -> list[tuple[str, bool, int | None, int | None]]:
        if not _storable(fleet, mission_id):
            return []
        e = episodes.c
        with self._tx() as conn:
            rows = conn.execute(
                select(e.robot_id, e.captured, e.capture_time, e.policy_version).where(
                    e.fleet == fleet, e.mission_id == mission_id
                )
            ).all()
        return [(r, bool(c), ct, pv) for r, c, ct, pv in rows]

    def mission_steps(self, fleet: str, mission_id: str) -> int:
        """The most steps (t = 0, 1, ...) any stored record of the mission holds (0: none)."""
        e = episodes.c
        if not _storable(fleet, mission_id):
            return 0
        with self._tx() as conn:
            most = conn.execute(
                select(func.max(e.steps)).where(e.fleet == fleet, e.mission_id == mission_id)
            ).scalar_one()
        return int(most or 0)

    # ------------------------------------------------------------------ missions
    def add_mission(
        self,
        mission_id: str,
        fleet: str,
        robots: list[str],
        params: dict[str, Any],
        pv: int,
        deadline: float | None = None,
    ) -> None:
        with self._tx() as conn:
            conn.execute(
                missions.insert().values(
                    id=mission_id,
                    fleet=fleet,
                    created=time.time(),
                    robots=_to_json(robots),
                    params=_to_json(params),
                    status="running",
                    policy_version=pv,
                    deadline=deadline,
                )
            )

    def mission_event(self, mission_id: str, event: dict[str, Any], status: str) -> bool:
        """End a running mission with ``event`` (its captured, stop or timeout message); False if it
        was not running (the first event that ends a mission is the one kept). Its detections still
        awaiting a decision are closed."""
        m, d = missions.c, detections.c
        now = time.time()
        with self._tx() as conn:
            ended = conn.execute(
                update(missions)
                .where(m.id == mission_id, m.status == "running")
                .values(event=_to_json(event), status=status, ended=now)
                .returning(m.id)
            ).first()
            if ended is not None:
                conn.execute(
                    update(detections)
                    .where(d.mission_id == mission_id, d.status == "pending")
                    .values(status="closed", decided=now)
                )
        return ended is not None

    # ------------------------------------------------------------------ detections
    _DETECTION_KEYS = ("id", "mission_id", "robot_id", "t", "node", "received", "status", "decided", "decided_by")

    def add_detection(self, fleet: str, mission_id: str, robot_id: str, t: int, node: int, status: str) -> int:
        with self._tx() as conn:
            row = conn.execute(
                detections.insert()
                .values(
                    fleet=fleet,
                    mission_id=mission_id,
                    robot_id=robot_id,
                    t=t,
                    node=node,
                    received=time.time(),
                    status=status,
                )
                .returning(detections.c.id)
            ).first()
        assert row is not None
        return int(row[0])

    def detections(
        self, fleet: str, mission_id: str | None = None, status: str | None = None, limit: int = 1000
    ) -> list[dict[str, Any]]:
        """Detections of ``fleet`` (of one mission, or with one status), oldest first."""
        d = detections.c
        if not _storable(mission_id, status):
            return []
        q = select(*(getattr(d, k) for k in self._DETECTION_KEYS)).where(d.fleet == fleet)
        if mission_id is not None:
            q = q.where(d.mission_id == mission_id)
        if status is not None:
            q = q.where(d.status == status)
        with self._tx() as conn:
            rows = conn.execute(q.order_by(d.id).limit(limit)).all()
        return [dict(zip(self._DETECTION_KEYS, r, strict=True)) for r in rows]

    def detection(self, detection_id: int) -> dict[str, Any] | None:
        d = detections.c
        with self._tx() as conn:
            row = conn.execute(
                select(*(getattr(d, k) for k in self._DETECTION_KEYS)).where(d.id == detection_id)
            ).one_or_none()
        return None if row is None else dict(zip(self._DETECTION_KEYS, row, strict=True))

    def decide_detection(self, detection_id: int, status: str, by: str, only_if: str | None = "pending") -> bool:
        """Record the decision on a detection; False if it was not ``only_if`` (already decided)."""
        d = detections.c
        q = update(detections).where(d.id == detection_id)
        if only_if is not None:
            q = q.where(d.status == only_if)
        with self._tx() as conn:
            done = conn.execute(q.values(status=status, decided=time.time(), decided_by=by).returning(d.id)).first()
        return done is not None

    _MISSION_KEYS = ("id", "fleet", "created", "robots", "params", "status", "policy_version", "event", "ended")

    def _mission(self, row: Any) -> dict[str, Any]:
        d = dict(zip((*self._MISSION_KEYS, "deadline", "withdrawn"), row, strict=True))
        for k in ("robots", "params", "event"):
            d[k] = _from_json(d[k])
        d["withdrawn"] = _from_json(d["withdrawn"]) or {}
        return d

    def _mission_query(self) -> Any:
        return select(*(getattr(missions.c, k) for k in (*self._MISSION_KEYS, "deadline", "withdrawn")))

    def withdraw(self, mission_id: str, robot_id: str, steps: int, reason: str) -> dict[str, Any] | None:
        """Record that ``robot_id`` left running mission ``mission_id`` (its first withdrawal is
        kept); the mission as it is now, or None when it is not running or the robot not in it."""
        m = missions.c
        with self._tx() as conn:
            row = conn.execute(
                self._mission_query().where(m.id == mission_id, m.status == "running").with_for_update()
            ).one_or_none()
            if row is None:
                return None
            mission = self._mission(row)
            if robot_id not in mission["robots"]:
                return None
            if robot_id not in mission["withdrawn"]:
                mission["withdrawn"][robot_id] = {"steps": int(steps), "reason": reason, "at": time.time()}
                conn.execute(
                    update(missions).where(m.id == mission_id).values(withdrawn=_to_json(mission["withdrawn"]))
                )
        return mission

    def get_mission(self, mission_id: str) -> dict[str, Any] | None:
        if not _storable(mission_id):
            return None
        with self._tx() as conn:
            row = conn.execute(self._mission_query().where(missions.c.id == mission_id)).one_or_none()
        return None if row is None else self._mission(row)

    def list_missions(self, fleet: str, limit: int, offset: int) -> tuple[list[dict[str, Any]], int]:
        """A page of ``fleet``'s missions, newest first, and how many there are."""
        m = missions.c
        with self._tx() as conn:
            total = conn.execute(select(func.count()).select_from(missions).where(m.fleet == fleet)).scalar_one()
            rows = conn.execute(
                self._mission_query()
                .where(m.fleet == fleet)
                .order_by(m.created.desc(), m.id)
                .limit(limit)
                .offset(offset)
            ).all()
        return [self._mission(r) for r in rows], total

    def running_among(self, mission_ids: Iterable[str]) -> list[str]:
        """Those of ``mission_ids`` that are running missions (one query)."""
        ids = [m for m in mission_ids if _storable(m)]
        if not ids:
            return []
        m = missions.c
        with self._tx() as conn:
            rows = conn.execute(select(m.id).where(m.id.in_(ids), m.status == "running")).all()
        return sorted(r for (r,) in rows)

    def running_missions(self, fleet: str) -> list[dict[str, Any]]:
        m = missions.c
        with self._tx() as conn:
            rows = conn.execute(self._mission_query().where(m.fleet == fleet, m.status == "running")).all()
        return [self._mission(r) for r in rows]

    def mission_outcomes(self, fleet: str) -> list[dict[str, Any]]:
        """Every mission of ``fleet`` whose records arrived: its status, step limit and stop reason,
        the policy versions its robots flew, whether some robot captured and the first capture time."""
        e, m = episodes.c, missions.c
        first_capture = func.min(case((e.captured == 1, e.capture_time), else_=None))
        with self._tx() as conn:
            per = conn.execute(
                select(
                    e.mission_id,
                    func.min(e.policy_version),
                    func.max(e.policy_version),
                    func.max(e.captured),
                    first_capture,
                    func.max(e.steps),
                )
                .where(e.fleet == fleet)
                .group_by(e.mission_id)
            ).all()
            info = {
                mid: (status, _from_json(params), _from_json(ev))
                for mid, status, params, ev in conn.execute(
                    select(m.id, m.status, m.params, m.event).where(m.fleet == fleet)
                ).all()
            }
            out = []
            for mid, v_lo, v_hi, captured, ct, steps in per:
                status, params, ev = info.get(mid, (None, {}, None))
                out.append(
                    {
                        "mission_id": mid,
                        "status": status,
                        "max_steps": (params or {}).get("max_steps"),
                        "stop_reason": (ev or {}).get("reason"),
                        "policy_version": v_lo if v_lo == v_hi else None,  # None: robots flew different versions
                        "captured": bool(captured),
                        "capture_time": ct,
                        "steps": steps,  # the most steps (t = 0, 1, ...) a record holds
                        "seconds": self._seconds(conn, fleet, mid, ev or {}, bool(captured)),
                    }
                )
        return out

    @staticmethod
    def _seconds(conn: Connection, fleet: str, mission_id: str, event: dict[str, Any], captured: bool) -> float | None:
        """A mission on the mission clock in seconds: the capture's moment (its captured message), or,
        not captured, its last reading's time when every record carries times; None otherwise."""
        if captured:
            return event.get("time_s") if event.get("type") == "captured" else None
        if event.get("reason") not in ("step limit", "time limit"):  # stopped or timed out early: it counts for nothing
            return None
        return Store._last_reading_s(conn, fleet, mission_id)

    @staticmethod
    def _last_reading_s(conn: Connection, fleet: str, mission_id: str) -> float | None:
        """The latest last reading's time (mission clock, seconds) over the mission's stored
        records; None unless every record carries times."""
        e = episodes.c
        rows = conn.execute(select(e.record).where(e.fleet == fleet, e.mission_id == mission_id)).all()
        last = [(_from_json(rec) or {}).get("steps", [{}])[-1].get("time_s") for (rec,) in rows]
        return float(max(last)) if last and all(isinstance(x, int | float) for x in last) else None

    def mission_last_reading_s(self, fleet: str, mission_id: str) -> float | None:
        """The mission clock of the latest reading in the mission's stored records (seconds), None
        when a record has no times (robots not on the clock) or none is stored."""
        if not _storable(fleet, mission_id):
            return None
        with self._tx() as conn:
            return self._last_reading_s(conn, fleet, mission_id)

    @staticmethod
    def counted_capture_time(outcome: dict[str, Any]) -> float | None:
        """The capture time a mission outcome (``mission_outcomes``, ``canary_outcomes``) counts
        for: its capture time when captured, its step limit when it ran to it, its last step when it
        ran to its time limit, None when it was stopped or timed out early (it does not count)."""
        if outcome["captured"] and outcome["capture_time"] is not None:
            return float(outcome["capture_time"])
        if outcome["stop_reason"] == "step limit" and outcome["max_steps"]:
            return float(outcome["max_steps"])
        if outcome["stop_reason"] == "time limit" and outcome.get("steps"):
            return float(outcome["steps"] - 1)
        return None

    @staticmethod
    def counted_seconds(outcome: dict[str, Any]) -> float | None:
        """On the mission clock (``canary_outcomes``' "seconds"): the capture's moment, or the last
        reading's when the mission ran to its step or time limit; None where ``counted_capture_time`` is
        None or the mission was not on the clock. A robot's step count on the clock is its own
        (a robot that stays reads once a second), so trials compare seconds where both arms have them."""
        if Store.counted_capture_time(outcome) is None:
            return None
        return None if outcome.get("seconds") is None else float(outcome["seconds"])

    def canary_outcomes(self, fleet: str, canary_version: int) -> list[dict[str, Any]]:
        """The missions flown for the canary of ``canary_version`` whose every record has arrived:
        their arm and pair (mission params "canary"), step limit, stop reason, and the first capture
        time if some robot captured."""
        m, e = missions.c, episodes.c
        tag = f'%"canary_version":{int(canary_version)}%'
        with self._tx() as conn:
            rows = conn.execute(
                select(m.id, m.robots, m.params, m.event).where(m.fleet == fleet, m.params.like(tag))
            ).all()
            out = []
            for mid, robots, params, ev in rows:
                recs = conn.execute(
                    select(e.robot_id, e.captured, e.capture_time, e.steps).where(e.fleet == fleet, e.mission_id == mid)
                ).all()
                if not set(_from_json(robots)) <= {r for r, _c, _t, _s in recs}:
                    continue
                p, caps = _from_json(params), [t for _r, c, t, _s in recs if c and t is not None]
                event = _from_json(ev) or {}
                out.append(
                    {
                        "mission_id": mid,
                        "arm": p["canary"]["arm"],
                        "pair": p["canary"]["pair"],
                        "max_steps": p.get("max_steps"),
                        "stop_reason": event.get("reason"),
                        "captured": bool(caps),
                        "capture_time": min(caps) if caps else None,
                        "steps": max(s for _r, _c, _t, s in recs),
                        "seconds": self._seconds(conn, fleet, mid, event, bool(caps)),  # on the mission clock
                    }
                )
        return out

    def busy_robots(self, fleet: str) -> dict[str, str]:
        """{robot: mission} for every robot of a running mission whose record has not arrived and
        that has not withdrawn from it."""
        busy = {}
        for mission in self.running_missions(fleet):
            done = {r for r, *_ in self.mission_records(fleet, mission["id"])} | set(mission["withdrawn"])
            busy.update({r: mission["id"] for r in mission["robots"] if r not in done})
        return busy

    def expired_missions(self, fleet: str, now: float) -> list[dict[str, Any]]:
        """Running missions whose deadline has passed."""
        m = missions.c
        with self._tx() as conn:
            rows = conn.execute(
                self._mission_query().where(
                    m.fleet == fleet, m.status == "running", m.deadline.is_not(None), m.deadline < now
                )
            ).all()
        return [self._mission(r) for r in rows]

    # ------------------------------------------------------------------ policies
    def add_policy(
        self, version: int, sha256: str, size: int, parent: int | None, run_id: str | None, meta: dict[str, Any]
    ) -> None:
        with self._tx() as conn:
            conn.execute(
                policies.insert().values(
                    version=version,
                    created=time.time(),
                    sha256=sha256,
                    bytes=size,
                    parent=parent,
                    run_id=run_id,
                    meta=_to_json(meta),
                )
            )

    def update_policy_artifact(self, version: int, sha256: str, size: int, weights_sha256: str) -> None:
        """A version's artifact was rebuilt (format conversion): its new digest and size."""
        p = policies.c
        with self._tx() as conn:
            meta = conn.execute(select(p.meta).where(p.version == version)).scalar_one()
            meta = {**json.loads(meta), "weights_sha256": weights_sha256}
            conn.execute(
                update(policies).where(p.version == version).values(sha256=sha256, bytes=size, meta=_to_json(meta))
            )

    def update_policy_meta(self, version: int, extra: dict[str, Any]) -> None:
        """Add (or replace) top-level entries of a version's meta (e.g. its canary's evidence)."""
        p = policies.c
        with self._tx() as conn:
            meta = conn.execute(select(p.meta).where(p.version == version)).scalar_one_or_none()
            if meta is not None:
                conn.execute(
                    update(policies).where(p.version == version).values(meta=_to_json({**json.loads(meta), **extra}))
                )

    _POLICY_KEYS = ("version", "created", "sha256", "bytes", "parent", "run_id", "meta")

    def policies(self) -> list[dict[str, Any]]:
        p = policies.c
        with self._tx() as conn:
            rows = conn.execute(select(*(getattr(p, k) for k in self._POLICY_KEYS)).order_by(p.version)).all()
        return [{**dict(zip(self._POLICY_KEYS, r, strict=True)), "meta": json.loads(r[6])} for r in rows]

    def policy(self, version: int) -> dict[str, Any] | None:
        p = policies.c
        with self._tx() as conn:
            r = conn.execute(select(*(getattr(p, k) for k in self._POLICY_KEYS)).where(p.version == version)).first()
        return None if r is None else {**dict(zip(self._POLICY_KEYS, r, strict=True)), "meta": json.loads(r[6])}

    def next_version(self) -> int:
        with self._tx() as conn:
            v = conn.execute(select(func.max(policies.c.version))).scalar()
        return 1 if v is None else int(v) + 1

    def get_setting(self, key: str) -> str | None:
        with self._tx() as conn:
            v = conn.execute(select(settings.c.value).where(settings.c.key == key)).scalar_one_or_none()
        return None if v is None else str(v)

    def set_setting(self, key: str, value: str) -> None:
        stmt = self._insert(settings).values(key=key, value=value)
        stmt = stmt.on_conflict_do_update(index_elements=["key"], set_={"value": stmt.excluded.value})
        with self._tx() as conn:
            conn.execute(stmt)

    # ------------------------------------------------------------------ training runs
    def add_run(self, run_id: str, params: dict[str, Any]) -> None:
        with self._tx() as conn:
            conn.execute(
                training_runs.insert().values(id=run_id, created=time.time(), status="queued", params=_to_json(params))
            )

    def update_run(self, run_id: str, **fields: Any) -> None:
        values = {k: (_to_json(v) if k in ("progress", "metrics") else v) for k, v in fields.items()}
        with self._tx() as conn:
            conn.execute(update(training_runs).where(training_runs.c.id == run_id).values(**values))

    def request_cancel(self, run_id: str) -> str | None:
        """An operator cancels a run: a queued one is cancelled now, a running one is marked (its
        process stops at its next check, and a restart meanwhile keeps it cancelled). Returns
        the run's status afterwards, None if it was neither queued nor running."""
        r = training_runs.c
        now = time.time()
        if not _storable(run_id):
            return None
        with self._tx() as conn:
            status = conn.execute(select(r.status).where(r.id == run_id)).scalar_one_or_none()
            if status == "queued":
                conn.execute(
                    update(training_runs)
                    .where(r.id == run_id)
                    .values(status="cancelled", finished=now, cancel_requested=now)
                )
                return "cancelled"
            if status == "running":
                conn.execute(update(training_runs).where(r.id == run_id).values(cancel_requested=now))
                return "running"
        return None

    _RUN_KEYS = ("id", "created", "started", "finished", "status", "params", "progress", "metrics", "version", "error")

    def get_run(self, run_id: str) -> dict[str, Any] | None:
        runs = self.runs(run_id)
        return runs[0] if runs else None

    def runs(self, run_id: str | None = None) -> list[dict[str, Any]]:
        r = training_runs.c
        if not _storable(run_id):
            return []
        q = select(*(getattr(r, k) for k in (*self._RUN_KEYS, "cancel_requested")))
        q = q.where(r.id == run_id) if run_id else q.order_by(r.created, r.id)
        with self._tx() as conn:
            rows = conn.execute(q).all()
        out = []
        for row in rows:
            d = dict(zip((*self._RUN_KEYS, "cancel_requested"), row, strict=True))
            for k in ("params", "progress", "metrics"):
                d[k] = _from_json(d[k])
            out.append(d)
        return out

    def requeue_interrupted_runs(self) -> list[tuple[str, str]]:
        """Runs left queued or running by a previous server process did not finish: each becomes
        cancelled if an operator had asked for that, queued again otherwise (the supervisor
        resumes it). Returns (run, status)."""
        r = training_runs.c
        now = time.time()
        out = []
        with self._tx() as conn:
            rows = conn.execute(
                select(r.id, r.cancel_requested).where(r.status.in_(("queued", "running"))).order_by(r.created)
            ).all()
            for run_id, cancelled in rows:
                if cancelled is not None:
                    conn.execute(update(training_runs).where(r.id == run_id).values(status="cancelled", finished=now))
                    out.append((run_id, "cancelled"))
                else:
                    conn.execute(update(training_runs).where(r.id == run_id).values(status="queued"))
                    out.append((run_id, "queued"))
        return out

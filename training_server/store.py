"""The server's durable state: one SQLite database (WAL) under the data directory.

Tables: episodes (one row per (fleet, robot, mission), the record verbatim), rejections (counts
by reason), missions, policies (immutable versions; the artifacts live on disk beside the
database), training_runs, and settings (the current version). Every write commits before the
caller acknowledges anything (synchronous=FULL), so an acknowledged episode survives a crash.

One connection, guarded by a lock: the Zenoh ingest worker, the HTTP handlers and the training
supervisor all go through it; a training process reads episodes through its own connection.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

SCHEMA = """
CREATE TABLE IF NOT EXISTS episodes (
    id INTEGER PRIMARY KEY,
    fleet TEXT NOT NULL, robot_id TEXT NOT NULL, mission_id TEXT NOT NULL,
    policy_version INTEGER, steps INTEGER NOT NULL, captured INTEGER NOT NULL, capture_time INTEGER,
    received REAL NOT NULL, record TEXT NOT NULL,
    UNIQUE (fleet, robot_id, mission_id)
);
CREATE TABLE IF NOT EXISTS rejections (reason TEXT PRIMARY KEY, count INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS missions (
    id TEXT PRIMARY KEY, fleet TEXT NOT NULL, created REAL NOT NULL, robots TEXT NOT NULL,
    params TEXT NOT NULL, status TEXT NOT NULL, policy_version INTEGER, event TEXT, ended REAL
);
CREATE TABLE IF NOT EXISTS policies (
    version INTEGER PRIMARY KEY, created REAL NOT NULL, sha256 TEXT NOT NULL, bytes INTEGER NOT NULL,
    parent INTEGER, run_id TEXT, meta TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS training_runs (
    id TEXT PRIMARY KEY, created REAL NOT NULL, started REAL, finished REAL, status TEXT NOT NULL,
    params TEXT NOT NULL, progress TEXT, metrics TEXT, version INTEGER, error TEXT
);
CREATE TABLE IF NOT EXISTS settings (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


def _j(x: Any) -> str | None:
    return None if x is None else json.dumps(x, separators=(",", ":"))


def _unj(s: str | None) -> Any:
    return None if s is None else json.loads(s)


class Store:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.lock = threading.Lock()
        self.db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=FULL")
        self.db.execute("PRAGMA busy_timeout=10000")
        self.db.executescript(SCHEMA)

    def close(self) -> None:
        with self.lock:
            self.db.close()

    # ------------------------------------------------------------------ episodes
    def add_episodes(self, rows: Iterable[tuple[str, str, str, int | None, int, bool, int | None, str]]) -> list[bool]:
        """Insert (fleet, robot, mission, policy_version, steps, captured, capture_time, record json)
        rows in one transaction; per row True if stored, False if it was already there."""
        out = []
        now = time.time()
        with self.lock:
            self.db.execute("BEGIN IMMEDIATE")
            try:
                for fleet, robot, mission, pv, steps, captured, ct, rec in rows:
                    cur = self.db.execute(
                        "INSERT OR IGNORE INTO episodes (fleet, robot_id, mission_id, policy_version, steps, "
                        "captured, capture_time, received, record) VALUES (?,?,?,?,?,?,?,?,?)",
                        (fleet, robot, mission, pv, steps, int(captured), ct, now, rec),
                    )
                    out.append(cur.rowcount == 1)
                self.db.execute("COMMIT")
            except BaseException:
                self.db.execute("ROLLBACK")
                raise
        return out

    def reject(self, reasons: Iterable[str]) -> None:
        with self.lock:
            for r in reasons:
                self.db.execute(
                    "INSERT INTO rejections (reason, count) VALUES (?, 1) "
                    "ON CONFLICT(reason) DO UPDATE SET count = count + 1",
                    (r,),
                )

    def episode_stats(self, fleet: str) -> dict[str, Any]:
        with self.lock:
            stored = self.db.execute("SELECT COUNT(*) FROM episodes WHERE fleet=?", (fleet,)).fetchone()[0]
            missions = self.db.execute(
                "SELECT COUNT(DISTINCT mission_id) FROM episodes WHERE fleet=?", (fleet,)
            ).fetchone()[0]
            rej = dict(self.db.execute("SELECT reason, count FROM rejections ORDER BY reason").fetchall())
            byv = self.db.execute(
                "SELECT policy_version, COUNT(*) FROM episodes WHERE fleet=? GROUP BY policy_version", (fleet,)
            ).fetchall()
        return {
            "stored": stored,
            "rejected": rej,
            "missions": missions,
            "by_policy_version": {str(v): c for v, c in byv},
        }

    def list_episodes(
        self, fleet: str, limit: int, after: int, mission_id: str | None, robot_id: str | None
    ) -> list[dict[str, Any]]:
        q = (
            "SELECT id, robot_id, mission_id, policy_version, steps, captured, capture_time, received "
            "FROM episodes WHERE fleet=? AND id>?"
        )
        args: list[Any] = [fleet, after]
        if mission_id:
            q += " AND mission_id=?"
            args.append(mission_id)
        if robot_id:
            q += " AND robot_id=?"
            args.append(robot_id)
        q += " ORDER BY id LIMIT ?"
        args.append(limit)
        with self.lock:
            rows = self.db.execute(q, args).fetchall()
        keys = ("id", "robot_id", "mission_id", "policy_version", "steps", "captured", "capture_time", "received")
        return [{**dict(zip(keys, r, strict=True)), "captured": bool(r[5])} for r in rows]

    def get_record(self, fleet: str, robot_id: str, mission_id: str) -> dict[str, Any] | None:
        with self.lock:
            row = self.db.execute(
                "SELECT record FROM episodes WHERE fleet=? AND robot_id=? AND mission_id=?",
                (fleet, robot_id, mission_id),
            ).fetchone()
        return None if row is None else json.loads(row[0])

    def mission_records(self, fleet: str, mission_id: str) -> list[tuple[str, bool, int | None, int | None]]:
        with self.lock:
            return [
                (r, bool(c), ct, pv)
                for r, c, ct, pv in self.db.execute(
                    "SELECT robot_id, captured, capture_time, policy_version FROM episodes "
                    "WHERE fleet=? AND mission_id=?",
                    (fleet, mission_id),
                ).fetchall()
            ]

    # ------------------------------------------------------------------ missions
    def add_mission(self, mission_id: str, fleet: str, robots: list[str], params: dict[str, Any], pv: int) -> None:
        with self.lock:
            self.db.execute(
                "INSERT INTO missions (id, fleet, created, robots, params, status, policy_version) "
                "VALUES (?,?,?,?,?,?,?)",
                (mission_id, fleet, time.time(), _j(robots), _j(params), "running", pv),
            )

    def mission_event(self, mission_id: str, event: dict[str, Any], status: str) -> None:
        with self.lock:
            self.db.execute(
                "UPDATE missions SET event=COALESCE(event, ?), status=?, ended=COALESCE(ended, ?) "
                "WHERE id=? AND status='running'",
                (_j(event), status, time.time(), mission_id),
            )

    def get_mission(self, mission_id: str) -> dict[str, Any] | None:
        with self.lock:
            row = self.db.execute(
                "SELECT id, fleet, created, robots, params, status, policy_version, event, ended "
                "FROM missions WHERE id=?",
                (mission_id,),
            ).fetchone()
        if row is None:
            return None
        return {
            "id": row[0],
            "fleet": row[1],
            "created": row[2],
            "robots": _unj(row[3]),
            "params": _unj(row[4]),
            "status": row[5],
            "policy_version": row[6],
            "event": _unj(row[7]),
            "ended": row[8],
        }

    # ------------------------------------------------------------------ policies
    def add_policy(
        self, version: int, sha256: str, size: int, parent: int | None, run_id: str | None, meta: dict[str, Any]
    ) -> None:
        with self.lock:
            self.db.execute(
                "INSERT INTO policies (version, created, sha256, bytes, parent, run_id, meta) VALUES (?,?,?,?,?,?,?)",
                (version, time.time(), sha256, size, parent, run_id, _j(meta)),
            )

    def update_policy_artifact(self, version: int, sha256: str, size: int, weights_sha256: str) -> None:
        """A version's artifact was rebuilt (format conversion): its new digest and size."""
        with self.lock:
            (meta,) = self.db.execute("SELECT meta FROM policies WHERE version=?", (version,)).fetchone()
            meta = {**json.loads(meta), "weights_sha256": weights_sha256}
            self.db.execute(
                "UPDATE policies SET sha256=?, bytes=?, meta=? WHERE version=?", (sha256, size, _j(meta), version)
            )

    def policies(self) -> list[dict[str, Any]]:
        with self.lock:
            rows = self.db.execute(
                "SELECT version, created, sha256, bytes, parent, run_id, meta FROM policies ORDER BY version"
            ).fetchall()
        keys = ("version", "created", "sha256", "bytes", "parent", "run_id", "meta")
        return [{**dict(zip(keys, r, strict=True)), "meta": json.loads(r[6])} for r in rows]

    def policy(self, version: int) -> dict[str, Any] | None:
        return next((p for p in self.policies() if p["version"] == version), None)

    def next_version(self) -> int:
        with self.lock:
            v = self.db.execute("SELECT MAX(version) FROM policies").fetchone()[0]
        return 1 if v is None else int(v) + 1

    def get_setting(self, key: str) -> str | None:
        with self.lock:
            row = self.db.execute("SELECT value FROM settings WHERE key=?", (key,)).fetchone()
        return None if row is None else str(row[0])

    def set_setting(self, key: str, value: str) -> None:
        with self.lock:
            self.db.execute(
                "INSERT INTO settings (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE SET value=excluded.value",
                (key, value),
            )

    # ------------------------------------------------------------------ training runs
    def add_run(self, run_id: str, params: dict[str, Any]) -> None:
        with self.lock:
            self.db.execute(
                "INSERT INTO training_runs (id, created, status, params) VALUES (?,?,?,?)",
                (run_id, time.time(), "queued", _j(params)),
            )

    def update_run(self, run_id: str, **fields: Any) -> None:
        cols = []
        vals: list[Any] = []
        for k, v in fields.items():
            cols.append(f"{k}=?")
            vals.append(_j(v) if k in ("progress", "metrics") else v)
        with self.lock:
            self.db.execute(f"UPDATE training_runs SET {', '.join(cols)} WHERE id=?", (*vals, run_id))

    def get_run(self, run_id: str) -> dict[str, Any] | None:
        runs = self.runs(run_id)
        return runs[0] if runs else None

    def runs(self, run_id: str | None = None) -> list[dict[str, Any]]:
        q = "SELECT id, created, started, finished, status, params, progress, metrics, version, error "
        q += "FROM training_runs"
        with self.lock:
            rows = (
                self.db.execute(q + " WHERE id=?", (run_id,)).fetchall()
                if run_id
                else self.db.execute(q + " ORDER BY created").fetchall()
            )
        keys = ("id", "created", "started", "finished", "status", "params", "progress", "metrics", "version", "error")
        out = []
        for r in rows:
            d = dict(zip(keys, r, strict=True))
            for k in ("params", "progress", "metrics"):
                d[k] = _unj(d[k])
            out.append(d)
        return out

    def interrupted_runs(self) -> list[str]:
        """Runs left queued/running by a previous server process (they did not finish)."""
        with self.lock:
            return [
                r[0]
                for r in self.db.execute(
                    "SELECT id FROM training_runs WHERE status IN ('queued', 'running')"
                ).fetchall()
            ]

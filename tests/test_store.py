"""The server's database: migrations (a data directory of release 0.1.0 opens with nothing lost),
clear errors for a database it cannot use, and the same behaviour on SQLite and PostgreSQL."""

from __future__ import annotations

import hashlib
import json
import sqlite3
import tarfile
from pathlib import Path

import pytest
from sqlalchemy import text

from shared.core.graph import builtin_graph
from training_server.cli import main as server_main
from training_server.server import Server
from training_server.store import (
    Store,
    current_revision,
    head_revision,
    make_engine,
    read_episode_records,
    sqlite_url,
)

DATA = Path(__file__).parent / "data"


def _old_data_dir(tmp_path: Path) -> Path:
    """The data directory release 0.1.0 wrote (tests/data/make_datadir_0_1_0.py, run at 729df11)."""
    with tarfile.open(DATA / "datadir-0.1.0.tar.gz") as tar:
        tar.extractall(tmp_path, filter="data")
    return tmp_path / "data"


def _rows(db: Path, table: str) -> list[tuple]:
    with sqlite3.connect(db) as c:
        return c.execute(f"SELECT * FROM {table} ORDER BY 1").fetchall()


def test_a_data_directory_of_release_0_1_0_migrates_with_nothing_lost(tmp_path):
    d = _old_data_dir(tmp_path)
    before = {t: _rows(d / "mures.db", t) for t in ("episodes", "rejections", "missions", "policies", "settings")}
    runs_before = _rows(d / "mures.db", "training_runs")
    assert len(before["episodes"]) == 6 and len(before["missions"]) == 2 and len(runs_before) == 2
    srv = Server(d, builtin_graph("office"), "default", d / "operator.token", d / "agent.token")
    try:
        assert current_revision(srv.store.engine) == head_revision()
        assert srv.current_version() == 1
        art = srv.artifact(1)
        assert srv.store.policy(1)["sha256"] == hashlib.sha256(art.read_bytes()).hexdigest()
        stats = srv.store.episode_stats("default")
        assert stats["stored"] == 6 and stats["missions"] == 3 and stats["rejected"] == {"bad-json": 2, "bad-move": 1}
        rec = srv.store.get_record("default", "r0", "m1")
        assert rec["outcome"] == {"captured": True, "capture_time": 2, "captured_by": "r0"}
        m1 = srv.store.get_mission("m1")
        assert m1["status"] == "captured" and m1["event"]["captured_by"] == "r0" and m1["deadline"] is None
        assert [(r["id"], r["status"]) for r in srv.store.runs()] == [("run-a", "failed"), ("run-b", "cancelled")]
    finally:
        srv.close()
    after = {t: _rows(d / "mures.db", t) for t in before}
    for t in before:  # every old row is still there, with the new columns (None) appended
        assert [row[: len(before[t][0])] for row in after[t]] == before[t], t
    assert [r[:10] for r in _rows(d / "mures.db", "training_runs")] == runs_before
    # a second start finds nothing to migrate
    srv = Server(d, builtin_graph("office"), "default", d / "operator.token", d / "agent.token")
    srv.close()


def test_a_database_of_a_newer_release_is_refused_clearly(tmp_path):
    url = sqlite_url(tmp_path)
    Store(url).close()
    engine = make_engine(url)
    with engine.begin() as conn:
        conn.execute(text("UPDATE alembic_version SET version_num = '9999'"))
    engine.dispose()
    with pytest.raises(ValueError, match=r"revision '9999'.*newer release"):
        Store(url)


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("mysql://root@127.0.0.1/x", "only sqlite"),
        ("not a url", "is not a database URL"),
        ("postgresql+psycopg://postgres@127.0.0.1:1/mures", "cannot open the database"),
    ],
)
def test_bad_database_urls_get_a_clear_error(tmp_path, capsys, url, message):
    with pytest.raises(ValueError, match=message):
        Store(url)
    code = server_main(["--env", "office", "--data-dir", str(tmp_path / "d"), "--database-url", url])
    assert code == 2 and message.split("'")[0] in capsys.readouterr().err
    assert not (tmp_path / "d" / "mures.db").exists()


def test_the_same_data_on_both_backends(tmp_path, database_url):
    """Every store operation the server uses, on SQLite and on PostgreSQL: the same answers."""
    srv_url = database_url or sqlite_url(tmp_path)
    s = Store(srv_url)
    try:
        rows = [("f", f"r{k}", "m1", k, 3, k == 1, 2 if k == 1 else None, json.dumps({"k": k}), None) for k in range(3)]
        rows.append(("f", "r0", "m2", 0, 2, False, None, json.dumps({"k": 3}), "impossible: z = 1 at t=0 ..."))
        assert s.add_episodes(rows) == [True, True, True, True]
        assert s.add_episodes(rows[:2]) == [False, False]
        s.reject(["json", "json", "move"])
        assert s.episode_stats("f") == {
            "stored": 4,
            "rejected": {"json": 2, "move": 1},
            "set_aside": {"impossible": 1},
            "missions": 2,
            "usable_missions": 1,
            "by_policy_version": {"0": 2, "1": 1, "2": 1},
        }
        assert [json.loads(r) for r in read_episode_records(srv_url, "f", 10)] == [{"k": 2}, {"k": 1}, {"k": 0}]
        assert s.list_episodes("f", 10, 3, None, None)[0]["set_aside"].startswith("impossible")
        assert [e["id"] for e in s.list_episodes("f", 2, 0, None, None)] == [1, 2]
        assert s.get_record("f", "r2", "m1") == {"k": 2}
        s.add_mission("m1", "f", ["r0", "r1", "r2", "r3"], {"seed": 1}, 1, deadline=10.0)
        assert s.busy_robots("f") == {"r3": "m1"}
        assert [m["id"] for m in s.expired_missions("f", 11.0)] == ["m1"] and s.expired_missions("f", 9.0) == []
        d = s.add_detection("f", "m1", "r1", 4, 7, "pending")
        assert [x["id"] for x in s.detections("f", status="pending")] == [d]
        assert s.mission_event("m1", {"type": "stop"}, "stopped") and not s.mission_event("m1", {}, "captured")
        assert s.detection(d)["status"] == "closed" and not s.decide_detection(d, "confirmed", "operator")
        assert s.get_mission("m1")["status"] == "stopped" and s.busy_robots("f") == {}
        s.add_policy(1, "ab", 10, None, None, {"x": 1})
        s.update_policy_artifact(1, "cd", 11, "w")
        assert s.policy(1)["sha256"] == "cd" and s.policy(1)["meta"] == {"x": 1, "weights_sha256": "w"}
        assert s.next_version() == 2 and s.policy(2) is None
        s.set_setting("k", "1")
        s.set_setting("k", "2")
        assert s.get_setting("k") == "2" and s.get_setting("none") is None
        s.add_run("a", {"episodes": 1})
        s.update_run("a", status="running", progress={"phase": "em"})
        assert s.get_run("a")["progress"] == {"phase": "em"}
        assert s.request_cancel("a") == "running" and s.requeue_interrupted_runs() == [("a", "cancelled")]
    finally:
        s.close()

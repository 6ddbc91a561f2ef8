"""The REST API in-process (FastAPI's TestClient): a real Server (SQLite, policy versions) with the
Zenoh bus and the training supervisor replaced by recorders. Every response is checked against
the served OpenAPI document: its status must be one the route documents, and an error body must
be the one Error schema."""

from __future__ import annotations

import io
import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from shared.core.graph import builtin_graph
from shared.core.models import Sensor
from shared.core.records import make_record
from shared.learning.config import default
from training_server.api import create_app
from training_server.cli import build_parser, check_exposure
from training_server.cli import main as server_main
from training_server.server import Server

OP, AG = "op-token", "agent-token"


class FakeBus:
    """What the API needs of training_server.bus.Bus, recorded."""

    def __init__(self) -> None:
        self.online: dict[str, float] = {}
        self.gone: dict[str, float] = {}  # robots that dropped off: when last heard of
        self.live: dict[str, dict[str, Any]] = {}  # robot -> last telemetry
        self.truth: dict[str, dict[str, Any]] = {}  # mission -> the simulated world's last ground truth
        self.published: list[dict[str, Any]] = []
        self.stats = {"ingest_batches": 3, "ingest_seconds": 0.25}

    def agents_online(self) -> dict[str, float]:
        return dict(self.online)

    def agents(self) -> dict[str, dict[str, Any]]:
        heard = {**self.gone, **self.online}
        return {
            r: {"online": r in self.online, "since": self.online.get(r), "last_seen": t, "live": self.live.get(r)}
            for r, t in sorted(heard.items())
        }

    def truth_of(self, mission_id: str) -> dict[str, Any] | None:
        return self.truth.get(mission_id)

    def publish_mission(self, msg: dict[str, Any]) -> None:
        self.published.append(msg)


class FakeSupervisor:
    def __init__(self) -> None:
        self.submitted: list[str] = []
        self.cancelled: list[str] = []

    def submit(self, run_id: str) -> None:
        self.submitted.append(run_id)

    def cancel(self, run_id: str) -> bool:
        self.cancelled.append(run_id)
        return True


class CheckedClient(TestClient):
    """A TestClient that fails the test when a response's status is not documented for its route."""

    def request(self, method: str, url: Any, *args: Any, **kwargs: Any) -> Any:  # type: ignore[override]
        resp = super().request(method, url, *args, **kwargs)
        op, template = _operation(self.app.openapi(), method, str(url).split("?")[0])  # type: ignore[attr-defined]
        if op is not None:
            assert str(resp.status_code) in op["responses"], (
                f"{method} {template} answered {resp.status_code}, documented: {sorted(op['responses'])}"
            )
            if resp.status_code >= 400:
                schema = op["responses"][str(resp.status_code)]["content"]["application/json"]["schema"]
                assert schema == {"$ref": "#/components/schemas/Error"}, (method, template, schema)
                assert set(resp.json()) == {"error"} and resp.json()["error"], resp.text
        return resp


def _operation(spec: dict[str, Any], method: str, path: str) -> tuple[dict[str, Any] | None, str | None]:
    """The OpenAPI operation serving ``method path`` (a literal segment beats a parameter)."""
    hits = []
    for template, ops in spec["paths"].items():
        if method.lower() in ops and re.fullmatch(re.sub(r"\{[^/]+\}", "[^/]+", template), path):
            hits.append((template.count("{"), template))
    if not hits:
        return None, None
    template = min(hits)[1]
    return spec["paths"][template][method.lower()], template


@pytest.fixture
def api(tmp_path: Path, database_url: str | None):
    """The API over each database backend in turn (SQLite, PostgreSQL)."""
    graph = builtin_graph("office")
    (tmp_path / "op.token").write_text(OP + "\n")
    (tmp_path / "agent.token").write_text(AG + "\n")
    srv = Server(
        tmp_path / "data", graph, "default", tmp_path / "op.token", tmp_path / "agent.token", database_url=database_url
    )
    srv.ensure_initial_policy(2, None, Sensor(), seed=0)
    srv.bus = FakeBus()
    srv.supervisor = FakeSupervisor()
    with CheckedClient(create_app(srv)) as client:
        yield srv, client
    srv.close()


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _store_episode(srv: Server, robot: str = "r1", mission: str = "m1") -> None:
    g = srv.graph
    rec = make_record(
        g,
        fleet="default",
        mission_id=mission,
        robot_id=robot,
        nodes=[g.start, g.start],
        z=[0, 1],
        sensor=Sensor(),
        captured=True,
        capture_time=1,
        captured_by=robot,
        policy_version=1,
    )
    import json

    srv.store.add_episodes([("default", robot, mission, 1, 2, True, 1, json.dumps(rec), None)])


def test_tokens_and_roles(api):
    _srv, c = api
    assert c.get("/api/v1/health").json()["status"] == "ok"  # no token needed
    r = c.get("/api/v1/map")
    assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer"
    assert c.get("/api/v1/map", headers=auth("nope")).status_code == 401
    assert c.get("/api/v1/map", headers=auth(AG)).json()["graph_id"].startswith("sha256:")
    r = c.post("/api/v1/missions", json={}, headers=auth(AG))
    assert r.status_code == 403 and "operator" in r.json()["error"]


def test_missions_start_follow_stop(api):
    srv, c = api
    r = c.post("/api/v1/missions", json={}, headers=auth(OP))
    assert r.status_code == 409 and "no agents online" in r.json()["error"]
    srv.bus.online = {"r1": 1.0, "r2": 2.0}
    r = c.post("/api/v1/missions", json={"seed": 7, "mission_id": "m-a"}, headers=auth(OP))
    assert r.status_code == 201 and r.headers["location"] == "/api/v1/missions/m-a"
    m = r.json()
    assert m["robots"] == ["r1", "r2"] and m["params"]["seed"] == 7 and m["params"]["max_steps"] == 180
    assert srv.bus.published[-1]["type"] == "start" and srv.bus.published[-1]["policy_version"] == 1
    assert c.post("/api/v1/missions", json={"mission_id": "m-a"}, headers=auth(OP)).status_code == 409
    assert c.post("/api/v1/missions", json={"robots": ["r1", "r1"]}, headers=auth(OP)).status_code == 422
    r = c.post("/api/v1/missions", json={"robots": ["r9"]}, headers=auth(OP))
    assert r.status_code == 409 and "r9" in r.json()["error"]
    assert c.get("/api/v1/missions/m-a", headers=auth(AG)).json()["status"] == "running"
    assert c.post("/api/v1/missions/m-a/stop", headers=auth(OP)).json()["status"] == "stopped"
    assert srv.bus.published[-1] == {"type": "stop", "mission_id": "m-a", "reason": "operator"}
    assert c.get("/api/v1/missions/nope", headers=auth(AG)).status_code == 404
    # a time limit on the mission clock: the step limit then only guards
    r = c.post("/api/v1/missions", json={"seed": 8, "max_seconds": 600}, headers=auth(OP))
    assert r.status_code == 201 and r.json()["params"]["max_seconds"] == 600
    assert r.json()["params"]["max_steps"] == 100_000
    assert srv.bus.published[-1]["max_seconds"] == 600 and srv.bus.published[-1]["max_steps"] == 100_000


def test_a_mission_without_limits_for_robots_on_the_clock_gets_the_step_limits_horizon_in_time(api):
    """Robots on the mission clock say so in their telemetry, with their speed; a mission started for
    them with no limit is limited to 3 n moves of the map's median edge at the slowest one's speed
    (a robot on the clock that stays reads once a second: a step limit would end it early)."""
    import dataclasses

    srv, c = api
    srv.bus.online = {"r1": 1.0, "r2": 2.0, "r3": 3.0}
    srv.bus.live = {"r1": {"state": "idle", "clock": "seconds", "speed": 0.5},
                    "r2": {"state": "idle", "clock": "seconds", "speed": 0.4}, "r3": {"state": "idle"}}  # fmt: skip
    start = c.post("/api/v1/missions", json={"robots": ["r1"]}, headers=auth(OP))
    assert "max_seconds" not in srv.bus.published[-1]  # the built-in map has no edge lengths: steps alone
    c.post(f"/api/v1/missions/{start.json()['id']}/stop", headers=auth(OP))
    lengths = np.linspace(2.0, 8.0, srv.graph.m)
    srv.graph = dataclasses.replace(srv.graph, edge_lengths=lengths)
    for robots, speed in ((["r1"], 0.5), (["r1", "r2", "r3"], 0.4)):
        r = c.post("/api/v1/missions", json={"robots": robots}, headers=auth(OP))
        expected = round(3 * srv.graph.n * float(np.median(lengths)) / speed, 1)
        assert r.status_code == 201 and r.json()["params"]["max_seconds"] == expected
        assert srv.bus.published[-1]["max_seconds"] == expected and srv.bus.published[-1]["max_steps"] == 100_000
        c.post(f"/api/v1/missions/{r.json()['id']}/stop", headers=auth(OP))
    by = {a["robot_id"]: a for a in c.get("/api/v1/fleet", headers=auth(AG)).json()["agents"]}
    assert (by["r1"]["speed"], by["r2"]["speed"], by["r3"]["speed"]) == (0.5, 0.4, None)
    # a robot on the step index, or a request that names a step limit, keeps the step limit alone
    for body in ({"robots": ["r3"]}, {"robots": ["r1"], "max_steps": 40}):
        r = c.post("/api/v1/missions", json=body, headers=auth(OP))
        assert r.json()["params"]["max_seconds"] is None and "max_seconds" not in srv.bus.published[-1]
        assert r.json()["params"]["max_steps"] == body.get("max_steps", 3 * srv.graph.n)
        c.post(f"/api/v1/missions/{r.json()['id']}/stop", headers=auth(OP))


@pytest.mark.parametrize(
    ("path", "body", "field"),
    [
        ("/api/v1/policies/current", {"version": True}, "version"),  # a bool is not a version
        ("/api/v1/policies/current", {"version": "1"}, "version"),
        ("/api/v1/missions", {"seed": "5000"}, "seed"),  # no strings for integers
        ("/api/v1/missions", '{"seed": 1e400}', "seed"),  # JSON's 1e400 is infinity
        ("/api/v1/missions", {"seed": 2**63}, "seed"),  # does not fit the database
        ("/api/v1/missions", {"robots": ["bad id!"]}, "robots"),
        ("/api/v1/missions", {"colour": "red"}, "colour"),
        ("/api/v1/missions", {"max_seconds": 0}, "max_seconds"),
        ("/api/v1/missions", {"max_seconds": "60"}, "max_seconds"),
        ("/api/v1/missions", '{"max_seconds": Infinity}', "max_seconds"),
        ("/api/v1/training-runs", '{"lr": NaN}', "lr"),
        ("/api/v1/training-runs", {"episodes": 5000.5}, "episodes"),
        ("/api/v1/training-runs", {"gate": "yes"}, "gate"),
        ("/api/v1/training-runs", {"unknown": 1}, "unknown"),
    ],
)
def test_bad_requests_are_422_naming_the_field_and_change_nothing(api, path, body, field):
    srv, c = api
    srv.bus.online = {"r1": 1.0}
    _store_episode(srv)
    before = (srv.current_version(), srv.store.get_mission("m1"), srv.store.runs(), list(srv.bus.published))
    if isinstance(body, str):  # raw JSON text (the client itself refuses to encode NaN and infinity)
        r = c.post(path, content=body, headers={**auth(OP), "Content-Type": "application/json"})
    else:
        r = c.post(path, json=body, headers=auth(OP))
    assert r.status_code == 422 and field in r.json()["error"], r.text
    assert (srv.current_version(), srv.store.get_mission("m1"), srv.store.runs(), srv.bus.published) == before


def test_bad_queries(api):
    _srv, c = api
    for q in ("after=9223372036854775808", "after=-1", "limit=0", "limit=abc"):
        r = c.get(f"/api/v1/episodes?{q}", headers=auth(AG))
        assert r.status_code == 422, q
    assert c.get("/api/v1/policies/0", headers=auth(AG)).status_code == 422
    assert c.get("/api/v1/policies/x", headers=auth(AG)).status_code == 422


def test_episodes_paged_and_one_record(api):
    srv, c = api
    for k in range(3):
        _store_episode(srv, robot=f"r{k}")
    page = c.get("/api/v1/episodes?limit=2", headers=auth(AG)).json()
    assert [i["robot_id"] for i in page["items"]] == ["r0", "r1"] and page["next_after"] == page["items"][-1]["id"]
    rest = c.get(f"/api/v1/episodes?limit=2&after={page['next_after']}", headers=auth(AG)).json()
    assert [i["robot_id"] for i in rest["items"]] == ["r2"] and rest["next_after"] is None
    rec = c.get("/api/v1/episodes/r1/m1", headers=auth(AG)).json()
    assert rec["schema"] == "mures.episode/1" and rec["steps"][1] == {"t": 1, "node": 43, "z": 1}
    assert c.get("/api/v1/episodes/r9/m1", headers=auth(AG)).status_code == 404
    stats = c.get("/api/v1/episodes/stats", headers=auth(AG)).json()
    assert stats["stored"] == 3 and stats["missions"] == 1 and stats["by_policy_version"] == {"1": 3}


def test_policies_promote_and_artifact_etag(api):
    _srv, c = api
    listed = c.get("/api/v1/policies", headers=auth(AG)).json()
    assert listed["current"] == 1 and [p["version"] for p in listed["items"]] == [1]
    assert c.post("/api/v1/policies/current", json={"version": 5}, headers=auth(OP)).status_code == 404
    r = c.get("/api/v1/policies/1/artifact", headers=auth(AG))
    assert r.status_code == 200 and r.headers["etag"] == f'"{listed["items"][0]["sha256"]}"'
    assert r.headers["content-type"] == "application/x-tar"
    r2 = c.get("/api/v1/policies/1/artifact", headers={**auth(AG), "If-None-Match": r.headers["etag"]})
    assert r2.status_code == 304 and r2.content == b""
    assert c.get("/api/v1/policies/2/artifact", headers=auth(AG)).status_code == 404
    assert c.post("/api/v1/policies/current", json={"version": 1}, headers=auth(OP)).json()["current"] is True


def test_training_runs(api):
    srv, c = api
    r = c.post("/api/v1/training-runs", headers=auth(OP))
    assert r.status_code == 409 and "0 missions recorded, 50 needed (50 more)" in r.json()["error"]
    _store_episode(srv)
    # one mission is too little to fit a model on (a run on it promoted a worse policy): refused, saying why
    r = c.post("/api/v1/training-runs", json={"episodes": 512}, headers=auth(OP))
    assert r.status_code == 409 and "1 missions recorded, 50 needed (49 more)" in r.json()["error"]
    # travel times need the map's edge lengths: refused at once, naming the map
    r = c.post("/api/v1/training-runs", json={"speed": 0.5, "min_missions": 1}, headers=auth(OP))
    assert r.status_code == 409 and f"map {srv.graph.name} has no edge lengths" in r.json()["error"]
    assert c.get("/api/v1/training-runs", headers=auth(AG)).json()["items"] == []
    r = c.post("/api/v1/training-runs", json={"episodes": 512, "beta": 1, "min_missions": 1}, headers=auth(OP))
    assert r.status_code == 202 and r.headers["location"].endswith(r.json()["id"])
    run = r.json()
    # the defaults of the trainer's own settings are TrainConfig's; an lr left out is the method's own
    # (TrainConfig's, or a general policy fine-tune's), chosen when the run starts
    assert run["params"]["lr"] is None and run["params"]["em_max_iter"] == default("em_max_iter")
    assert run["params"]["beta"] == 1.0 and run["status"] == "queued" and srv.supervisor.submitted == [run["id"]]
    r = c.post(f"/api/v1/training-runs/{run['id']}/cancel", headers=auth(OP))
    assert r.status_code == 202 and r.json()["status"] == "cancelled"  # a queued run is cancelled at once
    assert c.post(f"/api/v1/training-runs/{run['id']}/cancel", headers=auth(OP)).status_code == 409
    assert c.get("/api/v1/training-runs/none", headers=auth(AG)).status_code == 404
    assert [x["id"] for x in c.get("/api/v1/training-runs", headers=auth(AG)).json()["items"]] == [run["id"]]


def test_metrics_from_prometheus_client(api):
    srv, c = api
    _store_episode(srv)
    srv.store.reject(["move", "move", "json"])
    assert c.get("/metrics").status_code == 401  # a fleet token, unless --metrics-without-token
    assert c.get("/metrics", headers={"Authorization": "Bearer wrong"}).status_code == 401
    srv.metrics_without_token = True
    assert c.get("/metrics").status_code == 200
    srv.metrics_without_token = False
    r = c.get("/metrics", headers=auth(AG))
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    samples = {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for fam in text_string_to_metric_families(r.text)
        for s in fam.samples
    }
    assert samples[("mures_episodes_stored", ())] == 1
    assert samples[("mures_episodes_rejected_total", (("reason", "move"),))] == 2
    assert samples[("mures_policy_current_version", ())] == 1
    assert samples[("mures_training_runs", (("status", "queued"),))] == 0
    assert samples[("mures_ingest_batches_total", ())] == 3


def test_unknown_routes_and_methods_get_the_error_schema(api):
    _srv, c = api
    r = c.get("/api/v1/nothing-here")
    assert r.status_code == 404 and r.json() == {"error": "Not Found"}
    r = c.delete("/api/v1/health")
    assert r.status_code == 405 and r.headers["allow"] == "GET" and set(r.json()) == {"error"}
    # Allow lists every method of the path, also where two routes share it or it has a parameter
    assert c.options("/api/v1/policies/current").headers["allow"] == "GET, POST"
    assert c.delete("/api/v1/missions/m-1").headers["allow"] == "GET"
    r = c.post("/api/v1/missions", content=b"\xff{", headers={**auth(OP), "Content-Type": "application/json"})
    assert r.status_code in (400, 422) and "JSON" in r.json()["error"], r.text


def test_openapi_documents_auth_errors_on_every_protected_route(api):
    _srv, c = api
    spec = c.get("/openapi.json").json()
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            if path == "/api/v1/health":
                assert "401" not in op["responses"], (method, path)
                continue
            assert "401" in op["responses"], (method, path)
            # 403: an operator action with the agent token, or a robot's token on other robots' records
            scoped = path in (
                "/api/v1/episodes",
                "/api/v1/episodes/{robot_id}/{mission_id}",
                "/api/v1/missions/{mission_id}/export.mcap",
                "/api/v1/missions/{mission_id}/replay",
            )
            assert ("403" in op["responses"]) == (method == "post" or scoped), (method, path)
            assert "HTTPValidationError" not in str(op["responses"]), (method, path)


def test_a_large_body_is_413_unread_and_not_echoed(api):
    srv, c = api
    srv.bus.online = {"r1": 1.0}
    _store_episode(srv)  # so that a training run would be accepted if its handler ran
    big = b'{"robots": ["' + b"r" * (2 << 20) + b'"]}'
    r = c.post("/api/v1/missions", content=big, headers={**auth(OP), "Content-Type": "application/json"})
    assert r.status_code == 413 and len(r.content) < 200 and "larger than" in r.json()["error"]

    def chunks():  # no Content-Length: the limit counts the bytes as they come; the first MiB is valid JSON
        yield b"{}"
        for _ in range(40):
            yield b" " * (64 << 10)

    r = c.post("/api/v1/training-runs", content=chunks(), headers={**auth(OP), "Content-Type": "application/json"})
    assert r.status_code == 413 and srv.store.runs() == [] and srv.bus.published == []


def test_one_server_per_data_directory_and_private_files(api, tmp_path):
    srv, _c = api
    with pytest.raises(ValueError, match="in use by another training-server"):
        Server(srv.data_dir, srv.graph, "default", tmp_path / "op.token", tmp_path / "agent.token")
    assert srv.data_dir.stat().st_mode & 0o777 == 0o700
    if srv.store.dialect == "sqlite":
        assert (srv.data_dir / "mures.db").stat().st_mode & 0o777 == 0o600


def test_failed_sign_ins_are_logged_and_rate_limited(api, caplog):
    _srv, c = api
    for _ in range(10):
        assert c.get("/api/v1/fleet", headers=auth("guess")).status_code == 401
    assert "failed sign-in from testclient" in caplog.text
    r = c.get("/api/v1/fleet", headers=auth(AG))  # even the right token, from this address, for a while
    assert r.status_code == 429 and int(r.headers["retry-after"]) > 0
    assert c.get("/api/v1/health").status_code == 200  # no token, no limit


def test_rotated_tokens_take_effect_at_the_next_request(api, tmp_path):
    _srv, c = api
    assert c.get("/api/v1/fleet", headers=auth(AG)).status_code == 200
    assert server_main(["rotate-token", "agent", "--token-file", str(tmp_path / "agent.token")]) == 0
    new = (tmp_path / "agent.token").read_text().strip()
    assert new != AG and (tmp_path / "agent.token").stat().st_mode & 0o777 == 0o600
    assert c.get("/api/v1/fleet", headers=auth(AG)).status_code == 401
    assert c.get("/api/v1/fleet", headers=auth(new)).status_code == 200
    assert server_main(["rotate-token", "agent", "--data-dir", str(tmp_path / "nowhere")]) == 2


def test_operator_actions_are_audited(api):
    srv, c = api
    srv.bus.online = {"r1": 1.0}
    c.post("/api/v1/missions", json={"mission_id": "m-audit"}, headers=auth(OP))
    c.post("/api/v1/missions/m-audit/stop", headers=auth(AG))  # refused, and recorded as an attempt
    c.get("/api/v1/missions/m-audit", headers=auth(OP))  # reading is not an action
    # a program acting with the operator token says so (fleet-sim's simulated operator), and the
    # audit log and the decision it made record it, not a person
    det = srv.store.add_detection(srv.fleet, "m-audit", "r1", 0, 1, "pending")
    sim = {**auth(OP), "X-Mures-Actor": "fleet-sim simulated operator"}
    assert c.post(f"/api/v1/detections/{det}/dismiss", headers=sim).json()["decided_by"] == (
        "operator (fleet-sim simulated operator)"
    )
    assert c.get("/api/v1/whoami", headers=sim).json()["role"] == "operator"
    c.post("/api/v1/missions/m-audit/stop", headers={**auth(OP), "X-Mures-Actor": "a\nforged line"})  # ignored
    log = srv.audit.read()
    assert [(e["who"], e["action"], e["status"]) for e in log] == [
        ("operator", "POST /api/v1/missions", 201),
        ("agent", "POST /api/v1/missions/m-audit/stop", 403),
        ("operator (fleet-sim simulated operator)", f"POST /api/v1/detections/{det}/dismiss", 200),
        ("operator", "POST /api/v1/missions/m-audit/stop", 200),
    ]
    assert all(e["client"] == "testclient" and e["ts"] > 0 for e in log)


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--http", "0.0.0.0:8000"], "--http 0.0.0.0 is reachable from the network"),
        (["--zenoh-listen", "tcp/0.0.0.0:7447"], "--zenoh-listen tcp/0.0.0.0:7447 is reachable"),
        (["--tls-cert", "c.pem"], "--tls-cert and --tls-key go together"),
    ],
)
def test_the_server_refuses_to_listen_beyond_loopback_unprotected(args, fragment):
    with pytest.raises(ValueError, match=None) as exc:
        check_exposure(build_parser().parse_args(["--env", "office", *args]))
    assert fragment in str(exc.value)
    if "--tls-cert" not in args:
        check_exposure(build_parser().parse_args(["--env", "office", *args, "--insecure"]))  # said explicitly
    check_exposure(build_parser().parse_args(["--env", "office", "--http", "127.0.0.1:8000"]))


def test_a_busy_robot_gets_no_second_mission_and_missions_time_out(api):
    srv, c = api
    srv.bus.online = {"r1": 1.0, "r2": 2.0, "r3": 3.0}
    m = c.post("/api/v1/missions", json={"robots": ["r1", "r2"], "mission_id": "m-a"}, headers=auth(OP)).json()
    assert m["deadline"] == pytest.approx(m["created"] + srv.mission_timeout, abs=5)
    r = c.post("/api/v1/missions", json={"robots": ["r2", "r3"]}, headers=auth(OP))
    assert r.status_code == 409 and "r2 (mission m-a)" in r.json()["error"] and "r3" not in r.json()["error"]
    published = len(srv.bus.published)
    assert c.post("/api/v1/missions", json={"robots": ["r3"], "mission_id": "m-b"}, headers=auth(OP)).status_code == 201
    _store_episode(srv, robot="r1", mission="m-a")  # r1 is done with m-a; r2 still flies it
    assert c.post("/api/v1/missions", json={"robots": ["r1"], "mission_id": "m-c"}, headers=auth(OP)).status_code == 201
    assert len(srv.bus.published) == published + 2
    # a mission asking for a short timeout ends when it passes; the robots are told to stop
    r = c.post("/api/v1/missions", json={"robots": ["r2"], "timeout_s": 0.05}, headers=auth(OP))
    assert r.status_code == 409  # r2 is still busy with m-a
    assert c.post("/api/v1/missions/m-a/stop", headers=auth(OP)).json()["status"] == "stopped"
    m = c.post("/api/v1/missions", json={"robots": ["r2"], "timeout_s": 0.05}, headers=auth(OP)).json()
    assert m["deadline"] - m["created"] < 1
    time.sleep(0.1)
    assert srv.expire_missions() == [m["id"]] and srv.expire_missions() == []
    assert srv.bus.published[-1] == {"type": "stop", "mission_id": m["id"], "reason": "timeout"}
    got = c.get(f"/api/v1/missions/{m['id']}", headers=auth(AG)).json()
    assert got["status"] == "timed-out" and got["event"]["reason"] == "timeout"
    # no longer than the server's own limit
    assert c.post("/api/v1/missions", json={"robots": ["r2"], "timeout_s": 0}, headers=auth(OP)).status_code == 422


def test_missions_listed_newest_first_and_paged(api):
    srv, c = api
    srv.bus.online = {f"r{k}": 1.0 for k in range(3)}
    ids = []
    for k in range(3):
        ids.append(c.post("/api/v1/missions", json={"robots": [f"r{k}"]}, headers=auth(OP)).json()["id"])
        time.sleep(0.01)
    page = c.get("/api/v1/missions?limit=2", headers=auth(AG)).json()
    assert [m["id"] for m in page["items"]] == ids[::-1][:2] and page["total"] == 3
    rest = c.get("/api/v1/missions?limit=2&offset=2", headers=auth(AG)).json()
    assert [m["id"] for m in rest["items"]] == ids[:1]
    assert c.get("/api/v1/missions?offset=-1", headers=auth(AG)).status_code == 422
    assert c.get("/api/v1/missions", headers=auth("nope")).status_code == 401


def test_one_refused_row_does_not_affect_the_others_in_its_batch(api):
    """A value the database cannot hold (validation keeps these out; here it is bypassed) is refused
    alone: the rest of the transaction is stored."""
    import json

    srv, _c = api
    rows = [("default", f"r{k}", "m1", 1, 2, False, None, json.dumps({"k": k}), None) for k in range(3)]
    rows[1] = ("default", "r1", "m1", 2**64, 2, False, None, "{}", None)
    assert srv.store.add_episodes(rows) == [True, None, True]
    assert srv.store.add_episodes(rows[:1]) == [False]
    assert {e["robot_id"] for e in srv.store.list_episodes("default", 10, 0, None, None)} == {"r0", "r2"}


def test_interrupted_runs_are_queued_again_or_stay_cancelled_and_leftovers_are_removed(api, tmp_path, database_url):
    srv, _c = api
    for run_id in ("a", "b", "c"):
        srv.store.add_run(run_id, {"episodes": 512})
    srv.store.update_run("b", status="running")
    srv.store.update_run("c", status="running")
    assert srv.store.request_cancel("c") == "running"  # cancelled, but the server died before the process stopped
    assert srv.store.request_cancel("nope") is None
    (srv.data_dir / "staging" / "run-x").mkdir()
    (srv.data_dir / "staging" / "run-x" / "weights.safetensors").write_bytes(b"partial")
    (srv.data_dir / "policies" / ".v2.tmp").mkdir()
    (srv.data_dir / "policies" / "v2").mkdir()  # copied, but its row never committed: never served
    srv.close()
    reopen = lambda: Server(  # noqa: E731
        srv.data_dir, srv.graph, "default", tmp_path / "op.token", tmp_path / "agent.token", database_url=database_url
    )
    (srv.data_dir / "policies" / "v7").mkdir()  # not the next version: another database's, so refuse
    with pytest.raises(ValueError, match=r"policy versions the database .* does not know \(v7\)"):
        reopen()
    assert (srv.data_dir / "policies" / "v2").is_dir()  # nothing deleted
    (srv.data_dir / "policies" / "v7").rmdir()
    srv2 = reopen()
    try:
        assert sorted(srv2.store.requeue_interrupted_runs()) == [("a", "queued"), ("b", "queued"), ("c", "cancelled")]
        assert srv2.store.get_run("c")["status"] == "cancelled" and srv2.store.get_run("b")["status"] == "queued"
        assert list((srv2.data_dir / "staging").iterdir()) == []
        assert sorted(d.name for d in (srv2.data_dir / "policies").iterdir()) == ["v1"]
        assert srv2.store.next_version() == 2 and srv2.current_version() == 1
    finally:
        srv2.close()


def test_fleet_shows_each_robot_online_or_not_flying_or_idle_and_its_last_state(api):
    srv, c = api
    srv.bus.online = {"r1": 1.0, "r2": 2.0}
    srv.bus.gone = {"r3": 3.0}
    m = c.post("/api/v1/missions", json={"robots": ["r1"], "mission_id": "m-f"}, headers=auth(OP)).json()
    srv.bus.live = {
        "r1": {
            "state": "mission",
            "mission_id": m["id"],
            "t": 7,
            "node": 43,
            "z": 1,
            "mode": "partial",
            "policy_version": 1,
            "backend": "sim",
            "down_reason": None,
            "last_failure": None,
            "revoked": None,
        },
        "r2": {"state": "idle", "node": 12, "policy_version": 1, "z": 1, "mode": "team"},
    }
    f = c.get("/api/v1/fleet", headers=auth(AG)).json()
    by = {a["robot_id"]: a for a in f["agents"]}
    assert f["online"] == 2 and list(by) == ["r1", "r2", "r3"]
    assert by["r1"] | {"since": 0, "last_seen": 0} == {
        "robot_id": "r1",
        "online": True,
        "since": 0,
        "last_seen": 0,
        "state": "flying",
        "mission_id": "m-f",
        "step": 7,
        "node": 43,
        "policy_version": 1,
        "z": 1,
        "mode": "partial",
        "backend": "sim",
        "speed": None,
        "down_reason": None,
        "last_failure": None,
        "revoked": None,
    }
    assert by["r2"]["state"] == "idle" and by["r2"]["node"] == 12 and by["r2"]["mission_id"] is None
    assert by["r2"]["z"] is None and by["r2"]["backend"] is None  # z only within the mission it flies
    assert by["r2"]["mode"] is None  # and how a step was decided too
    assert by["r3"]["state"] == "offline" and by["r3"]["online"] is False and by["r3"]["since"] is None


def test_a_mission_exported_as_mcap_reads_back(api):
    """The MCAP export read back with the mcap library: each robot's steps as recorded, its belief
    recomputed from its own record (the version's belief model), the map and the outcome."""
    import json

    from mcap.reader import make_reader

    from shared.core.belief_filter import BeliefFilter
    from shared.core.snapshot_format import read_snapshot

    srv, c = api
    srv.bus.online = {"r1": 1.0, "r2": 2.0}
    m = c.post("/api/v1/missions", json={"robots": ["r1", "r2"], "mission_id": "m-x"}, headers=auth(OP)).json()
    for r in ("r1", "r2"):
        _store_episode(srv, robot=r, mission="m-x")
    r = c.get("/api/v1/missions/m-x/export.mcap", headers=auth(AG))
    assert r.status_code == 200 and r.headers["content-type"] == "application/octet-stream"
    assert 'filename="m-x.mcap"' in r.headers["content-disposition"]
    reader = make_reader(io.BytesIO(r.content))
    got: dict[str, list] = {}
    for schema, channel, message in reader.iter_messages():
        assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
        got.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
    assert sorted(got) == ["/map", "/mission/outcome", "/robots/r1/belief", "/robots/r1/state",
                           "/robots/r2/belief", "/robots/r2/state"]  # fmt: skip
    assert got["/map"][0][1]["nodes"] == [int(v) for v in srv.graph.labels]
    rec = c.get("/api/v1/episodes/r1/m-x", headers=auth(AG)).json()
    assert [(s["t"], s["node"], s["z"]) for _, s in got["/robots/r1/state"]] == [
        (s["t"], s["node"], s["z"]) for s in rec["steps"]
    ]
    t0 = int(m["created"] * 1e9)
    assert [t for t, _ in got["/robots/r1/state"]] == [t0 + s["t"] * 1_000_000_000 for s in rec["steps"]]
    bf = BeliefFilter(srv.graph, read_snapshot(srv.snapshot_dir(1), srv.graph).model, Sensor())
    g = srv.graph
    want = [bf.reset(g.index[s["node"]], s["z"]).copy() if k == 0 else bf.update(g.index[s["node"]], s["z"]).copy()
            for k, s in enumerate(rec["steps"])]  # fmt: skip
    beliefs = [b["belief"] for _, b in got["/robots/r1/belief"]]
    assert np.allclose(beliefs, want, atol=1e-6) and all(abs(sum(b) - 1) < 1e-4 for b in beliefs)
    view = c.get("/api/v1/missions/m-x", headers=auth(AG)).json()
    assert got["/mission/outcome"][0][1] == {
        "mission_id": "m-x",
        "status": view["status"],
        "captured": True,
        "capture_time": 1,
        "captured_by": view["outcome"].get("captured_by"),  # the world's captured message names it
    }
    assert c.get("/api/v1/missions/nope/export.mcap", headers=auth(AG)).status_code == 404
    assert c.get("/api/v1/missions/m-x/export.mcap").status_code == 401


def test_ids_no_database_can_hold_are_not_found_not_server_errors(api):
    """PostgreSQL refuses NUL in text (Schemathesis found the 500 on GET /episodes): a filter that
    cannot be an id is 422, a path id that cannot exist is 404, on both backends."""
    _srv, c = api
    assert c.get("/api/v1/episodes?mission_id=a%00b", headers=auth(AG)).status_code == 422
    assert c.get("/api/v1/episodes?robot_id=%00", headers=auth(AG)).status_code == 422
    for path in (
        "/api/v1/missions/a%00b",
        "/api/v1/missions/a%00b/export.mcap",
        "/api/v1/episodes/r1/m%00",
        "/api/v1/training-runs/x%00",
    ):
        assert c.get(path, headers=auth(OP)).status_code == 404, path
    for path in ("/api/v1/training-runs/x%00/cancel", "/api/v1/missions/a%00b/stop"):
        assert c.post(path, headers=auth(OP)).status_code == 404, path


def test_the_api_docs_load_from_the_server_itself_not_a_cdn(api):
    """/docs and /redoc work on a site network with no way out: their scripts come from the server."""
    _srv, c = api
    for page in ("/docs", "/redoc"):
        html = c.get(page).text
        scripts = re.findall(r'(?:src|href)="([^"]+\.(?:js|css))"', html)
        assert scripts and all(s.startswith("/") for s in scripts), (page, scripts)
        for s in scripts:
            assert c.get(s).status_code == 200, s


def test_a_mission_that_ran_to_its_time_limit_counts_its_last_reading(api):
    """The robots stop at their first reading at or past max_seconds; the server ends the mission as
    "time limit", and it counts in trials and per-version figures: its last reading's seconds and
    its last step (a mission stopped early counts for nothing)."""
    import json

    srv, _c = api
    g = srv.graph
    params = {"max_steps": 100_000, "max_seconds": 60.0, "seed": 0,
              "canary": {"arm": "baseline", "pair": 0, "canary_version": 9}}  # fmt: skip
    srv.store.add_mission("t0", "default", ["r1", "r2"], params, 1)
    for robot, steps, last_s in (("r1", 7, 61.5), ("r2", 12, 60.0)):
        rec = make_record(g, fleet="default", mission_id="t0", robot_id=robot, nodes=[g.start] * steps,
                          z=[0] * steps, sensor=Sensor(), captured=False, capture_time=None, captured_by=None,
                          policy_version=1, times=np.linspace(0.0, last_s, steps))  # fmt: skip
        srv.store.add_episodes([("default", robot, "t0", 1, steps, False, None, json.dumps(rec), None)])
    srv.records_complete("t0")
    assert srv.store.get_mission("t0")["event"]["reason"] == "time limit"
    (outcome,) = srv.store.canary_outcomes("default", 9)
    assert srv.store.counted_seconds(outcome) == 61.5 and srv.store.counted_capture_time(outcome) == 11
    # a mission whose robots stopped before the limit (each its own end) is not at it
    srv.store.add_mission("t1", "default", ["r1"], {**params, "canary": None}, 1)
    rec = make_record(g, fleet="default", mission_id="t1", robot_id="r1", nodes=[g.start] * 3, z=[0] * 3,
                      sensor=Sensor(), captured=False, capture_time=None, captured_by=None, policy_version=1,
                      times=[0.0, 5.0, 9.0])  # fmt: skip
    srv.store.add_episodes([("default", "r1", "t1", 1, 3, False, None, json.dumps(rec), None)])
    srv.records_complete("t1")
    assert srv.store.get_mission("t1")["event"]["reason"] == "ended by the robots"


def test_a_trial_on_the_mission_clock_counts_seconds_and_one_in_steps_counts_steps(api):
    """A robot's step count on the clock is its own (a robot that stays reads once a second), so a
    trial whose missions all flew on the clock compares their capture times in seconds."""
    import json

    srv, _c = api
    g = srv.graph
    for mid, arm, pair, seconds in (("a0", "baseline", 0, 30.0), ("a1", "canary", 0, 80.0),
                                    ("b0", "baseline", 1, 40.0), ("b1", "canary", 1, 90.0)):  # fmt: skip
        params = {"max_steps": 50, "seed": pair, "canary": {"arm": arm, "pair": pair, "canary_version": 7}}
        srv.store.add_mission(mid, "default", ["r1"], params, 1)
        # on the clock the canary's robot stayed often: more seconds, yet fewer of its own steps
        steps = 3 if arm == "canary" else 9
        rec = make_record(g, fleet="default", mission_id=mid, robot_id="r1", nodes=[g.start] * steps,
                          z=[0] * (steps - 1) + [1], sensor=Sensor(), captured=True, capture_time=steps - 1,
                          captured_by="r1", policy_version=1, times=np.linspace(0.0, seconds, steps))  # fmt: skip
        srv.store.add_episodes([("default", "r1", mid, 1, steps, True, steps - 1, json.dumps(rec), None)])
        srv.store.mission_event(mid, {"type": "captured", "captured_by": "r1", "time_s": seconds}, "captured")
    outcomes = {o["mission_id"]: o for o in srv.store.canary_outcomes("default", 7)}
    assert {k: srv.store.counted_seconds(o) for k, o in outcomes.items()} == {"a0": 30.0, "a1": 80.0, "b0": 40.0,
                                                                             "b1": 90.0}  # fmt: skip
    assert {k: srv.store.counted_capture_time(o) for k, o in outcomes.items()} == {"a0": 8, "a1": 2, "b0": 8, "b1": 2}
    # the trial's decision: fewer steps but more seconds is worse, and rolled back
    srv.store.set_setting("canary", json.dumps({"version": 7, "baseline": 1, "run_id": None, "pairs": 2}))
    decision = srv.check_canary()
    assert decision["decision"] == "rolled back" and decision["unit"] == "seconds", decision
    assert decision["canary_mean"] == 85.0 and decision["baseline_mean"] == 35.0
    # the fleet's performance per version says the seconds of the missions on the clock
    perf = _c.get("/api/v1/policies/performance", headers=auth(AG)).json()["items"]
    v1 = next(p for p in perf if p["version"] == 1)
    assert v1["missions_on_clock"] == 4 and v1["mean_capture_time_s"] == 60.0 and v1["mean_capture_time"] == 5.0

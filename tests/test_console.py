"""The operator console's server side, in-process (the API fixture of tests/test_api.py, on each
database backend): the pages, who a token is, the event stream, the replay, the capture time per
version, the estimated target model, the alerts and the map layout. The browser tests are in
tests/test_console_browser.py."""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
from test_api import AG, OP, api, auth  # noqa: F401 - api: the fixture (the in-process API)

from shared.core.belief_filter import BeliefFilter
from shared.core.graph import builtin_graph, graph_from_dict
from shared.core.models import Sensor, uniform_walk
from shared.core.records import make_record
from shared.core.snapshot_format import read_snapshot
from shared.engine.evaluate import mean_ci95
from training_server.api.policies import stationary
from training_server.console import PAGES
from training_server.console.hub import Hub
from training_server.console.layout import node_layout
from training_server.jobs import TrainingParams


def _mission(srv, mid, robots, version=1, status_event=None, records=None, max_steps=30, seed=0):
    """A mission of ``robots`` flown with ``version`` and its records: {robot: (nodes, z, capture_time)}."""
    g = srv.graph
    srv.store.add_mission(mid, "default", robots, {"seed": seed, "max_steps": max_steps, "start_node": 43}, version)
    rows = []
    for robot, (nodes, z, ct) in (records or {}).items():
        rec = make_record(
            g,
            fleet="default",
            mission_id=mid,
            robot_id=robot,
            nodes=[g.index[v] for v in nodes],
            z=z,
            sensor=Sensor(),
            captured=ct is not None,
            capture_time=ct,
            captured_by=robot if ct is not None else None,
            policy_version=version,
        )
        rows.append(("default", robot, mid, version, len(nodes), ct is not None, ct, json.dumps(rec), None))
    srv.store.add_episodes(rows)
    if status_event is not None:
        srv.store.mission_event(mid, status_event, "captured" if status_event["type"] == "captured" else "stopped")


def _events(text: str) -> dict[str, list]:
    out: dict[str, list] = {}
    for block in text.split("\n\n"):
        lines = block.split("\n")
        ev = next((ln[7:] for ln in lines if ln.startswith("event: ")), None)
        data = [ln[6:] for ln in lines if ln.startswith("data: ")]
        if ev and data:
            out.setdefault(ev, []).append(json.loads("\n".join(data)))
    return out


def test_pages_are_served_without_data_and_with_a_strict_policy(api):
    _srv, c = api
    for path in [*PAGES, "/missions/m-1"]:
        r = c.get(path)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html"), path
        csp = r.headers["content-security-policy"]
        assert "script-src 'self'" in csp and "frame-ancestors 'none'" in csp
        assert "<script>" not in r.text  # no inline script: the policy would block it
        assert OP not in r.text and AG not in r.text
    assert '<label for="token">Token</label>' in c.get("/signin").text
    defaults = TrainingParams()
    assert f'id="run-episodes" type="number" min="256" step="1" value="{defaults.episodes}"' in c.get("/training").text
    assert 'data-mission-id="m-1"' in c.get("/missions/m-1").text
    assert "&lt;x&gt;" in c.get("/missions/%3Cx%3E").text  # escaped, not markup
    js = c.get("/console/static/console.js")
    assert js.status_code == 200 and "openStream" in js.text
    assert c.get("/console/static/nope.js").status_code == 404
    assert all(p not in c.get("/openapi.json").json()["paths"] for p in PAGES)  # pages are not API


def test_whoami_tells_the_role(api):
    _srv, c = api
    assert c.get("/api/v1/whoami", headers=auth(OP)).json() == {"role": "operator", "who": "operator"}
    assert c.get("/api/v1/whoami", headers=auth(AG)).json() == {"role": "agent", "who": "agent"}
    assert c.get("/api/v1/whoami", headers=auth("wrong")).status_code == 401
    assert c.get("/api/v1/whoami").status_code == 401


def test_event_stream_sends_fleet_belief_and_status(api):
    srv, c = api
    n = srv.graph.n
    belief = [round(1.0 / n, 4)] * n
    srv.bus.online["r1"] = time.time()
    srv.bus.gone["r2"] = time.time() - 30
    srv.store.add_mission("m-live", "default", ["r1"], {"seed": 1, "max_steps": 5, "start_node": 43}, 1)
    srv.bus.live["r1"] = {"state": "mission", "mission_id": "m-live", "t": 3, "node": 44, "z": 1, "belief": belief}
    srv.bus.truth["m-live"] = {"t": 3, "target": 23, "robots": {"r1": {"node": 44, "z": 1, "seen": False}}}
    assert c.get("/api/v1/events?once=true").status_code == 401
    r = c.get("/api/v1/events?once=true&belief=r1", headers=auth(AG))
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/event-stream")
    ev = _events(r.text)
    fleet = ev["fleet"][0]
    a = {x["robot_id"]: x for x in fleet["agents"]}
    assert a["r1"]["state"] == "flying" and a["r1"]["step"] == 3 and a["r1"]["z"] == 1 and a["r1"]["node"] == 44
    assert a["r2"]["online"] is False and a["r2"]["state"] == "offline"
    assert fleet["truth"] == {"m-live": srv.bus.truth["m-live"]}
    assert ev["belief"] == [{"robot_id": "r1", "mission_id": "m-live", "t": 3, "belief": belief}]
    status = ev["status"][0]
    assert status["running_missions"] == ["m-live"] and status["current_policy"] == 1
    assert [x["kind"] for x in status["alerts"]] == ["robot-lost"] and "r2" in status["alerts"][0]["text"]
    assert c.get("/api/v1/events?once=true&belief=bad%20id", headers=auth(AG)).status_code == 422


def test_replay_recomputes_each_robots_belief_from_its_own_record(api):
    srv, c = api
    g = srv.graph
    recs = {"r1": ([43, 44, 23, 22], [0, 0, 1, 0], None), "r2": ([43, 50, 53], [0, 1, 1], 2)}
    _mission(srv, "m-r", ["r1", "r2"], records=recs, status_event={"type": "captured", "mission_id": "m-r", "t": 2})
    r = c.get("/api/v1/missions/m-r/replay", headers=auth(AG))
    assert r.status_code == 200
    body = r.json()
    assert body["nodes"] == [int(v) for v in g.labels] and body["mission"]["status"] == "completed"
    snap = read_snapshot(srv.snapshot_dir(1), g)
    for robot, (nodes, z, _ct) in recs.items():
        rep = body["robots"][robot]
        assert [s["node"] for s in rep["steps"]] == nodes and [s["z"] for s in rep["steps"]] == z
        bf = BeliefFilter(g, snap.model, Sensor())
        for k, (v, zk) in enumerate(zip(nodes, z, strict=True)):
            want = bf.reset(g.index[v], zk) if k == 0 else bf.update(g.index[v], zk)
            np.testing.assert_allclose(rep["belief"][k], want, atol=1e-4)
    assert c.get("/api/v1/missions/nope/replay", headers=auth(AG)).status_code == 404


def test_capture_time_per_version_counts_captures_and_step_limits_only(api):
    srv, c = api
    srv.ensure_initial_policy(2, None, Sensor(), seed=0)  # no-op: version 1 exists
    cts = [4, 9, 2]
    for i, ct in enumerate(cts):
        ev = {"type": "captured", "mission_id": f"m{i}", "t": ct}
        _mission(srv, f"m{i}", ["r1"], records={"r1": ([43] * (ct + 1), [0] * ct + [1], ct)}, status_event=ev)
    limit = {"type": "stop", "mission_id": "m-limit", "reason": "step limit"}
    _mission(srv, "m-limit", ["r1"], records={"r1": ([43] * 31, [0] * 31, None)}, status_event=limit)
    stop = {"type": "stop", "mission_id": "m-op", "reason": "operator"}
    _mission(srv, "m-op", ["r1"], records={"r1": ([43] * 3, [0] * 3, None)}, status_event=stop)
    body = c.get("/api/v1/policies/performance", headers=auth(AG)).json()
    mean, half = mean_ci95([*cts, 30])
    assert body["excluded"] == 1
    assert body["items"] == [
        {"version": 1, "missions": 4, "captured": 3, "mean_capture_time": round(mean, 4), "ci95": round(half, 4)}
    ]


def test_target_model_of_a_version(api):
    srv, c = api
    body = c.get("/api/v1/policies/1/model", headers=auth(AG)).json()
    model = read_snapshot(srv.snapshot_dir(1), srv.graph).model
    np.testing.assert_allclose(body["b0"], model.b0, atol=1e-6)
    gamma = model.dense()
    for u, row in body["moves"].items():
        assert math.isclose(sum(row.values()), 1.0, abs_tol=1e-5)
        for v, p in row.items():
            assert math.isclose(p, gamma[srv.graph.index[int(u)], srv.graph.index[int(v)]], abs_tol=1e-6)
    np.testing.assert_allclose(body["stationary"], stationary(gamma), atol=1e-6)
    assert c.get("/api/v1/policies/9/model", headers=auth(AG)).status_code == 404


def test_stationary_distribution_is_a_fixed_point():
    g = builtin_graph("office")
    gamma = uniform_walk(g).dense()
    pi = stationary(gamma)
    np.testing.assert_allclose(gamma.T @ pi, pi, atol=1e-9)
    assert math.isclose(pi.sum(), 1.0) and pi.min() > 0
    deg = g.deg_closed / g.deg_closed.sum()  # a uniform walk on the closed neighbourhoods: pi ~ |N[p]|
    np.testing.assert_allclose(pi, deg, atol=1e-6)


def test_alerts_for_lost_robots_failed_or_gated_runs_and_rising_rejections(api, monkeypatch):
    srv, c = api
    monkeypatch.setattr("training_server.console.hub.STATUS_EVERY", 0.0)
    assert c.get("/api/v1/alerts", headers=auth(AG)).json() == {"items": []}
    srv.bus.gone["r9"] = time.time() - 12
    for rid, err in (
        ("run-a", "training process died (exit code 9)"),
        ("run-b", "evaluation gate: new 9.1, current 8.0"),
    ):
        srv.store.add_run(rid, {})
        srv.store.update_run(rid, status="failed", finished=time.time(), error=err)
    srv.store.reject(["json", "json", "graph"])
    items = c.get("/api/v1/alerts", headers=auth(AG)).json()["items"]
    kinds = {a["kind"]: a for a in items}
    assert set(kinds) == {"robot-lost", "run-failed", "run-gated-out", "ingest-rejections"}
    assert kinds["robot-lost"]["subject"] == "r9" and kinds["run-gated-out"]["subject"] == "run-b"
    assert kinds["ingest-rejections"]["text"].startswith("3 episode records rejected")
    assert c.get("/api/v1/alerts").status_code == 401


def test_rejection_alert_needs_new_rejections(api, monkeypatch):
    srv, _c = api
    monkeypatch.setattr("training_server.console.hub.STATUS_EVERY", 0.0)
    srv.store.reject(["json"])  # before anyone watched: old news, no alert
    hub = Hub(srv)
    assert hub.alerts() == []
    assert hub.alerts() == []  # nothing new since


def test_layout_uses_file_positions_or_lays_out_every_node_apart():
    g = builtin_graph("office")
    pos, source = node_layout(g)
    assert source == "automatic" and set(pos) == {int(v) for v in g.labels}
    xy = np.array(list(pos.values()))
    assert xy.min() >= 0 and xy.max() <= 1
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(len(xy))
    assert d.min() > 0.005  # no two rooms drawn on top of each other
    assert node_layout(g) == (pos, source)  # the same picture every time
    edge_len = np.array([np.linalg.norm(xy[u] - xy[v]) for u, v in g.edges])
    assert np.median(edge_len) < np.median(d)  # neighbours drawn nearer than most pairs
    data = {"name": "t", "start_node": 1, "nodes": [1, 2, 3], "edges": [[1, 2], [2, 3]]}
    data["positions"] = {"1": [0, 0], "2": [10, 0], "3": [10, 5]}
    pos, source = node_layout(graph_from_dict(data))
    assert source == "file" and pos == {1: (0.0, 0.5), 2: (1.0, 0.5), 3: (1.0, 0.0)}


def test_event_stream_ends_when_the_server_stops(api):
    srv, c = api
    srv.is_stopping = lambda: True
    r = c.get("/api/v1/events", headers=auth(AG))  # no once: returns only because the server stops
    assert r.status_code == 200 and r.text.startswith("retry:")


@pytest.mark.parametrize("bad", ["/api/v1/policies/0/model", "/api/v1/policies/x/model"])
def test_bad_model_versions_are_422(api, bad):
    _srv, c = api
    assert c.get(bad, headers=auth(AG)).status_code == 422


def test_status_lists_the_ten_newest_runs_newest_first(api):
    srv, c = api
    for k in range(12):
        srv.store.add_run(f"run-{k:02d}", {})
        time.sleep(0.002)  # distinct creation times
    status = _events(c.get("/api/v1/events?once=true", headers=auth(AG)).text)["status"][0]
    assert [r["id"] for r in status["runs"]] == [f"run-{k:02d}" for k in range(11, 1, -1)]

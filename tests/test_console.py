"""The operator console's server side, in-process (the API fixture of tests/test_api.py, on each
database backend): the pages, who a token is, the event stream, the replay, the capture time per
version, the estimated target model, the alerts and the map layout. The browser tests are in
tests/test_console_browser.py."""

from __future__ import annotations

import json
import time

import numpy as np
from test_api import AG, OP, api, auth  # noqa: F401 - api: the fixture (the in-process API)

from shared.core.belief_filter import BeliefFilter
from shared.core.models import Sensor
from shared.core.records import make_record
from shared.core.snapshot_format import read_snapshot
from shared.core.team import CollectiveBelief
from training_server.bus import live_state
from training_server.console import PAGES
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
    defaults, training = TrainingParams(), c.get("/training").text
    assert (
        f'id="run-budget" type="number" min="0.001" max="1" step="any" value="{defaults.budget_fraction}"' in training
    )
    assert '<option value="cepg" selected>' in training and '<option value="best">' in training
    for method in ("pg", "maddpg", "masac", "facmac", "mambpo", "mappo"):  # every method, and best's candidates
        assert f'<option value="{method}">' in training and f'<input type="checkbox" value="{method}"' in training
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
    team = [0.0] * n
    team[g_row := srv.graph.index[23]] = 1.0
    srv.bus.live["r1"] = {"state": "mission", "mission_id": "m-live", "t": 3, "node": 44, "z": 1, "belief": belief}
    srv.bus.live["r1"]["team_belief"] = team
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
    assert ev["belief"] == [{"robot_id": "r1", "mission_id": "m-live", "t": 3, "belief": belief, "team_belief": team}]
    assert ev["belief"][0]["team_belief"][g_row] == 1.0
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
    # the team's collective belief: both records' observations of each step fused (Eq. 6-7); r2's
    # record ends at step 2, so step 3 holds r1's observation alone
    collective = CollectiveBelief(g, snap.model, Sensor(), ["r1", "r2"])
    for robot, (nodes, z, _ct) in recs.items():
        for k, (v, zk) in enumerate(zip(nodes, z, strict=True)):
            collective.add(k, robot, g.index[v], zk)
    assert len(body["team_belief"]) == 4
    for k in range(4):
        np.testing.assert_allclose(body["team_belief"][k], collective.belief(k), atol=1e-4)
    _mission(srv, "m-one", ["r1"], records={"r1": ([43, 44], [0, 0], None)})
    assert c.get("/api/v1/missions/m-one/replay", headers=auth(AG)).json()["team_belief"] is None
    assert c.get("/api/v1/missions/nope/replay", headers=auth(AG)).status_code == 404


def test_the_server_keeps_a_robots_beliefs_only_when_they_are_n_probabilities():
    n = 5
    good = [0.2] * n
    for team, kept in ((good, True), (good[:-1], False), ([*good[:-1], "x"], False), ([*good[:-1], 1.5], False)):
        msg = {"state": "mission", "mission_id": "m", "t": 1, "node": 3, "belief": good, "team_belief": team}
        live = live_state(msg, n)
        assert live is not None and live["belief"] == good and ("team_belief" in live) is kept
    assert live_state({"state": "flying"}, n) is None and live_state(None, n) is None
    # a robot on the mission clock says its speed; one that is not a positive number is not kept
    for speed, kept in ((0.5, True), (0, False), (-1.0, False), ("0.5", False), (True, False), (float("inf"), False)):
        live = live_state({"state": "idle", "clock": "seconds", "speed": speed}, n)
        assert live is not None and (live.get("speed") == speed and live.get("clock") == "seconds") is kept
        assert kept or ("speed" not in live and "clock" not in live)


def test_the_automatic_layout_draws_no_node_over_another():
    """The built-in maps have no positions: their force-directed layout keeps every two nodes at
    least two of the console's node radii apart, so neither nodes nor their labels overlap."""
    from shared.core.graph import builtin_graph
    from training_server.console.layout import node_layout, node_radius

    for name in ("office", "museum", "ward"):
        graph = builtin_graph(name)
        layout = node_layout(graph)
        xy = np.array([layout.positions[int(v)] for v in graph.labels])
        dist = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(graph.n) * 9
        assert layout.source == "automatic" and dist.min() >= 2 * node_radius(graph.n), name
        assert xy.min() >= 0 and xy.max() <= 1 and node_layout(graph) == layout  # the same picture every time


def test_an_imported_maps_picture_lies_under_its_graph(tmp_path):
    """`training-server --map-image`: GET /api/v1/map/layout places the map's picture so that each
    node, drawn at its map-frame position, lies on its own pixel of the picture; a map that is not
    the graph's is refused in one line."""
    from types import SimpleNamespace

    import pytest
    from PIL import Image

    from shared.core.graph import graph_from_dict
    from shared.floorplan.graph_file import graph_dict, map_picture
    from shared.floorplan.occupancy import MapError, read_map
    from shared.floorplan.rooms import segment
    from training_server.api.maps import map_image, map_layout

    floor = np.full((80, 120), 0, dtype=np.uint8)
    floor[5:75, 5:55] = 254  # two halls joined by a door
    floor[5:75, 60:115] = 254
    floor[35:45, 55:60] = 254
    Image.fromarray(floor).save(tmp_path / "m.pgm")
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: 0.1\norigin: [-3.0, 2.0, 0.0]\n")
    grid = read_map(tmp_path / "m.yaml")
    data = graph_dict(grid, segment(grid, max_region_m=3.0), "M", {})
    graph = graph_from_dict(data)
    srv = SimpleNamespace(graph=graph, map_picture=map_picture(tmp_path / "m.yaml", data["source"]))
    layout = map_layout(srv)
    img = layout.image
    assert img is not None and img.url == "/api/v1/map/image"
    h, w = floor.shape
    for label, (x, y) in layout.positions.items():
        col = (x - img.x) / img.width * w
        row = (y - img.y) / img.height * h
        assert floor[int(row), int(col)] == 254, label  # on the free space it was placed on
        assert (int(row), int(col)) == tuple(int(v) for v in grid.to_pixel(*data["positions"][label]))
    png = map_image(srv)
    assert png.media_type == "image/png" and png.body.startswith(b"\x89PNG")
    floor[40, 40] = 0  # another image: refused
    Image.fromarray(floor).save(tmp_path / "m.pgm")
    with pytest.raises(MapError, match="not the one this graph was imported from"):
        map_picture(tmp_path / "m.yaml", data["source"])

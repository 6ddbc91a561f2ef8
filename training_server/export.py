"""A finished (or running) mission as an MCAP file (https://mcap.dev), the format Foxglove and the
ROS tools open: GET /api/v1/missions/{id}/export.mcap.

Topics (JSON messages, each with a JSON Schema):
  /map                      once, at the mission's start: nodes, edges, positions (when the map has them)
  /robots/<id>/state        per step t: node, z (the robot's observation), x and y when known
  /robots/<id>/belief       per step t: the robot's own belief b_t over the map's nodes (in the map's
                            node order), recomputed from its own record alone with the belief model
                            and sensor of the policy version it flew (Eq. 1, shared.core.belief_filter)
  /mission/outcome          once, after the last step: status, captured, capture_time, captured_by
Records carry steps, not clock times: a step t is stamped mission start + t seconds.
"""

from __future__ import annotations

import io
import json
from typing import Any

from shared.core.belief_filter import BeliefFilter
from shared.core.models import Sensor
from shared.core.snapshot_format import SnapshotError, read_snapshot
from shared.core.team import CollectiveBelief

STEP_NS = 1_000_000_000  # one step shown as one second

_SCHEMAS = {
    "mures.Map": {
        "type": "object",
        "properties": {
            "name": {"type": "string"},
            "nodes": {"type": "array", "items": {"type": "integer"}},
            "edges": {"type": "array", "items": {"type": "array", "items": {"type": "integer"}}},
            "positions": {"type": "object"},
        },
    },
    "mures.RobotState": {
        "type": "object",
        "properties": {
            "robot_id": {"type": "string"},
            "t": {"type": "integer"},
            "node": {"type": "integer"},
            "z": {"type": "integer"},
            "x": {"type": "number"},
            "y": {"type": "number"},
        },
    },
    "mures.Belief": {
        "type": "object",
        "properties": {
            "robot_id": {"type": "string"},
            "t": {"type": "integer"},
            "nodes": {"type": "array", "items": {"type": "integer"}},
            "belief": {"type": "array", "items": {"type": "number"}},
        },
    },
    "mures.Outcome": {
        "type": "object",
        "properties": {
            "mission_id": {"type": "string"},
            "status": {"type": "string"},
            "captured": {"type": "boolean"},
            "capture_time": {"type": ["integer", "null"]},
            "captured_by": {"type": ["string", "null"]},
        },
    },
}


def mission_mcap(srv: Any, mission: Any, records: dict[str, dict[str, Any]]) -> bytes:
    """The MCAP bytes of ``mission`` (the API's Mission view) from its robots' stored ``records``."""
    from mcap.writer import Writer

    g = srv.graph
    t0 = int(mission.created * 1e9)
    messages: list[tuple[int, str, str, dict[str, Any]]] = []  # (log time, topic, schema, message)
    pos = {int(g.labels[k]): xy for k, xy in g.positions.items()}
    messages.append((t0, "/map", "mures.Map", g.to_json()))
    snaps: dict[int, Any] = {}
    for robot, rec in sorted(records.items()):
        steps = rec["steps"]
        for st in steps:
            state = {"robot_id": robot, "t": st["t"], "node": st["node"], "z": st["z"]}
            if st["node"] in pos:
                state["x"], state["y"] = pos[st["node"]]
            messages.append((t0 + st["t"] * STEP_NS, f"/robots/{robot}/state", "mures.RobotState", state))
        beliefs = recomputed_beliefs(srv, rec, snaps)
        if beliefs is None:
            continue
        for k, (st, b) in enumerate(zip(steps, beliefs, strict=True)):
            belief = {"robot_id": robot, "t": st["t"], "belief": [round(float(x), 6) for x in b]}
            if k == 0:
                belief["nodes"] = [int(v) for v in g.labels]
            messages.append((t0 + st["t"] * STEP_NS, f"/robots/{robot}/belief", "mures.Belief", belief))
    last = max((st["t"] for rec in records.values() for st in rec["steps"]), default=0)
    out = mission.outcome or {}
    messages.append(
        (
            t0 + last * STEP_NS,
            "/mission/outcome",
            "mures.Outcome",
            {
                "mission_id": mission.id,
                "status": mission.status,
                "captured": bool(out.get("captured", False)),
                "capture_time": out.get("capture_time"),
                "captured_by": out.get("captured_by"),
            },
        )
    )
    buf = io.BytesIO()
    w = Writer(buf)
    w.start(profile="", library="mures-fleet")
    schema_ids = {
        name: w.register_schema(name=name, encoding="jsonschema", data=json.dumps(s).encode())
        for name, s in _SCHEMAS.items()
    }
    channels: dict[str, int] = {}
    seq: dict[str, int] = {}
    for log_time, topic, schema, msg in sorted(messages, key=lambda m: (m[0], m[1])):
        if topic not in channels:
            channels[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=schema_ids[schema])
        seq[topic] = seq.get(topic, -1) + 1
        w.add_message(
            channels[topic],
            log_time=log_time,
            data=json.dumps(msg).encode(),
            publish_time=log_time,
            sequence=seq[topic],
        )
    w.finish()
    return buf.getvalue()


def recomputed_beliefs(srv: Any, rec: dict[str, Any], cache: dict[int, Any]) -> list[Any] | None:
    """The robot's belief b_t (an (n,) array in the map's row order) after each step of its record,
    from that record alone (Eq. 1); None when the policy version it flew is not on this server."""
    bf = _belief_filter(srv, rec, cache)
    if bf is None:
        return None
    out = []
    for k, st in enumerate(rec["steps"]):
        p = srv.graph.index[st["node"]]
        out.append(bf.reset(p, st["z"]) if k == 0 else bf.update(p, st["z"]))
    return out


def recomputed_team_belief(srv: Any, records: dict[str, dict[str, Any]], cache: dict[int, Any]) -> list[Any] | None:
    """The team's collective belief b^c_t (an (n,) array in the map's row order) after each step of
    a mission, from every robot's record (Eq. 6-7: all the team's observations of a step fused, as
    a robot whose links delivered them all held it), with the belief model of the version the
    first record flew; None for fewer than two records or when that version is gone."""
    if len(records) < 2:
        return None
    first = records[min(records)]
    version = first.get("policy_version")
    snap = _snapshot(srv, version, cache) if version is not None else None
    if snap is None:
        return None
    collective = CollectiveBelief(srv.graph, snap.model, Sensor(**first["sensor"]), sorted(records))
    for robot, rec in records.items():
        for t, st in enumerate(rec["steps"]):
            collective.add(t, robot, srv.graph.index[st["node"]], st["z"])
    return [collective.belief(t) for t in range(max(len(r["steps"]) for r in records.values()))]


def _snapshot(srv: Any, version: int, cache: dict[int, Any]) -> Any:
    """The policy version's snapshot (None when it is not on this server any more), read once."""
    if version not in cache:
        try:
            cache[version] = read_snapshot(srv.snapshot_dir(version), srv.graph)
        except (OSError, SnapshotError, ValueError):
            cache[version] = None
    return cache[version]


def _belief_filter(srv: Any, rec: dict[str, Any], cache: dict[int, Any]) -> BeliefFilter | None:
    """The robot's own belief filter: the belief model of the policy version it flew, its sensor;
    None when that version is not on this server any more."""
    version = rec.get("policy_version")
    snap = _snapshot(srv, version, cache) if version is not None else None
    if snap is None:
        return None
    return BeliefFilter(srv.graph, snap.model, Sensor(**rec["sensor"]))

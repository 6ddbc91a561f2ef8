"""Hypothesis strategies for episode records (docs/SPEC.md section 5) sent to a server over Zenoh:
valid ones, and valid ones broken by one mutation whose rejection reason is known in advance.

``sendings(graph, fleet)`` draws a ``Sending``: the Zenoh key's robot and mission, the payload
bytes, and ``reason``, None for a record the server must store (or call a duplicate), else the
reason code it must reject it with. The mutations are chosen so that each breaks exactly the rule
its reason names, and breaks it before any other check (parse_record's order).
"""

from __future__ import annotations

import json
import string
from dataclasses import dataclass
from typing import Any

from hypothesis import strategies as st

from shared.core.graph import Graph
from shared.core.records import MAX_INT, SCHEMA

ID_CHARS = string.ascii_letters + string.digits + "_.-"
# robots from a small alphabet, missions from a larger one: most keys are new, and some come up
# again, so resends (duplicates) are tried too
ids = st.text(alphabet="abc", min_size=1, max_size=3)
mission_ids = st.text(alphabet=string.ascii_lowercase, min_size=1, max_size=4) | st.integers(0, 2**48).map(
    lambda k: f"{k:x}"
)


@dataclass(frozen=True)
class Sending:
    robot: str
    mission: str
    payload: bytes
    reason: str | None  # None: valid

    @property
    def valid(self) -> bool:
        return self.reason is None


@st.composite
def valid_records(draw: Any, graph: Graph, fleet: str) -> dict[str, Any]:
    """A record that parse_record accepts: a walk on the graph (stay or follow an edge), z in {0, 1},
    an outcome consistent with the steps, sometimes a field the schema does not know."""
    T = draw(st.integers(0, 40))
    p = draw(st.integers(0, graph.n - 1))
    nodes = [p]
    for _ in range(T):
        nbrs = [int(v) for v in graph.closed(nodes[-1])]
        nodes.append(draw(st.sampled_from(nbrs)))
    captured = draw(st.booleans())
    eta_fn = draw(st.sampled_from([0.0, 0.1, 0.3, 0.5]))
    eta_fp = draw(st.sampled_from([0.0, 0.1, 0.3] + ([] if eta_fn == 0.5 else [0.5])))
    rec: dict[str, Any] = {
        "schema": SCHEMA,
        "fleet": fleet,
        "mission_id": "m-" + draw(mission_ids),
        "robot_id": "r-" + draw(ids),
        "graph_id": graph.graph_id,
        "policy_version": draw(st.none() | st.integers(0, MAX_INT)),
        "sensor": {"eta_fn": eta_fn, "eta_fp": eta_fp, "detection": "node"},
        "steps": [{"t": t, "node": int(graph.labels[v]), "z": draw(st.integers(0, 1))} for t, v in enumerate(nodes)],
        "outcome": {
            "captured": captured,
            "capture_time": draw(st.integers(0, T)) if captured else None,
            "captured_by": draw(st.none() | st.text(alphabet=ID_CHARS, min_size=1, max_size=8)) if captured else None,
        },
    }
    if draw(st.booleans()):
        rec["x-extra"] = draw(st.integers() | st.text(max_size=5))  # unknown fields are dropped, not refused
    return rec


def _bad_ints() -> st.SearchStrategy[Any]:
    return st.sampled_from([-1, 2**63, 2**64, True, 1.5, "1"])


@st.composite
def mutated(draw: Any, rec: dict[str, Any], graph: Graph) -> tuple[Any, str]:
    """(a broken copy of ``rec``, the reason code the server must give)."""
    rec = json.loads(json.dumps(rec))
    steps = rec["steps"]
    kind = draw(
        st.sampled_from(
            [
                "not-object",
                "schema",
                "missing",
                "fleet",
                "bad-id",
                "graph_id",
                "policy_version",
                "sensor",
                "no-steps",
                "t",
                "node",
                "z",
                "move",
                "outcome",
            ]
        )
    )
    if kind == "not-object":
        return draw(st.lists(st.integers(), max_size=3) | st.integers() | st.text(max_size=5) | st.none()), kind
    if kind == "schema":
        rec["schema"] = draw(st.sampled_from(["mures.episode/2", "", None, 1]))
        return rec, "schema"
    if kind == "missing":
        del rec[draw(st.sampled_from(["fleet", "mission_id", "robot_id", "graph_id", "sensor", "steps", "outcome"]))]
        return rec, "missing-field"
    if kind == "fleet":
        rec["fleet"] = "other-" + draw(ids)
        return rec, "fleet"
    if kind == "bad-id":
        rec["robot_id"] = draw(st.sampled_from(["", "a b", "r/1", "x" * 129, "é"]))
        return rec, "bad-id"
    if kind == "graph_id":
        rec["graph_id"] = "sha256:" + "0" * 64
        return rec, "graph_id"
    if kind == "policy_version":
        rec["policy_version"] = draw(_bad_ints())
        return rec, "bad-field"
    if kind == "sensor":
        rec["sensor"][draw(st.sampled_from(["eta_fn", "eta_fp"]))] = draw(st.sampled_from([-0.1, 0.75, 2.0, "x"]))
        return rec, "sensor"
    if kind == "no-steps":
        rec["steps"] = []
        return rec, "steps"
    k = draw(st.integers(0, len(steps) - 1))
    if kind == "t":
        steps[k]["t"] = draw(st.sampled_from([k + 1, -1, None, str(k), True]))
        return rec, "t-sequence"
    if kind == "node":
        steps[k]["node"] = draw(st.sampled_from([10**9, -5, "a", None, True, 1.5]))
        return rec, "node"
    if kind == "z":
        steps[k]["z"] = draw(st.sampled_from([2, -1, True, "1", 0.5, None]))
        return rec, "z"
    if kind == "move":
        u = graph.index[steps[-1]["node"]]
        far = [int(graph.labels[v]) for v in range(graph.n) if v not in set(int(x) for x in graph.closed(u))]
        steps.append({"t": len(steps), "node": draw(st.sampled_from(far)), "z": 0})
        return rec, "move"
    # outcome
    rec["outcome"] = draw(
        st.sampled_from(
            [
                {"captured": "yes"},
                {"captured": 1},
                {"captured": True, "capture_time": len(steps)},
                {"captured": True, "capture_time": -1},
                {"captured": True, "capture_time": None},
                {"captured": True, "capture_time": 0, "captured_by": "a b"},
            ]
        )
    )
    return rec, "outcome"


@st.composite
def sendings(draw: Any, graph: Graph, fleet: str) -> Sending:
    rec = draw(valid_records(graph, fleet))
    robot, mission = rec["robot_id"], rec["mission_id"]
    what = draw(st.sampled_from(["valid", "valid", "mutated", "bytes", "key"]))
    if what == "valid":
        return Sending(robot, mission, json.dumps(rec).encode(), None)
    if what == "bytes":  # not JSON at all: cut short, or arbitrary bytes
        raw = json.dumps(rec).encode()
        payload = draw(st.sampled_from([raw[: len(raw) // 2], b"\xff\xfe" + raw, b"{", b"nul"]))
        return Sending(robot, mission, payload, "json")
    if what == "key":  # a valid record on another robot's key
        return Sending(robot + "x", mission, json.dumps(rec).encode(), "key")
    bad, reason = draw(mutated(rec, graph))
    return Sending(robot, mission, json.dumps(bad).encode(), reason)

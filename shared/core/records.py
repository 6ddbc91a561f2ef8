"""Episode records (docs/SPEC.md section 5): validation, parsing and writing.

A record is what one robot reports after one mission. ``parse_record`` checks everything a
receiver must check (schema, fleet, graph_id, sensor bounds, the t sequence, moves that stay or
follow an edge, z values, sizes, the outcome) and raises ``RecordError`` whose ``reason`` is a
short stable code (for counting rejections) and whose message says what is wrong and where.
"""

from __future__ import annotations

import json
import numbers
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np

from shared.core.choices import DETECTIONS, TEAM_SEARCHERS
from shared.core.graph import Graph
from shared.core.models import ModelError, Sensor

SCHEMA = "mures.episode/1"
MAX_STEPS = 100_000
MAX_MISSION_ROBOTS = 256  # robots in one mission at most (the missions API's limit)
MAX_INT = 2**63 - 1  # integers must fit the database's 64 bits
MAX_RECORD_BYTES = 16 * 1024 * 1024
SET_ASIDE_REASONS = ("impossible",)  # the codes that start a set-aside record's "<code>: <why>" (unexplained)
ID_RE = re.compile(r"^[A-Za-z0-9_.\-]{1,128}$")  # usable as one Zenoh key segment


def _show(x: Any) -> str:
    """A value quoted in an error message, cut to 40 characters (never echo a huge input)."""
    text = repr(x)
    return text if len(text) <= 40 else text[:37] + "..."


class RecordError(ValueError):
    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Episode:
    """A validated record. ``nodes``/``z`` are (T+1,) arrays over t = 0..T, nodes as graph rows."""

    fleet: str
    mission_id: str
    robot_id: str
    policy_version: int | None
    sensor: Sensor
    nodes: np.ndarray
    z: np.ndarray
    captured: bool
    capture_time: int | None
    captured_by: str | None
    # {"team_searcher", "team_steps", "partial_steps", "own_steps"[, "observations_heard", "observations_sent"]}
    coordination: dict[str, Any] | None = None
    times: np.ndarray | None = None  # (T+1,) float64 the mission clock of each reading (s), where recorded


def _need(rec: dict[str, Any], key: str, kind: type | tuple[type, ...]) -> Any:
    if key not in rec:
        raise RecordError("missing-field", f"field {key!r} is missing")
    v = rec[key]
    if not isinstance(v, kind) or isinstance(v, bool):
        raise RecordError("bad-field", f"field {key!r} has the wrong type ({type(v).__name__})")
    return v


def parse_record(rec: Any, graph: Graph, fleet: str | None = None) -> Episode:
    """Validate one record against ``graph`` (and ``fleet`` if given) and parse it."""
    if not isinstance(rec, dict):
        raise RecordError("not-object", f"a record must be a JSON object, got {type(rec).__name__}")
    if rec.get("schema") != SCHEMA:
        raise RecordError("schema", f"schema must be {SCHEMA!r}, got {_show(rec.get('schema'))}")
    rec_fleet = _need(rec, "fleet", str)
    if fleet is not None and rec_fleet != fleet:
        raise RecordError("fleet", f"record is for fleet {_show(rec_fleet)}, expected {fleet!r}")
    mission_id = _need(rec, "mission_id", str)
    robot_id = _need(rec, "robot_id", str)
    for name, v in (("fleet", rec_fleet), ("mission_id", mission_id), ("robot_id", robot_id)):
        if not ID_RE.match(v):
            raise RecordError("bad-id", f"{name} {v[:40]!r} must be 1-128 characters of A-Z a-z 0-9 _ . -")
    gid = _need(rec, "graph_id", str)
    if gid != graph.graph_id:
        raise RecordError("graph_id", f"graph_id {gid[:20]}... does not match this map ({graph.graph_id[:20]}...)")
    pv = rec.get("policy_version")
    if pv is not None and (not isinstance(pv, int) or isinstance(pv, bool) or not 0 <= pv <= MAX_INT):
        raise RecordError("bad-field", f"policy_version must be an integer in [0, 2^63-1] or null, got {str(pv)[:40]}")
    sensor_raw = _need(rec, "sensor", dict)
    try:
        sensor = Sensor(
            eta_fn=sensor_raw.get("eta_fn", 0.0),
            eta_fp=sensor_raw.get("eta_fp", 0.0),
            detection=sensor_raw.get("detection", "node"),
        )
    except ModelError as exc:
        raise RecordError("sensor", f"sensor: {exc}") from None
    if sensor.detection == "custom" and graph.sensing_sets is None:
        raise RecordError("sensor", f"sensor detection 'custom' but the map has no sensing table (use {DETECTIONS})")
    steps = _need(rec, "steps", list)
    if not steps:
        raise RecordError("steps", "steps is empty")
    if len(steps) > MAX_STEPS:
        raise RecordError("size", f"{len(steps)} steps exceed the limit of {MAX_STEPS}")
    nodes = np.empty(len(steps), dtype=np.int64)
    z = np.empty(len(steps), dtype=np.int8)
    index = graph.index
    timed = isinstance(steps[0], dict) and "time_s" in steps[0]
    times = np.empty(len(steps)) if timed else None
    for k, st in enumerate(steps):
        if not isinstance(st, dict):
            raise RecordError("steps", f"step #{k} is not an object")
        t, node, zz = st.get("t"), st.get("node"), st.get("z")
        if t != k or isinstance(t, bool):
            raise RecordError("t-sequence", f"step #{k} has t = {_show(t)}; t must run 0, 1, 2, ... without gaps")
        if isinstance(node, bool) or not isinstance(node, int) or node not in index:
            raise RecordError("node", f"step t={k}: node {_show(node)} is not a node of this map")
        if isinstance(zz, bool) or not isinstance(zz, int) or zz not in (0, 1):
            raise RecordError("z", f"step t={k}: z must be 0 or 1, got {_show(zz)}")
        nodes[k] = index[node]
        z[k] = int(zz)
        if times is not None or "time_s" in st:
            times = _step_time(st, k, times)
    adj = graph.closed_adjacency if graph.n <= 4096 else None
    for k in range(1, len(nodes)):
        u, v = nodes[k - 1], nodes[k]
        ok = adj[u, v] if adj is not None else v in graph.closed(int(u))
        if not ok:
            raise RecordError(
                "move",
                f"step t={k}: move {graph.labels[u]} -> {graph.labels[v]} neither stays nor follows an edge",
            )
    out = _need(rec, "outcome", dict)
    captured = out.get("captured")
    if not isinstance(captured, bool):
        raise RecordError("outcome", "outcome.captured must be true or false")
    ct = out.get("capture_time")
    by = out.get("captured_by")
    if captured:
        if not isinstance(ct, int) or isinstance(ct, bool) or not (0 <= ct <= len(steps) - 1):
            raise RecordError(
                "outcome",
                f"outcome.capture_time {_show(ct)} must be an integer between 0 and the last t ({len(steps) - 1})",
            )
        if by is not None and (not isinstance(by, str) or not ID_RE.match(by)):
            raise RecordError("outcome", f"outcome.captured_by {_show(by)} is not a robot id")
    else:
        ct, by = None, None
    coordination = _coordination(rec.get("coordination"))
    return Episode(
        fleet=rec_fleet,
        mission_id=mission_id,
        robot_id=robot_id,
        policy_version=pv,
        sensor=sensor,
        nodes=nodes,
        z=z,
        captured=captured,
        capture_time=ct,
        captured_by=by,
        coordination=coordination,
        times=times,
    )


def _step_time(st: dict[str, Any], k: int, times: np.ndarray | None) -> np.ndarray:
    """``times`` with step k's ``time_s`` in: every step carries one or none does, each a finite
    number of seconds >= 0, none before the step before it."""
    ts = st.get("time_s")
    if times is None or ts is None:
        raise RecordError("time", f"step t={k}: time_s on some steps only (every step has one, or none does)")
    if not is_seconds(ts):
        raise RecordError("time", f"step t={k}: time_s must be a finite number of seconds >= 0, got {_show(ts)}")
    if k and ts < times[k - 1]:
        raise RecordError("time", f"step t={k}: time_s {ts} is before the step before it ({times[k - 1]:g})")
    times[k] = float(ts)
    return times


def is_seconds(v: Any) -> TypeGuard[float]:
    """A time on the mission clock: a finite real number >= 0 (a JSON true is not one)."""
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and 0 <= float(v) < float("inf")


def _count(v: Any) -> TypeGuard[int]:
    """A whole number >= 0 (a JSON true is not one)."""
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _coordination(raw: Any) -> dict[str, Any] | None:
    """The optional ``coordination`` of a record: how many of the robot's decisions followed its
    team's plan with every teammate's step in, how many with one missing, and how many its own
    policy (shared/core/team.py ``TeamAgent.act``). One a step, but a record cut at a capture the
    robot learned of after it went on searching holds fewer steps than it decided."""
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise RecordError("coordination", "coordination must be an object")
    searcher = raw.get("team_searcher")
    if searcher is not None and searcher not in TEAM_SEARCHERS:
        raise RecordError("coordination", f"coordination.team_searcher {_show(searcher)} is not a team searcher")
    counts = [raw.get("team_steps"), raw.get("partial_steps", 0), raw.get("own_steps")]
    if not all(_count(c) for c in counts) or sum(counts) > MAX_STEPS:
        raise RecordError(
            "coordination",
            f"coordination's team_steps, partial_steps and own_steps must be integers >= 0, at most {MAX_STEPS} in all",
        )
    out = {"team_searcher": searcher, "team_steps": counts[0], "partial_steps": counts[1], "own_steps": counts[2]}
    heard, sent = raw.get("observations_heard"), raw.get("observations_sent")
    if heard is not None or sent is not None:  # what the robot's links delivered (records since teams)
        if not (_count(heard) and _count(sent) and heard <= sent):
            raise RecordError(
                "coordination",
                "coordination's observations_heard and observations_sent must be integers >= 0, heard at most sent",
            )
        out["observations_heard"], out["observations_sent"] = heard, sent
    dropped, flown_for = raw.get("teammates_dropped"), raw.get("flown_for")
    if dropped is not None or flown_for is not None:  # teammates withdrawn mid-mission (records since team sizes)
        if not (_count(dropped) and _count(flown_for) and 1 <= flown_for <= MAX_MISSION_ROBOTS):
            raise RecordError(
                "coordination",
                "coordination's teammates_dropped must be an integer >= 0 and flown_for one in "
                f"1..{MAX_MISSION_ROBOTS}",
            )
        out["teammates_dropped"], out["flown_for"] = dropped, flown_for
    return out


def make_record(
    graph: Graph,
    *,
    fleet: str,
    mission_id: str,
    robot_id: str,
    nodes: list[int] | np.ndarray,
    z: list[int] | np.ndarray,
    sensor: Sensor,
    captured: bool,
    capture_time: int | None,
    captured_by: str | None,
    policy_version: int | None = None,
    coordination: dict[str, Any] | None = None,
    times: list[float] | np.ndarray | None = None,
) -> dict[str, Any]:
    """Build a record from rows ``nodes`` and observations ``z`` for t = 0..T (and the mission
    clock of each reading, ``times``, where the robot keeps one)."""
    labels = graph.labels
    rec: dict[str, Any] = {
        "schema": SCHEMA,
        "fleet": fleet,
        "mission_id": mission_id,
        "robot_id": robot_id,
        "graph_id": graph.graph_id,
        "policy_version": policy_version,
        "sensor": sensor.to_json(),
        "steps": [
            {"t": t, "node": int(labels[p]), "z": int(zz)} for t, (p, zz) in enumerate(zip(nodes, z, strict=True))
        ],
        "outcome": {"captured": captured, "capture_time": capture_time, "captured_by": captured_by},
    }
    if times is not None:
        for step, ts in zip(rec["steps"], times, strict=True):
            step["time_s"] = round(float(ts), 3)
    if coordination is not None:
        rec["coordination"] = coordination
    return rec


def emission_likelihoods(ep: Episode, capture_aware: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(l_in, l_out), each (T+1,): P(z_t | e_t in D(p_t)) and P(z_t | e_t outside it), the entries of
    Lambda (Eq. 2) for this robot's readings. ``capture_aware`` (docs/SPEC.md section 10): a z = 1
    that did not end the mission was a false alarm (e_t outside D(p_t)), and the capturing robot's
    last z = 1 was the target (e_t inside)."""
    (in0, in1), (out0, out1) = ep.sensor.likelihoods()
    l_in = np.where(ep.z == 1, in1, in0)
    l_out = np.where(ep.z == 1, out1, out0)
    if capture_aware:
        steps = len(ep.z)
        before_capture = np.arange(steps) < ep.capture_time if ep.capture_time is not None else np.ones(steps, bool)
        l_in = np.where((ep.z == 1) & before_capture, 0.0, l_in)
        if ep.captured and ep.captured_by == ep.robot_id and ep.capture_time == steps - 1:
            l_out[steps - 1] = 0.0
    return l_in, l_out


def spread(graph: Graph, possible: np.ndarray) -> np.ndarray:
    """Where the target can be one step later: ``possible`` (..., n) bool over nodes, each node
    reachable from any node of its closed neighbourhood (the support of Gamma^T b, O(n + m))."""
    return np.logical_or.reduceat(possible[..., graph.closed_idx], graph.closed_ptr[:-1], axis=-1)


def unexplained(ep: Episode, graph: Graph) -> str | None:
    """Why no path of the target on the map (a walk over closed neighbourhoods from any node)
    explains the record under its own sensor model, or None when some path does. Only a zero in
    Lambda can rule a path out (eta_fn = 0 or eta_fp = 0, or a false alarm), so this is the support
    of the forward filter (Eq. 1) under any model whose Gamma_hat and b0 have full support on
    the map: O(T (n + m)) on the CSR neighbourhoods, no dense array."""
    ptr, idx = graph.detection_sets(ep.sensor.detection)
    (_in0, _in1), (out0, _out1) = ep.sensor.likelihoods()
    last = len(ep.z) - 1
    claims_capture = ep.captured and ep.captured_by == ep.robot_id and ep.capture_time == last
    if out0 > 0 and not claims_capture and not (ep.z == 1).any() and int(np.diff(ptr).max()) < graph.n:
        # every reading 0, none of which rules out a node outside D(p_t): V \ D(p_t) stays possible
        # at every step (a closed neighbourhood holds its node), so the record is explained
        return None
    l_in, l_out = emission_likelihoods(ep)
    possible = np.ones(graph.n, dtype=bool)
    for t in range(len(ep.z)):
        if t:
            possible = spread(graph, possible)  # where the target can be at t
        inside = np.zeros(graph.n, dtype=bool)
        p = int(ep.nodes[t])
        inside[idx[ptr[p] : ptr[p + 1]]] = True
        possible &= np.where(inside, l_in[t] > 0, l_out[t] > 0)
        if not possible.any():
            node = int(graph.labels[p])
            if ep.z[t] == 1 and l_in[t] == 0:
                what = f"z = 1 at t={t} on node {node} did not end the mission, and the sensor has no false positives"
            elif ep.z[t] == 1:
                what = f"z = 1 at t={t} on node {node}: no place the target could be is within the detection set"
            else:
                what = (
                    f"z = 0 at t={t} on node {node}: the sensor has no false negatives and the target can only be there"
                )
            return f"impossible: {what} (eta_fn={ep.sensor.eta_fn}, eta_fp={ep.sensor.eta_fp})"
    return None


def canonical_record(ep: Episode, graph: Graph) -> dict[str, Any]:
    """The record of a parsed episode with the contract's fields only (what the server stores:
    fields this schema version does not know are dropped, not kept verbatim)."""
    return make_record(
        graph,
        fleet=ep.fleet,
        mission_id=ep.mission_id,
        robot_id=ep.robot_id,
        nodes=ep.nodes,
        z=ep.z,
        sensor=ep.sensor,
        captured=ep.captured,
        capture_time=ep.capture_time,
        captured_by=ep.captured_by,
        policy_version=ep.policy_version,
        coordination=ep.coordination,
        times=ep.times,
    )


def read_jsonl(path: str | Path) -> Iterator[tuple[int, Any]]:
    """Yield (line number, parsed JSON or a RecordError) for each non-empty line."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            if not line.strip():
                continue
            if len(line) > MAX_RECORD_BYTES:
                yield lineno, RecordError("size", f"line {lineno} is longer than {MAX_RECORD_BYTES} bytes")
                continue
            try:
                yield lineno, json.loads(line)
            except json.JSONDecodeError as exc:
                yield lineno, RecordError("json", f"line {lineno}: not valid JSON ({exc.msg})")

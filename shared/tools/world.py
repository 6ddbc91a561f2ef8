"""The fleet simulator's world: it owns the hidden target and advances in lockstep with the agents.

Each simulated robot (robot_agent.backend.SimBackend) sends its (t, node) as a query on
``mures/<fleet>/sim/<mission>/<robot>``. When every robot still in the mission has reported step
t, the world moves the target (t > 0: e_t ~ Gamma(e_{t-1}, .)), draws each robot's z_t from the
sensor model (docs/SPEC.md section 1) and replies to every query. It only answers z: a robot that
reads z = 1 reports the detection to the server as a real robot does, and the server decides the
capture (docs/SPEC.md section 6), so every fleet-sim mission exercises that path. The world
ends a mission when the server says it is over, or at its step limit (where the agents stop
on their own). A robot that does not report within ``step_timeout``, or that the server says
has withdrawn (its backend failed), is withdrawn from the mission and the others go on
(robustness, paper Fig. 12). ``seen(mission, robot, t)`` tells whether e_t was in D(p_t): the truth that a simulated
operator confirms or dismisses a detection with (fleet-sim under ``--capture confirm``).

Deterministic for a mission seed: the target's path and every z are drawn from one generator
seeded by the mission seed, in the mission's robot order, whatever order the queries arrive in.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.core.records import is_seconds
from shared.core.wire import WORLD_CLOCK_PROBE, mission_key, parse_message, sim_key, truth_key

log = logging.getLogger("mures.world")


@dataclass
class _Mission:
    robots: list[str]
    rng: np.random.Generator
    max_steps: int
    target: int  # e_t, a row
    max_seconds: float | None = None  # the time limit on the mission clock (the continuous world's)
    t: int = 0
    active: set[str] = field(default_factory=set)
    reports: dict[str, tuple[int, Any]] = field(default_factory=dict)  # robot -> (row, query)
    waits: dict[str, float] = field(default_factory=dict)  # robot -> its decision's wait for teammates, if it said
    waiting_since: float = 0.0
    last_step: float = 0.0
    ended: bool = False
    ended_at: float = 0.0
    path: list[int] = field(default_factory=list)  # target rows over t
    seen: dict[tuple[str, int], bool] = field(default_factory=dict)  # (robot, t) -> e_t in D(p_t)
    confirm: bool = False  # the mission's detections wait for an operator (capture "confirm")
    undecided: set[tuple[str, int]] = field(default_factory=set)  # (robot, t) of z = 1 not yet decided
    undecided_since: float = 0.0


class World:
    CLOCK = "steps"  # every robot's step t together (the continuous world: "seconds", each its own)

    def __init__(
        self,
        session: zenoh.Session,
        fleet: str,
        graph: Graph,
        target: TargetModel,
        sensor: Sensor,
        step_timeout: float = 10.0,
        step_delay: float = 0.0,
    ) -> None:
        self.session, self.fleet, self.graph = session, fleet, graph
        self.gamma = target.dense()
        self.cum = np.cumsum(self.gamma, axis=1)
        self.b0 = np.cumsum(target.b0)
        self.sensor = sensor
        self.detect = graph.detection_matrix(sensor.detection)  # detect[p, e]: e in D(p)
        self.step_timeout = step_timeout
        self.step_delay = step_delay
        self.events: queue.Queue[tuple[str, Any]] = queue.Queue()
        self.missions: dict[str, _Mission] = {}
        self.parked: dict[str, list[Any]] = {}
        self.finished: dict[str, dict[str, Any]] = {}  # mission -> outcome, for inspection
        self.step_seconds: list[float] = []  # time from a step's first report to the replies
        self.step_intervals: list[float] = []  # time between consecutive steps of a mission (lockstep period)
        self.running = True
        self.sub = session.declare_subscriber(mission_key(fleet, "*"), lambda s: self.events.put(("msg", s)))
        self.queryable = session.declare_queryable(sim_key(fleet, "*", "*"), lambda q: self.events.put(("q", q)))
        self.thread = threading.Thread(target=self._loop, name="world", daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.running = False
        self.thread.join(3)
        self.sub.undeclare()
        self.queryable.undeclare()

    # ------------------------------------------------------------------ event loop
    def _loop(self) -> None:
        while self.running:
            try:
                kind, item = self.events.get(timeout=0.1)
            except queue.Empty:
                kind, item = "tick", None
            try:
                if kind == "msg":
                    self._on_message(item.payload.to_bytes())
                elif kind == "q":
                    self._on_query(item)
                self._check_timeouts()
            except Exception:
                log.exception("world event %s", kind)

    def _on_message(self, payload: bytes) -> None:
        msg = parse_message(payload)
        if msg is None:
            return
        mid = msg["mission_id"]
        if msg["type"] == "start":
            if mid in self.missions:
                return
            self.missions[mid] = self._new_mission(msg)
            for q in self.parked.pop(mid, []):
                self._on_query(q)
        elif msg["type"] in ("captured", "stop") and mid in self.missions:
            self.finished.setdefault(mid, msg)
            self._end(mid, publish=None)
        elif msg["type"] == "withdrawn" and mid in self.missions:  # a robot whose backend failed
            m = self.missions[mid]
            robot = str(msg.get("robot_id"))
            if robot in m.active:
                m.active.discard(robot)
                log.info("mission %s: %s withdrew; the others go on", mid, robot)
                if m.reports:
                    self._advance_if_ready(mid, m)
        elif msg["type"] == "dismissed" and mid in self.missions:
            m = self.missions[mid]
            m.undecided.discard((str(msg.get("robot_id")), msg.get("t")))
            m.waiting_since = time.monotonic()  # the robots' wait for the decision is no timeout of theirs
            self._advance_if_ready(mid, m)

    def _new_mission(self, msg: dict[str, Any]) -> _Mission:
        """The state of the mission whose start message is ``msg``: e_0 ~ b0 from the mission seed."""
        rng = np.random.default_rng(int(msg.get("seed", 0)) % (2**63))
        e0 = int(np.searchsorted(self.b0, rng.random() * self.b0[-1], side="right"))
        robots = list(msg.get("robots") or [])
        m = _Mission(
            robots=robots,
            rng=rng,
            max_steps=int(msg.get("max_steps") or 3 * self.graph.n),
            target=min(e0, self.graph.n - 1),
            active=set(robots),
            confirm=msg.get("capture") == "confirm",
        )
        m.path.append(m.target)
        return m

    def _on_query(self, q: Any) -> None:
        parts = str(q.key_expr).split("/")
        if len(parts) != 5:
            return self._err(q, "bad key")
        mid, robot = parts[3], parts[4]
        if mid == WORLD_CLOCK_PROBE:  # a robot asking which clock this world keeps (robot-agent --team-clock auto)
            q.reply(q.key_expr, json.dumps({"clock": self.CLOCK}).encode())
            return q.drop()
        m = self.missions.get(mid)
        if m is None:
            if mid not in self.parked:  # a mission started before this world joined never answers
                log.info("mission %s: robots ask, but its start message has not come (yet)", mid)
            self.parked.setdefault(mid, []).append(q)  # the start message may still be on its way
            return None
        if m.ended:
            q.reply(q.key_expr, b'{"ended": true}')
            return q.drop()
        if robot not in m.active:
            return self._err(q, f"robot {robot} is not (or no longer) in mission {mid}")
        try:
            body = json.loads(q.payload.to_bytes())
            t, node = int(body["t"]), int(body["node"])
            row = self.graph.index[node]
            wait = body.get("wait_s")
        except (ValueError, KeyError, TypeError, AttributeError):
            return self._err(q, 'payload must be {"t": int, "node": label on the map, "wait_s": seconds (optional)}')
        if wait is not None and not is_seconds(wait):
            return self._err(q, f"wait_s must be seconds (a finite number >= 0), got {wait!r}")
        why = self._refusal(m, robot, t, row)
        if why:
            return self._err(q, why)
        if not m.reports:
            m.waiting_since = time.monotonic()
        m.reports[robot] = (row, q)
        if wait is not None:
            m.waits[robot] = float(wait)
        self._advance_if_ready(mid, m)
        return None

    def _refusal(self, m: _Mission, robot: str, t: int, row: int) -> str | None:
        """Why robot ``robot``'s report of step ``t`` on ``row`` is refused, or None: in lockstep,
        every robot reports the world's step once."""
        if t != m.t or robot in m.reports:
            return f"step t={t} out of lockstep (world is at t={m.t})"
        return None

    def _advance_if_ready(self, mid: str, m: _Mission) -> None:
        """Advance when every active robot has reported and, under "confirm", the operator has
        decided every detection of the last step: a decision takes no step of the simulated world,
        so its missions capture as the batched simulator's do (the first z = 1 with the target in
        D(p); a false alarm ends nothing)."""
        if not m.ended and set(m.reports) >= m.active and not m.undecided:
            self._advance(mid, m)

    def _err(self, q: Any, text: str) -> None:
        try:
            q.reply_err(text.encode())
            q.drop()
        except Exception:
            log.debug("reply_err failed", exc_info=True)

    def _check_timeouts(self) -> None:
        now = time.monotonic()
        for mid, m in list(self.missions.items()):
            if m.ended:
                if now - m.ended_at > 60:
                    del self.missions[mid]
                continue
            if m.undecided and now - m.undecided_since > self.step_timeout:
                log.warning("mission %s: no decision on the detections %s; going on", mid, sorted(m.undecided))
                m.undecided.clear()
                self._advance_if_ready(mid, m)
            elif m.reports and now - m.waiting_since > self.step_timeout:
                gone = m.active - set(m.reports)
                log.warning("mission %s: %s did not report step %d; withdrawn", mid, ", ".join(sorted(gone)), m.t)
                m.active -= gone
                self._advance(mid, m)
        for mid in [k for k, qs in self.parked.items() if not qs]:
            del self.parked[mid]

    def _advance(self, mid: str, m: _Mission) -> None:
        """All active robots reported step m.t: move the target (t > 0), observe, reply."""
        if self.step_delay:
            time.sleep(self.step_delay)
        if m.t > 0:
            m.target = int(np.searchsorted(self.cum[m.target], m.rng.random() * self.cum[m.target, -1], side="right"))
            m.target = min(m.target, self.graph.n - 1)
            m.path.append(m.target)
        (_in0, in1), (_out0, out1) = self.sensor.likelihoods()
        replies = []
        replies_by_robot: dict[str, dict[str, Any]] = {}
        for robot in m.robots:  # fixed order: deterministic draws
            if robot not in m.reports:
                continue
            row, q = m.reports[robot]
            u = m.rng.random()
            seen = bool(self.detect[row, m.target])
            z = int(u < (in1 if seen else out1))
            m.seen[robot, m.t] = seen
            if z and m.confirm:
                m.undecided.add((robot, m.t))
                m.undecided_since = time.monotonic()
            replies.append((q, z))
            replies_by_robot[robot] = {"node": int(self.graph.labels[row]), "z": z, "seen": seen}
        for q, z in replies:
            q.reply(q.key_expr, json.dumps({"z": z}).encode())
            q.drop()  # finalise: the robot's get() returns now
        self._publish_truth(mid, m, replies_by_robot)
        now = time.monotonic()
        self.step_seconds.append(now - m.waiting_since)
        if m.t > 0:
            self.step_intervals.append(now - m.last_step)
        m.last_step = now
        t = m.t
        m.reports = {}
        m.t += 1
        if not m.active:
            self._end(mid, {"type": "stop", "mission_id": mid, "reason": "no robots"})
        elif t >= m.max_steps:  # the agents stop there on their own, as real robots do
            self._end(mid, None)

    def seen(self, mission_id: str, robot: str, t: int) -> bool | None:
        """Whether the target was in D(p_t) of ``robot`` at step t (None: no such step known)."""
        m = self.missions.get(mission_id)
        return None if m is None else m.seen.get((robot, t))

    def _publish_truth(self, mid: str, m: _Mission, robots: dict[str, dict[str, Any]]) -> None:
        """The step's ground truth on mures/<fleet>/truth/<mission> for the console's debugging
        overlay: the target's node e_t and, per robot, z_t and whether e_t was in D(p_t) (a z_t = 1
        without it is a false alarm). Best effort: nothing in the mission waits for it."""
        msg = {"mission_id": mid, "t": m.t, "target": int(self.graph.labels[m.target]), "robots": robots}
        try:
            self.session.put(truth_key(self.fleet, mid), json.dumps(msg).encode())
        except Exception:
            log.debug("truth for %s not published", mid, exc_info=True)

    def _end(self, mid: str, publish: dict[str, Any] | None) -> None:
        m = self.missions[mid]
        if m.ended:
            return
        m.ended, m.ended_at = True, time.monotonic()
        for _row, q in m.reports.values():
            q.reply(q.key_expr, b'{"ended": true}')
            q.drop()
        m.reports = {}
        if publish is not None:
            self.finished[mid] = publish
            self.session.put(
                mission_key(self.fleet, mid),
                json.dumps(publish).encode(),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

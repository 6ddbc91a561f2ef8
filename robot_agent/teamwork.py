"""One mission's teamwork on the wire: this robot's observations out to its teammates, theirs in
to its ``TeamAgent`` (shared/core/team.py), and a bounded wait for them before each decision.

Each step the robot publishes (t, node, z) on ``mures/<fleet>/observations/<robot>/<mission>``
(best effort: congestion never blocks the robot, a lost message is no observation) and listens to
its teammates' on ``mures/<fleet>/observations/*/<mission>``. Before deciding at step t it waits at
most ``wait_s`` for every live teammate's step t; whatever has not come by then, the robot decides
without (its own policy on an incomplete step). No decision ever waits longer on the network. On
the mission clock (``TimedTeamAgent``: robot-agent --team-clock seconds) the robot publishes each
observation with its time and the node it left for, after deciding, and decides on what has come
without waiting.

A teammate whose liveliness token goes (its agent stopped, its process or its link died:
``mures/<fleet>/agents/<robot>``) is withdrawn from this robot's ``TeamAgent`` before its next
decision: out of the team's plan, and its own policy the version's team built for the robots
left (``TeamAgent.withdraw``).

``link_loss`` is a documented drop point for simulations (`robot-agent --link-loss P`, `mures
fleet-sim --link-loss P`): each outgoing observation is dropped with probability P before it is
sent. It changes what the network delivers, never how the robot decides.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import random
import time
from typing import Any

from shared.core.graph import Graph
from shared.core.team import TeamAgent
from shared.core.timed_team import TimedTeamAgent
from shared.core.wire import agent_key, observation_key, observation_message, parse_observation

log = logging.getLogger("mures.agent")

TEAM_WAIT_S = 0.5  # the longest a decision waits for the teammates' observations of its step


class Teamwork:
    """The wire side of ``agent`` (this robot's TeamAgent) during mission ``mission_id``; ``close()``
    at the mission's end."""

    def __init__(
        self,
        session: Any,
        fleet: str,
        graph: Graph,
        mission_id: str,
        agent: TeamAgent,
        wait_s: float = TEAM_WAIT_S,
        link_loss: float = 0.0,
    ) -> None:
        import zenoh

        self.graph, self.mission_id, self.agent = graph, mission_id, agent
        self.me, self.wait_s, self.link_loss = agent.me, wait_s, link_loss
        self.inbox: queue.Queue[dict[str, Any]] = queue.Queue()
        self.dropped = 0  # outgoing observations dropped at the drop point
        self.ignored = 0  # incoming messages that were malformed or not a teammate's
        self._session = session
        self._key = observation_key(fleet, self.me, mission_id)
        self._congestion = zenoh.CongestionControl.DROP
        self._sub = None
        if agent.searcher is not None:  # a robot that never plans with its team need not listen
            self._sub = session.declare_subscriber(observation_key(fleet, "*", mission_id), self._on_observation)
        self.gone: queue.Queue[str] = queue.Queue()  # teammates whose liveliness token went
        self._alive_sub = None
        if len(agent.robots) > 1:
            self._alive_sub = session.liveliness().declare_subscriber(agent_key(fleet, "*"), self._on_alive)

    def _on_alive(self, sample: Any) -> None:  # callback: queue only
        import zenoh

        if sample.kind == zenoh.SampleKind.DELETE:
            self.gone.put(str(sample.key_expr).rsplit("/", 1)[-1])

    def _on_observation(self, sample: Any) -> None:  # callback: parse and queue only
        msg, _why = parse_observation(str(sample.key_expr), sample.payload.to_bytes())
        if msg is None:
            self.ignored += 1
        elif msg["robot_id"] != self.me:  # its own comes back from the router: already folded in
            self.inbox.put(msg)

    def publish(self, t: int, node: int, z: int, time_s: float | None = None, goal: int | None = None) -> None:
        """This robot's observation of step ``t`` (``node`` a map label) to its teammates; on the
        mission clock with the reading's ``time_s`` and the label of the node it left for."""
        if self.link_loss and random.random() < self.link_loss:
            self.dropped += 1
            return
        msg = observation_message(self.mission_id, self.me, t, node, z, time_s, goal)
        try:
            self._session.put(self._key, json.dumps(msg).encode(), congestion_control=self._congestion)
        except Exception as exc:  # the link is down: teammates go without this step
            log.debug("mission %s: observation at t=%d not sent: %s", self.mission_id, t, exc)

    def gather(self, t: int) -> None:
        """Fold in the teammates' observations that have come, waiting at most ``wait_s`` for the
        rest of step ``t``'s (no wait once the step is complete, for a robot that searches alone,
        or while no teammate is heard at all); teammates whose liveliness went are withdrawn first."""
        self._withdraw()
        if self._sub is None:
            return
        if isinstance(self.agent, TimedTeamAgent):  # on the clock: what has come, and no wait (timed_team.py)
            self._drain()
            return
        deadline = time.monotonic() + self.wait_s
        while True:
            self._drain()
            left = deadline - time.monotonic()
            alone = len(self.agent.live(t)) == 1  # no teammate heard lately: nobody to wait for
            if alone or self.agent.complete(t) or left <= 0:
                return
            with contextlib.suppress(queue.Empty):
                self._fold(self.inbox.get(timeout=min(left, 0.05)))

    def _withdraw(self) -> None:
        while True:
            try:
                robot = self.gone.get_nowait()
            except queue.Empty:
                return
            if self.agent.withdraw(robot):
                left = len(self.agent.robots) - len(self.agent.withdrawn)
                log.info(
                    "mission %s: %s dropped out (liveliness gone or withdrawn); %d robots left, own policy for %d",
                    self.mission_id,
                    robot,
                    left,
                    self.agent.flown_for,
                )

    def _drain(self) -> None:
        while True:
            try:
                self._fold(self.inbox.get_nowait())
            except queue.Empty:
                return

    def _fold(self, msg: dict[str, Any]) -> None:
        row = self.graph.index.get(msg["node"])
        if row is None or msg["robot_id"] not in self.agent.robots:
            self.ignored += 1
            return
        if isinstance(self.agent, TimedTeamAgent):
            if "time_s" not in msg:  # a teammate on step indices: nothing to place on the clock
                self.ignored += 1
                return
            goal = self.graph.index.get(msg["goal"]) if "goal" in msg else None
            self.agent.observe_at(msg["robot_id"], msg["t"], row, msg["z"], msg["time_s"], goal)
            return
        self.agent.observe(msg["robot_id"], msg["t"], row, msg["z"])

    def close(self) -> None:
        if self.dropped or self.ignored:
            log.info(
                "mission %s: %d observations dropped at the drop point, %d messages ignored",
                self.mission_id,
                self.dropped,
                self.ignored,
            )
        for sub in (self._sub, self._alive_sub):
            if sub is not None:
                sub.undeclare()
        self._sub = self._alive_sub = None

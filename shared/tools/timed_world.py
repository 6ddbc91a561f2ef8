"""The continuous world served to robot agents: the fleet simulator's world (shared/tools/world.py)
with the building's geometry and a mission clock in seconds (shared/world/continuous.py), so that
`robot-agent --backend sim` processes, the server, its records, EM and retraining run against
travel times as a real building gives them.

The agents speak the same protocol as to the step world: a robot sends (t, node) on
``mures/<fleet>/sim/<mission>/<robot>`` when it has moved to ``node`` for its step t, and the world
replies with its z (and ``time_s``, the mission clock of that reading). The world keeps each robot's
clock: its step t reading happens when it arrives, its last arrival plus the move's travel time
(the edge's length along free space over the robot's speed, that speed drawn per move with
coefficient of variation ``speed_cv``; staying takes ``stay_s``). So a robot's steps are its own:
one robot may be at its step 9 while a teammate on long corridors is at its step 5, as on real
robots, and nothing waits for a common step index.

The target's path is drawn from a generator of its own, seeded by the mission seed: whatever the
robots do, a mission seed gives the same target path, so that two fleets flown on the same seeds are
compared on the same missions (paired). The readings' draws come from another.

Virtual time, conservatively (a discrete-event simulation): the world answers only when every
robot still in the mission has reported where it goes next, and then answers the earliest
reading, with the robots arriving within the earliest robot's wait for its teammates after it, at
once and in time order (a robot on the step rule waits up to 0.5 s for its teammates' observations
of its step, robot_agent/teamwork.py, and says so with its report; one on the mission clock waits
for none, so a teammate arriving 0.3 s after it is answered after its decision and hears of it, as
on real robots; ``together_s`` bounds the window); the target walks to that
moment in ticks of ``dt`` (``Targets``), and the reading is z = 1 with probability 1 - eta_fn when
the target is within the sensor's range in line of sight (``Building.sees``), eta_fp otherwise.
A robot's thinking and the network take no mission time, so a run does not depend on the
machine's speed: the same mission seed gives the same target path and readings, whatever order
the queries come in. What robot-agent does in wall time (its bounded wait for teammates, its
fall-back to its own policy) happens as it does on real robots.

Missions end as in the step world (the server's ``captured`` or ``stop``, every robot at its step
limit, or no robot left); ``seconds[mission]`` holds the capture time in seconds (the mission clock
of the capturing reading) or, for a mission not captured, the clock of its last reading.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from shared.core.models import Sensor, TargetModel, uniform_walk
from shared.core.wire import time_limit
from shared.tools.world import World, _Mission
from shared.world.continuous import Building, Targets, target_generator

TOGETHER_S = 0.5  # robots arriving this close after the earliest are answered with it, at most (TEAM_WAIT_S)


@dataclass
class Motion:
    """How robots and target move (docs/continuous-world.md): speeds in m/s, times in s."""

    speed: float = 0.5
    speed_cv: float = 0.0
    stop_prob: float = 0.0  # a move is held up (a door, a person in the way) with this probability ...
    stop_s: float = 30.0  # ... for an exponential time of this mean
    stay_s: float = 1.0
    target_speed: float = 0.5
    target_dwell_s: float = 10.0
    dt: float = 0.1
    target: TargetModel | None = None  # where the target goes after a dwell (per step); None: the uniform walk


@dataclass
class _TimedMission(_Mission):
    targets: Targets | None = None  # B = 1: this mission's target
    now_s: float = 0.0  # the target's clock
    clock_s: dict[str, float] = field(default_factory=dict)  # each robot's latest reading's time
    row: dict[str, int] = field(default_factory=dict)  # each robot's node row at that reading
    next_t: dict[str, int] = field(default_factory=dict)  # the step each robot reports next
    due_s: dict[str, float] = field(default_factory=dict)  # the time of each pending report's reading
    speed_rng: dict[str, np.random.Generator] = field(default_factory=dict)
    target_rng: np.random.Generator = field(default_factory=np.random.default_rng)
    time_of: dict[tuple[str, int], float] = field(default_factory=dict)  # (robot, t) -> reading's time
    finished_robots: set[str] = field(default_factory=set)  # answered at their step limit


class TimedWorld(World):
    """The world of module docstring, for the missions the server starts on ``fleet``."""

    CLOCK = "seconds"

    def __init__(
        self,
        session: zenoh.Session,
        fleet: str,
        building: Building,
        sensor: Sensor,
        motion: Motion | None = None,
        step_timeout: float = 10.0,
    ) -> None:
        self.building, self.motion = building, motion or Motion()
        self.seconds: dict[str, dict[str, Any]] = {}  # mission -> {"time_s", "captured"}
        shortest = min(float(building.length_m.min()) / self.motion.speed, self.motion.stay_s)
        # a robot answered at T reports its next reading at T + a move at the earliest (half that with speed noise)
        self.together_s = min(TOGETHER_S, shortest / (4 if self.motion.speed_cv else 2))
        target = self.motion.target or uniform_walk(building.graph)
        super().__init__(session, fleet, building.graph, target, sensor, step_timeout)

    # ------------------------------------------------------------------ hooks of World
    def _new_mission(self, msg: dict[str, Any]) -> _Mission:
        seed = int(msg.get("seed", 0)) % (2**63)
        rng = np.random.default_rng(seed)  # the readings'
        target_rng = target_generator(seed)  # the target's own: its path is the seed's alone
        robots = list(msg.get("robots") or [])
        targets = Targets.start(self.building, 1, target_rng, self.motion.target_dwell_s, self.motion.target)
        m = _TimedMission(
            robots=robots,
            rng=rng,
            max_steps=int(msg.get("max_steps") or 3 * self.graph.n),
            max_seconds=time_limit(msg),
            target=int(targets.at[0]),
            active=set(robots),
            confirm=msg.get("capture") == "confirm",
            targets=targets,
            next_t={r: 0 for r in robots},
            speed_rng={r: np.random.default_rng([seed, i]) for i, r in enumerate(robots)},
            target_rng=target_rng,
        )
        m.path.append(m.target)
        return m

    def _refusal(self, m: _Mission, robot: str, t: int, row: int) -> str | None:
        assert isinstance(m, _TimedMission)
        if robot in m.reports or t != m.next_t.get(robot):
            return f"step t={t} is not robot {robot}'s next (it is at t={m.next_t.get(robot, 0)})"
        if t == 0:
            m.due_s[robot] = 0.0
            return None
        here = m.row[robot]
        if row not in self.graph.closed(here):
            return f"node {int(self.graph.labels[row])} is not in N[{int(self.graph.labels[here])}]"
        m.due_s[robot] = m.clock_s[robot] + self._travel_s(m, robot, here, row)
        return None

    def _travel_s(self, m: _TimedMission, robot: str, here: int, row: int) -> float:
        """Seconds of ``robot``'s move from row ``here`` to ``row``: length / speed, the speed drawn
        per move (lognormal, mean ``speed``, coefficient of variation ``speed_cv``, within 0.5-2 x),
        plus a stop with probability ``stop_prob`` (exponential, mean ``stop_s``)."""
        mo = self.motion
        if row == here:
            return mo.stay_s
        speed = mo.speed
        rng = m.speed_rng[robot]
        if mo.speed_cv:
            sigma = math.sqrt(math.log1p(mo.speed_cv**2))
            factor = math.exp(sigma * float(rng.standard_normal()) - sigma**2 / 2)
            speed *= min(max(factor, 0.5), 2.0)
        held = float(rng.exponential(mo.stop_s)) if mo.stop_prob and rng.random() < mo.stop_prob else 0.0
        return float(self.building.length_m[self.building.edge_of[here, row]]) / speed + held

    def _advance(self, mid: str, m: _Mission) -> None:
        """Every robot still flying has reported its next reading: answer the earliest (and those
        within its wait for its teammates, at most ``together_s``, after it), in time order."""
        assert isinstance(m, _TimedMission) and m.targets is not None
        if not m.reports:
            if not m.active:
                self._end(mid, {"type": "stop", "mission_id": mid, "reason": "no robots"})
            return
        order = {r: i for i, r in enumerate(m.robots)}
        pending = sorted(m.reports, key=lambda r: (m.due_s[r], order[r]))
        first = m.due_s[pending[0]]
        window = min(self.together_s, m.waits.get(pending[0], TOGETHER_S))  # the earliest robot's wait
        (_in0, in1), (_out0, out1) = self.sensor.likelihoods()
        answered: dict[str, dict[str, Any]] = {}
        for robot in [r for r in pending if m.due_s[r] <= first + window]:
            row, q = m.reports.pop(robot)
            due = m.due_s.pop(robot)
            while m.now_s + self.motion.dt <= due:  # the target walks to the reading's moment
                m.targets.advance(
                    self.building,
                    self.motion.dt,
                    np.ones(1, dtype=bool),
                    m.target_rng,
                    self.motion.target_speed,
                    self.motion.target_dwell_s,
                    self.motion.target,
                )
                m.now_s += self.motion.dt
            t = m.next_t[robot]
            where = m.targets.pixels(self.building, np.zeros(1, dtype=np.int64))
            seen = bool(self.building.sees(np.array([row]), where)[0])
            z = int(m.rng.random() < (in1 if seen else out1))
            m.seen[robot, t] = seen
            m.time_of[robot, t] = due
            m.clock_s[robot], m.row[robot], m.next_t[robot] = due, row, t + 1
            m.t = max(m.t, t + 1)
            if z and m.confirm:
                m.undecided.add((robot, t))
                m.undecided_since = time.monotonic()
            q.reply(q.key_expr, f'{{"z": {z}, "time_s": {due:.3f}}}'.encode())
            q.drop()
            answered[robot] = {"node": int(self.graph.labels[row]), "z": z, "seen": seen, "t": t, "time_s": due}
            # the agent stops there on its own: its step limit, or its first reading at or past the
            # time limit (the clock as it reads it, to the millisecond)
            if t >= m.max_steps or (m.max_seconds is not None and float(f"{due:.3f}") >= m.max_seconds):
                m.active.discard(robot)
                m.finished_robots.add(robot)
        m.target = int(m.targets.at[0])
        m.waiting_since = time.monotonic()
        self._publish_truth(mid, m, answered)
        if not m.active:
            self._end(mid, None if m.finished_robots else {"type": "stop", "mission_id": mid, "reason": "no robots"})
        else:  # a robot that read its last step no longer holds the others back
            self._advance_if_ready(mid, m)

    def _end(self, mid: str, publish: dict[str, Any] | None) -> None:
        m = self.missions[mid]
        if not m.ended and isinstance(m, _TimedMission):
            end = self.finished.get(mid) or {}
            captured = end.get("type") == "captured"
            at = m.time_of.get((str(end.get("captured_by")), int(end.get("t", -1)))) if captured else None
            self.seconds[mid] = {
                "time_s": at if at is not None else max(m.clock_s.values(), default=0.0),
                "captured": at is not None,
            }
        super()._end(mid, publish)

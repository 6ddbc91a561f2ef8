"""Searching as a team on the mission clock: what a robot agent runs under `--team-clock seconds`,
when each move takes its own travel time and the robots' steps drift apart (docs/continuous-world.md).

The step rule (shared/core/team.py) matches the teammates' observations by step index and waits
for the current step's; with travel times a teammate's step t comes seconds or minutes later, so
the rule falls back to the robot's own policy for most decisions. On the clock instead:

- **Time model.** The mission clock is cut into ticks of ``tick_s`` seconds (1 s). The target
  moves once a tick with the version's Gamma_hat made a tick's worth (uniformization of the step
  model: Gamma_tick = I + (tick_s / step_s)(Gamma_hat - I), ``step_s`` the seconds one step of the
  model lasts: the graph's median move at the robot's speed). An observation is folded in at the
  tick its reading was made (k = floor(time_s / tick_s)), whenever it comes: a late one re-filters
  from its tick, exactly as on time (``CollectiveBelief`` keyed by tick). No tick is waited for.
- **Teammates in transit.** Each observation carries the node its robot left for (``goal``); the
  team's plan counts a teammate where it is headed.
- **Deciding.** On arrival, at once: the team's plan (FHPE-SA on the collective belief predicted
  to the current tick) when some teammate has been heard within ``timeout_s``, or at the mission's
  start (time 0: every robot is on the start node), and the links deliver (``link_quality``, as
  in team.py); its own policy otherwise. A decision is "team" when
  every teammate in the plan has been heard, "partial" when one is placed at the start node.
- **Links.** A teammate's observation counts as heard in time when it comes before this robot's
  first decision more than ``late_s`` after the reading: the network's delay, not the spread of
  travel times, decides whether the links are good.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from shared.core.clock import TICK_S, move_seconds, step_model, tick_model
from shared.core.fhpe_sa import HORIZON, FhpeSAPlanner
from shared.core.graph import Graph
from shared.core.snapshot_format import SnapshotData
from shared.core.team import TeamAgent

TIMEOUT_S = 120.0  # a teammate not heard for this long leaves the team's plan (a move takes 4-25 s)
LATE_S = 2.0  # a teammate's observation arriving this long after its reading's decision time is late


class TimedTeamAgent(TeamAgent):
    """Robot ``me`` of the mission's ``robots`` on the mission clock: ``observe_at(robot, t, p, z,
    time_s, goal)`` for its own and its teammates' observations as they come, then
    ``act_at(time_s, p)`` -> (next node row, "team", "partial" or "own"). ``step_s``: the seconds a
    step of the version's model lasts (``move_seconds``). The rest as ``TeamAgent``."""

    def __init__(
        self,
        snap: SnapshotData,
        graph: Graph,
        robots: list[str],
        me: str,
        seed: int,
        searcher: str | None,
        step_s: float,
        tick_s: float = TICK_S,
        timeout_s: float = TIMEOUT_S,
        **kw: Any,
    ) -> None:
        if snap.clock is not None and abs(snap.clock[1] - tick_s) > 1e-9:
            raise ValueError(f"the version was trained with ticks of {snap.clock[1]:g} s, the agent's are {tick_s:g} s")
        if snap.clock is not None and searcher == "fhpe-sa" and kw.get("planner") is None:
            # FHPE-SA moves once a step: a version trained on the clock gives it its model a step's worth
            trained_step_s = move_seconds(graph, snap.clock[0])  # a step at the speed it was trained at
            plan_model = kw.get("team_model") or step_model(snap.model, trained_step_s, snap.clock[1])
            kw["planner"] = FhpeSAPlanner(graph, plan_model, snap.sensor, HORIZON)
        # a team trained on the clock (`mures train --speed`) has its model per tick already, and its
        # own belief predicts every tick between readings; a --team-model, like a team of steps, is per step
        per_tick = snap.clock is not None and kw.get("team_model") is None
        model = kw.get("team_model") or snap.model
        kw["collective_model"] = model if per_tick else tick_model(model, step_s, tick_s)  # Gamma per tick
        super().__init__(snap, graph, robots, me, seed, searcher, **kw)
        self.tick_s, self.step_s, self.timeout_s = tick_s, step_s, timeout_s
        self.own_tick = 0  # the tick of this robot's latest reading
        self.heard_s = {r: -math.inf for r in self.robots if r != me}  # each teammate's latest reading's time
        self.goal: dict[str, int] = {}  # each robot's latest known node: where it is headed
        self.decided_s = -math.inf
        self.reading_s: dict[tuple[str, int], float] = {}  # (robot, t) -> the time of its step-t reading, as heard

    def tick(self, time_s: float) -> int:
        return max(0, math.floor(time_s / self.tick_s + 1e-9))

    def observe_at(self, robot: str, t: int, p: int, z: int, time_s: float, goal: int | None = None) -> None:
        """An observation (this robot's own, or a teammate's from the network) of the reading made
        at ``time_s`` on node row ``p``; ``goal`` the row it left for (None: not known yet)."""
        if robot == self.me:
            k = self.tick(time_s)
            if t == 0:
                self.own.reset(p, z)
            else:  # per tick: every tick since its last reading; per step: one step
                self.own.observe(p, z, k - self.own_tick if self.snap.clock is not None else 1)
            self.own_tick = k
        if robot not in self.robots:
            return
        self.reading_s[robot, t] = time_s
        self.collective.add(self.tick(time_s), robot, p, z)  # a second reading in one tick is not folded in
        if robot == self.me or t < self.last_heard[robot]:
            return
        if t > self.last_heard[robot]:  # a first copy of its latest step
            self.messages_heard += time_s > self.decided_s - LATE_S  # in time for the decisions after it
            self.last_heard[robot] = t
            self.heard_s[robot] = max(self.heard_s[robot], time_s)
            self.goal[robot] = p
        if goal is not None:
            self.goal[robot] = goal

    def _heading(self) -> np.ndarray:
        """The node rows the teammates not withdrawn were last heard to be headed for."""
        rows = [self.goal[r] for r in self.robots if r != self.me and r not in self.withdrawn and r in self.goal]
        return np.array(rows, dtype=np.int64)

    def _team_live(self, now_s: float) -> list[str]:
        """This robot and the teammates not withdrawn that were heard within ``timeout_s`` (all of
        them in the mission's first ``timeout_s``)."""
        return [
            r
            for r in self.robots
            if r not in self.withdrawn
            and (r == self.me or now_s - self.heard_s[r] <= self.timeout_s or now_s <= self.timeout_s)
        ]

    def act_at(self, time_s: float, p: int) -> tuple[int, str]:
        """The next node row for this robot, arrived on row ``p`` at ``time_s`` (its own
        observation given), and how it was decided (module docstring)."""
        self.decided_s = time_s
        if self.searcher is None:
            return self._own(p, self._heading())
        live = self._team_live(time_s)
        heard = [r for r in live if r != self.me and self.heard_s[r] > -math.inf]
        poor_links = not self.alone() and self.link_quality() < self.link_quality_min
        # at the mission's start every robot is on the start node: its teammates are known to be there
        # before any is heard; later a robot that hears none cannot tell their absence from its link's
        if (not heard and not self.alone() and time_s > 0) or poor_links:
            return self._own(p, self._heading())
        mode = "team" if len(heard) == len(live) - 1 else "partial"
        self.steps[mode] += 1
        k = self.tick(time_s)
        b = self.collective.belief(k)
        if self.searcher == "c-cepg":
            return self.own.act(p, belief=b), mode
        assert self.planner is not None
        pos = np.array([p if r == self.me else self.goal.get(r, self.graph.start) for r in self.robots], dtype=np.int64)
        active = np.array([r in live for r in self.robots])
        row = int(self._team_plan(k, b, pos, active)[self.index])
        self.goal[self.me] = row
        return row, mode

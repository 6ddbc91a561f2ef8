"""A team of robot agents flown in the batched simulator over a simulated network: what
`mures evaluate --searcher policy:DIR --team-searcher S --link-loss P --link-delay K` runs.

Each robot of each episode is a ``TeamAgent`` (shared/core/team.py), the decision code a robot
agent runs. After every step each robot's observation (t, node, z) goes to each teammate as its
own message: lost with probability ``link_loss``, else delivered ``link_delay`` steps later (0:
before the teammates decide at that step). A withdrawn robot sends nothing and stays put; with
``known_withdrawals`` its teammates learn it at once (as robot agents do when its liveliness
token goes: ``TeamAgent.withdraw``, which switches them to the team built for the robots left),
else only from its silence. Each
robot starts with what the same link delivered over its earlier missions (``HISTORY_SENT``
messages), as a robot agent that has flown on that network has measured it.

Robots with the same information compute the same plan; the plans are memoised per episode and
step by what they are computed from, which changes no decision and saves the N - 1 identical
computations a team makes when its links are up.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from shared.core.clock import TravelTimes
from shared.core.fhpe_sa import FhpeSAPlanner
from shared.core.graph import Graph
from shared.core.models import TargetModel
from shared.core.snapshot_format import SnapshotData
from shared.core.team import (
    FALLBACK_AFTER,
    LINK_QUALITY_MIN,
    TIMEOUT_STEPS,
    LinkHistory,
    TeamAgent,
    mission_seed,
)
from shared.core.timed_team import TimedTeamAgent
from shared.engine.sim import Obs

# the teammates' observations a robot has heard of over its earlier missions when an evaluation
# starts: its steady state with LINK_MEMORY = 0.9 and 60 a mission (3 teammates, 20 steps)
HISTORY_SENT = 600


class LinkedTeamSearcher:
    """The batched searcher of robots flying ``TeamAgent``s of ``snap`` with team searcher
    ``searcher`` ("fhpe-sa", "c-cepg", or None: each on its own policy) over links that lose a
    message with probability ``link_loss`` and delay it by ``link_delay`` steps."""

    shares_planner = True  # one planner for every robot (the plan's model is the team's)

    def __init__(
        self,
        snap: SnapshotData,
        graph: Graph,
        n_robots: int,
        seed: int = 0,
        searcher: str | None = "fhpe-sa",
        link_loss: float = 0.0,
        link_delay: int = 0,
        fallback_after: int | None = FALLBACK_AFTER,
        timeout_steps: int = TIMEOUT_STEPS,
        counter: dict[str, int] | None = None,
        team_model: TargetModel | None = None,
        link_quality_min: float = LINK_QUALITY_MIN,
        history_sent: int = HISTORY_SENT,
        known_withdrawals: bool = False,
    ) -> None:
        if not 0.0 <= link_loss <= 1.0:
            raise ValueError(f"link loss {link_loss} is not a probability in [0, 1]")
        if link_delay < 0:
            raise ValueError(f"link delay {link_delay} must be 0 or more steps")
        self.name = f"team:{searcher or 'none'}"
        self.snap, self.graph, self.N = snap, graph, n_robots
        self.searcher, self.link_loss, self.link_delay = searcher, link_loss, link_delay
        self.fallback_after, self.timeout_steps = fallback_after, timeout_steps
        self.rng = np.random.default_rng(seed)  # the missions' seeds
        self.link_rng = np.random.default_rng([seed, 1])  # the lost messages
        self.robots = [f"r{i + 1}" for i in range(n_robots)]
        self.team_model, self.link_quality_min, self.history_sent = team_model, link_quality_min, history_sent
        self.known_withdrawals = known_withdrawals
        model = team_model or snap.model
        shared = searcher == "fhpe-sa" and self.shares_planner
        self.planner = FhpeSAPlanner(graph, model, snap.sensor) if shared else None
        self.teams: dict[int, list[TeamAgent]] = {}  # slot -> the episode's robots
        self.inbox: dict[int, list[tuple[int, int, str, int, int, int]]] = {}  # slot -> (due, to, from, t, p, z)
        # robot-steps flown on the team's plan and on a robot's own policy, over every episode
        # (``counter``: shared by the searchers of one evaluation's chunks)
        self.steps = counter if counter is not None else {"team": 0, "partial": 0, "own": 0}

    def _begin(self, slot: int) -> None:
        mission = int(self.rng.integers(2**31))
        plans: dict[Any, np.ndarray] = {}
        team = []
        for i, r in enumerate(self.robots):
            agent = TeamAgent(
                self.snap,
                self.graph,
                self.robots,
                r,
                seed=mission,
                searcher=self.searcher,
                fallback_after=self.fallback_after,
                timeout_steps=self.timeout_steps,
                own_seed=mission_seed(mission, i),
                planner=self.planner,
                plan_cache=plans,
                team_model=self.team_model,
                link_quality_min=self.link_quality_min,
                link_history=self._history(),
            )
            team.append(agent)
        self.teams[slot], self.inbox[slot] = team, []

    def _history(self) -> LinkHistory:
        """What a robot's links delivered before this mission: ``history_sent`` messages over the
        same link, each delivered in time with probability 1 - link_loss (0 when delayed)."""
        in_time = 1.0 - self.link_loss if self.link_delay == 0 else 0.0
        heard = self.link_rng.binomial(self.history_sent, in_time)
        return LinkHistory(heard=float(heard), sent=float(self.history_sent))

    def act(self, obs: Obs) -> torch.Tensor:
        pos, z, t_all = obs.pos.numpy(), obs.z.numpy(), obs.t.numpy()
        active, new, alive = obs.active.numpy(), obs.new.numpy(), obs.alive.numpy()
        out = pos.copy()
        for e in (int(x) for x in np.nonzero(alive)[0]):
            if new[e] or e not in self.teams:
                self._begin(e)
            team, inbox, t = self.teams[e], self.inbox[e], int(t_all[e])
            for i, agent in enumerate(team):
                if not active[e, i]:
                    if self.known_withdrawals:
                        for mate in team:
                            mate.withdraw(agent.me)
                    continue
                p, zi = int(pos[e, i]), int(z[e, i])
                agent.observe(agent.me, t, p, zi)
                for j in range(self.N):
                    if j != i and self.link_rng.random() >= self.link_loss:
                        inbox.append((t + self.link_delay, j, agent.me, t, p, zi))
            due = [m for m in inbox if m[0] <= t]
            inbox[:] = [m for m in inbox if m[0] > t]
            for _due, j, sender, s, p, zi in due:
                team[j].observe(sender, s, p, zi)
            for i, agent in enumerate(team):
                if active[e, i]:
                    out[e, i], mode = agent.act(t, int(pos[e, i]))
                    self.steps[mode] += 1
        return torch.as_tensor(out)


class TimedLinkedTeamSearcher(LinkedTeamSearcher):
    """The team flown on the mission clock in the engine's travel times (``SearchSim(move_ticks=)``):
    what `mures evaluate --clock --team-searcher S` runs. Each robot is a ``TimedTeamAgent``
    (shared/core/timed_team.py), the code a robot agent runs under `--team-clock seconds`. A robot
    that arrives at tick t reads z at t ``clock.tick_s``, decides at once on what its links have
    delivered, and sends its observation with its goal to each teammate: lost with probability
    ``link_loss``, else delivered ``link_delay`` ticks later, and never before the next tick, so
    robots that decide at the same tick decide on the same information. ``link_delay`` counts ticks."""

    shares_planner = False  # each TimedTeamAgent builds the planner its version needs (a step's worth)

    def __init__(self, snap: SnapshotData, graph: Graph, n_robots: int, clock: TravelTimes, *a: Any, **kw: Any) -> None:
        super().__init__(snap, graph, n_robots, *a, **kw)
        self.clock = clock
        self.timed: dict[int, list[TimedTeamAgent]] = {}
        self.readings: dict[int, list[int]] = {}  # slot -> each robot's readings so far
        # slot -> messages (due tick, to, from, its reading's index, node, z, time_s, goal)
        self.mail: dict[int, list[tuple[int, int, str, int, int, int, float, int]]] = {}

    def _begin(self, slot: int) -> None:
        mission = int(self.rng.integers(2**31))
        self.timed[slot] = [
            TimedTeamAgent(
                self.snap,
                self.graph,
                self.robots,
                r,
                seed=mission,
                searcher=self.searcher,
                step_s=self.clock.step_s,
                tick_s=self.clock.tick_s,
                fallback_after=self.fallback_after,
                own_seed=mission_seed(mission, i),
                team_model=self.team_model,
                link_quality_min=self.link_quality_min,
                link_history=self._history(),
            )
            for i, r in enumerate(self.robots)
        ]
        self.mail[slot], self.readings[slot] = [], [0] * self.N

    def act(self, obs: Obs) -> torch.Tensor:
        pos, z, t_all = obs.pos.numpy(), obs.z.numpy(), obs.t.numpy()
        active, new, alive = obs.active.numpy(), obs.new.numpy(), obs.alive.numpy()
        ready = np.ones_like(active) if obs.ready is None else obs.ready.numpy()
        out = pos.copy()
        for e in (int(x) for x in np.nonzero(alive)[0]):
            if new[e] or e not in self.timed:
                self._begin(e)
            team, inbox, count, t = self.timed[e], self.mail[e], self.readings[e], int(t_all[e])
            now_s = t * self.clock.tick_s
            due = [m for m in inbox if m[0] <= t]
            inbox[:] = [m for m in inbox if m[0] > t]
            for _due, j, sender, k, p, zi, at_s, goal in due:
                team[j].observe_at(sender, k, p, zi, at_s, goal)
            if self.known_withdrawals:  # its liveliness token gone: its teammates drop it at once
                for gone in np.nonzero(~active[e])[0]:
                    for mate in team:
                        mate.withdraw(team[int(gone)].me)
            deciding = [i for i in range(self.N) if active[e, i] and ready[e, i]]
            for i in deciding:
                p, zi = int(pos[e, i]), int(z[e, i])
                team[i].observe_at(team[i].me, count[i], p, zi, now_s)
                row, mode = team[i].act_at(now_s, p)
                out[e, i] = row
                self.steps[mode] += 1
                sent = (team[i].me, count[i], p, zi, now_s, row)  # with where the robot is headed
                for j in range(self.N):
                    if j != i and self.link_rng.random() >= self.link_loss:
                        inbox.append((t + max(1, self.link_delay), j, *sent))
                count[i] += 1
        return torch.as_tensor(out)


def linked_team(
    snap: SnapshotData,
    graph: Graph,
    n_robots: int,
    seed: int,
    searcher: str | None,
    clock: TravelTimes | None = None,
    **kw: Any,
) -> LinkedTeamSearcher:
    """The robots' team flight: in steps (``LinkedTeamSearcher``), or on the mission clock when the
    evaluation runs on ``clock``'s travel times (``TimedLinkedTeamSearcher``). ``kw``: the links
    and the rest, as both take them."""
    if clock is not None:
        return TimedLinkedTeamSearcher(snap, graph, n_robots, clock, seed, searcher, **kw)
    return LinkedTeamSearcher(snap, graph, n_robots, seed, searcher, **kw)

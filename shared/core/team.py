"""Searching as a team (paper Theorem 3, Eq. 6-7) on a network that may lose, delay, repeat or
reorder messages: what a robot agent runs, in numpy.

Each robot publishes every step's observation (t, node, z) and receives its teammates'. From
them it keeps the team's collective belief,

    b^c_t ∝ Lambda^c_t Gamma_hat^T b^c_{t-1},   Lambda^c_t = prod_i Lambda(p^i_t, z^i_t)   (Eq. 6-7),

beside its own (Eq. 1, ``PolicyAgent``), and decides with the version's team searcher when the
collective belief is complete, with its own decentralised policy when it is not:

- ``CollectiveBelief`` holds every observation by (t, robot) and the belief after each step. An
  observation of an earlier step re-filters from that step on (O(n + m) a step, microseconds for
  a short replay), so a late observation changes the belief exactly as if it had come on time; a
  second copy is ignored; a teammate's step that never comes counts as no observation from it.
- ``TeamAgent`` is one robot's decision: the team's plan when every live teammate's observation
  of the current step is in (``complete``), the team's plan on what has come when one is missing
  but at least half of the teammates were heard at this step or the last (the others at their
  last known positions), its own policy on its own belief otherwise (or after ``fallback_after``
  incomplete steps in a row, if set; back to the team's plan once complete again), and throughout
  while its links deliver too few of the teammates' observations in time (``LinkHistory``). A
  teammate silent for ``timeout_steps`` steps is dropped from the team's plan, and taken in again
  when it reports. Its own policy is the version's team built for the mission's robots where the
  version holds one (``SnapshotData.team_for``); a teammate known to have dropped out (its
  liveliness token gone: ``withdraw``) leaves the plan at once, and the robot flies the team
  built for the robots left from its next decision where the version switches to it.

Team searchers: ``fhpe-sa`` (FHPE-SA on the team's model, every robot computing the whole team's
plan from its own copy of the same information, ties broken by a generator seeded by the mission
and the step, so that identical information gives identical plans without negotiation) and
``c-cepg`` (the version's network on the collective belief). The team's model is the version's
own unless another is given (``team_model``): planning needs a model good enough to plan with,
which a fleet's growing record of missions provides.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from shared.core.belief_filter import TINY, BeliefFilter
from shared.core.choices import TEAM_SEARCHERS
from shared.core.fhpe_sa import HORIZON, FhpeSAPlanner
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.core.snapshot_format import PolicyAgent, SnapshotData

# incomplete steps in a row before a robot flies its own policy; None: never while a teammate is
# heard. Measured (benchmarks/coordination.py, OFFICE N = 4, 200 episodes, links losing 30 % of the
# messages): falling back at every incomplete step captured in 10.34 steps, later than the robots'
# own policies alone (10.18), and planning on what has come in 7.72 (links up: 7.00)
FALLBACK_AFTER: int | None = None
# A robot plans with its team when at least half of its live teammates' last observations are at
# most STALE_STEPS old, and flies its own policy otherwise. On OFFICE N = 4 (300 paired episodes,
# benchmarks/coordination.py; the robots' own policies alone: 8.17), planning on any teammate heard
# within the timeout captured in 7.13 / 7.82 / 8.15 / 9.52 steps with 10 / 30 / 50 / 90 % of the
# messages lost, and planning only when every teammate is that recent in 7.63 / 8.63 / 9.12 / 8.12:
# mixing the robots' own decisions into the team's costs at moderate loss, stale plans at high loss
STALE_STEPS = 1
# A robot plans with its team only while its links deliver at least LINK_QUALITY_MIN of its
# teammates' observations in time for its decision at their step, over this mission and its
# earlier ones (``LinkHistory``), for three reasons measured with benchmarks/coordination.py:
# - planning whenever some teammate was heard gains up to about 40 % loss and loses beyond: on
#   OFFICE N = 4 (300 paired episodes, the robots' own policies alone 8.17) 7.61 / 8.14 / 8.95 /
#   9.33 steps with 30 / 50 / 70 / 90 % of the messages lost;
# - team and own decisions mixed in one mission cost more than either (a robot off the team's plan
#   leaves a hole in it), and a per-mission estimate mixes them: deciding on each mission's
#   messages alone captured in 7.84 / 11.45 / 13.02 / 8.67 steps at the same losses; the link's
#   history, alike for the robots of a fleet on one network, makes them decide alike;
# - planning on the teammates' positions of the step before (every message one step late) gained
#   on MUSEUM N = 4 (2.94 ± 2.15 steps sooner than the own policies) and lost on OFFICE N = 5
#   (0.95 ± 0.61 later; 400 paired episodes each): a late message counts as lost, so that the
#   team is never worse than its robots alone.
LINK_QUALITY_MIN = 0.6
LINK_MEMORY = 0.9  # the weight of a mission's messages in ``LinkHistory``, per mission since
TIMEOUT_STEPS = 3  # steps without a teammate's observation before it is dropped from the plan


def team_searcher_of(snap: SnapshotData) -> str | None:
    """The team searcher a policy version carries: its ``team_searcher`` (meta), "c-cepg" for a
    c-cepg snapshot without one, else None (each robot on its own policy, as before teams)."""
    given = snap.meta.get("team_searcher")
    if given in TEAM_SEARCHERS:
        return str(given)
    return "c-cepg" if snap.variant == "c-cepg" and given is None else None


def mission_seed(seed: int, index: int) -> int:
    """The action-sampling seed of the robot at ``index`` in a mission's robot list."""
    return (int(seed) * 1_000_003 + 7_919 * (index + 1)) % (2**63)


@dataclass
class LinkHistory:
    """The teammates' observations a robot's links delivered (``heard``) of those sent
    (``sent``) over its earlier missions, each mission weighted by LINK_MEMORY per mission since:
    how good its network is, steady across the robots of a fleet, so that they decide alike."""

    heard: float = 0.0
    sent: float = 0.0

    def fold(self, heard: int, sent: int) -> None:
        """Add a finished mission's counts (``TeamAgent.link_counts``)."""
        self.heard = LINK_MEMORY * self.heard + heard
        self.sent = LINK_MEMORY * self.sent + sent


class CollectiveBelief:
    """The collective belief of the robots ``robots`` (the mission's order), from observations
    added in any order: ``add(t, robot, p, z)``, then ``belief(t)`` -> b^c_t (n,)."""

    def __init__(self, graph: Graph, model: TargetModel, sensor: Sensor, robots: list[str]) -> None:
        self.n, self.robots = graph.n, list(robots)
        self._order = {r: i for i, r in enumerate(self.robots)}
        self._b0 = model.b0.copy()
        self._filter = BeliefFilter(graph, model, sensor)  # its weigh (Lambda(p, z)) and predict_of (Gamma_hat^T b)
        self.obs: list[dict[str, tuple[int, int]]] = []  # obs[t][robot] = (p, z)
        self._beliefs: list[np.ndarray] = []  # b^c_0 .. b^c_{k-1}, valid while no earlier step changes
        self.restarts = 0

    def add(self, t: int, robot: str, p: int, z: int) -> bool:
        """Fold in robot ``robot``'s observation of step ``t``; False (and nothing changes) for a
        robot outside the team or a step already reported by it (a second copy)."""
        if robot not in self._order or t < 0:
            return False
        while len(self.obs) <= t:
            self.obs.append({})
        if robot in self.obs[t]:
            return False
        self.obs[t][robot] = (int(p), int(z))
        del self._beliefs[t:]  # re-filtered from step t on when next asked
        return True

    def reported(self, t: int) -> set[str]:
        """The robots whose observation of step ``t`` is in."""
        return set(self.obs[t]) if t < len(self.obs) else set()

    def position(self, robot: str, t: int) -> tuple[int, int] | None:
        """(step, node row) of ``robot``'s latest observation at or before ``t``, or None."""
        for s in range(min(t, len(self.obs) - 1), -1, -1):
            if robot in self.obs[s]:
                return s, self.obs[s][robot][0]
        return None

    def likelihood(self, t: int) -> np.ndarray:
        """Lambda^c_t's diagonal (Eq. 7): the product of the reported robots' Lambda(p, z), in the
        mission's order (the same product whatever order the observations came in)."""
        lik = np.ones(self.n)
        got = self.obs[t] if t < len(self.obs) else {}
        for robot in sorted(got, key=self._order.__getitem__):
            self._filter.weigh(lik, *got[robot])
        return lik

    def belief(self, t: int) -> np.ndarray:
        """b^c_t (Eq. 6; t = 0: b^c_0 ∝ Lambda^c_0 b0, Theorem 2), re-filtering from the first step
        an observation changed. A vanished mass restarts from the step's observations alone (then
        uniform), as ``BatchedBelief.normalise`` does."""
        for s in range(len(self._beliefs), t + 1):
            lik = self.likelihood(s)
            prior = self._b0 if s == 0 else self._filter.predict_of(self._beliefs[s - 1])
            x = lik * prior
            total = x.sum()
            if total <= TINY:
                self.restarts += 1
                x, total = lik.copy(), lik.sum()
                if total <= TINY:
                    x, total = np.full(self.n, 1.0 / self.n), 1.0
            self._beliefs.append(x / total)
        return self._beliefs[t]


class TeamAgent:
    """Robot ``me`` of the mission's ``robots``: ``observe(robot, t, p, z)`` for its own and its
    teammates' observations as they come, then ``act(t, p)`` -> (next node row, "team" or "own").

    ``searcher``: "fhpe-sa", "c-cepg" or None (always its own policy, as before teams). The own
    policy is the snapshot's decentralised one; a c-cepg snapshot's network is flown on the
    robot's own belief when it falls back. The collective belief and the plan use ``team_model``
    (default the snapshot's model, which its own policy keeps)."""

    def __init__(
        self,
        snap: SnapshotData,
        graph: Graph,
        robots: list[str],
        me: str,
        seed: int,
        searcher: str | None,
        fallback_after: int | None = FALLBACK_AFTER,
        timeout_steps: int = TIMEOUT_STEPS,
        own_seed: int | None = None,
        planner: FhpeSAPlanner | None = None,
        plan_cache: dict[Any, np.ndarray] | None = None,
        team_model: TargetModel | None = None,
        link_quality_min: float = LINK_QUALITY_MIN,
        link_history: LinkHistory | None = None,
        collective_model: TargetModel | None = None,
    ) -> None:
        if searcher is not None and searcher not in TEAM_SEARCHERS:
            raise ValueError(f"team searcher {searcher!r}: expected one of {', '.join(TEAM_SEARCHERS)}")
        if (fallback_after is not None and fallback_after < 1) or timeout_steps < 1:
            raise ValueError("fallback_after and timeout_steps must be at least 1")
        self.graph, self.robots, self.me = graph, list(robots), me
        self.index = self.robots.index(me)
        self.seed, self.searcher = int(seed), searcher
        self.fallback_after, self.timeout_steps = fallback_after, timeout_steps
        self.snap = snap
        self.withdrawn: set[str] = set()  # teammates known to have dropped out (``withdraw``)
        team = snap.team_for(len(self.robots))
        self.own = PolicyAgent(team, graph, self.index, seed=self.seed if own_seed is None else own_seed, team=True)
        self.flown_for = team.robots if team is not snap else len(self.robots)  # the team size its policy is built for
        model = team_model or snap.model  # the team's (Gamma_hat, b0); the own policy keeps its own
        # the collective belief's model: the plan's, unless given (on the mission clock: per tick)
        self.collective = CollectiveBelief(graph, collective_model or model, snap.sensor, self.robots)
        if searcher == "fhpe-sa" and planner is None:
            planner = FhpeSAPlanner(graph, model, snap.sensor, HORIZON)
        self.planner = planner
        self.plan_cache = plan_cache  # plans by what they are computed from, shared by a simulated team
        self.incomplete_run = 0  # incomplete steps in a row
        self.link_quality_min, self.link_history = link_quality_min, link_history or LinkHistory()
        # teammates' observations received in time for the decision at their step (first copies),
        # each teammate's latest step heard, and the latest step decided
        self.messages_heard, self.last_heard = 0, {r: -1 for r in self.robots if r != me}
        self.decided = -1
        self.steps = {"team": 0, "partial": 0, "own": 0}

    def observe(self, robot: str, t: int, p: int, z: int) -> None:
        """An observation of step ``t`` (this robot's own, or a teammate's from the network)."""
        if robot == self.me:
            self.own.reset(p, z) if t == 0 else self.own.observe(p, z)
        if self.collective.add(t, robot, p, z) and robot != self.me:
            self.messages_heard += t > self.decided  # in time: before this robot decided at step t
            self.last_heard[robot] = max(self.last_heard[robot], t)

    def withdraw(self, robot: str) -> bool:
        """Teammate ``robot`` has dropped out of the mission (its liveliness token is gone): it
        leaves the team's plan now, and this robot's own policy becomes the team built for the
        robots left where the version holds one and switches to it (``SnapshotData.switches_to``;
        same belief). False (nothing changes) for this robot, a robot outside the mission or one
        withdrawn already."""
        if robot == self.me or robot not in self.robots or robot in self.withdrawn:
            return False
        self.withdrawn.add(robot)
        left = [r for r in self.robots if r not in self.withdrawn]
        if self.snap.switches_to(len(left)):
            self.own.fly(self.snap.team_for(len(left)), left.index(self.me))
            self.flown_for = len(left)
        return True

    def alone(self) -> bool:
        """This robot is the mission's only one, or every teammate has dropped out."""
        return len(self.robots) - len(self.withdrawn) == 1

    def _ages(self, t: int) -> dict[str, int | None]:
        """Each teammate's (not withdrawn) steps since its latest observation at or before ``t``
        (None: none yet)."""
        out: dict[str, int | None] = {}
        for r in self.robots:
            if r != self.me and r not in self.withdrawn:
                last = self.collective.position(r, t)
                out[r] = None if last is None else t - last[0]
        return out

    def live(self, t: int) -> list[str]:
        """The teammates in the team's plan at step ``t``: this robot, and each other robot not
        withdrawn that has reported within the last ``timeout_steps`` steps (all of them in the
        first steps)."""
        ages = self._ages(t)
        out = []
        for r in self.robots:
            age = ages.get(r)  # None for this robot, and for a teammate not heard yet
            if r in self.withdrawn:
                continue
            if r == self.me or (t < self.timeout_steps if age is None else age < self.timeout_steps):
                out.append(r)
        return out

    def heard(self, t: int) -> bool:
        """Some teammate has reported within the last ``timeout_steps`` steps. A robot that hears
        none cannot tell their absence from its own link being down, and flies its own policy."""
        return any(age is not None and age < self.timeout_steps for age in self._ages(t).values())

    def fresh(self, t: int) -> bool:
        """At least half of the other live robots' last observations are of step ``t`` or
        ``t - 1`` (``STALE_STEPS``): enough of the team known well enough to plan with."""
        ages = self._ages(t)
        others = [r for r in self.live(t) if r != self.me]
        recent = sum(1 for r in others if (age := ages[r]) is not None and age <= STALE_STEPS)
        return 2 * recent >= len(others)

    def complete(self, t: int) -> bool:
        """Every live teammate's observation of step ``t`` is in (and some teammate is heard)."""
        if self.alone():
            return True
        return self.heard(t) and set(self.live(t)) <= self.collective.reported(t)

    def act(self, t: int, p: int) -> tuple[int, str]:
        """The next node row for this robot at step ``t`` (its own observation of ``t`` given), and
        how it was decided: "team" (the team's plan, every live teammate's step in), "partial"
        (the team's plan on what has come: a teammate's step ``t`` missing, its last known position
        used) or "own" (its own policy: no team searcher, no teammate heard, fewer than half of
        the live teammates ``fresh``, ``fallback_after`` incomplete steps in a row, or too
        few of the teammates' observations delivered in time, ``link_quality``)."""
        self.decided = t
        if self.searcher is None:
            return self._own(p, self._mates(t))
        complete = self.complete(t)
        self.incomplete_run = 0 if complete else self.incomplete_run + 1
        usable = complete or (self.heard(t) and self.fresh(t))
        gave_up = self.fallback_after is not None and self.incomplete_run >= self.fallback_after
        poor_links = not self.alone() and self.link_quality() < self.link_quality_min
        if not usable or gave_up or poor_links:
            return self._own(p, self._mates(t))
        mode = "team" if complete else "partial"
        self.steps[mode] += 1
        b = self.collective.belief(t)
        if self.searcher == "c-cepg":
            return self.own.act(p, belief=b), mode
        assert self.planner is not None
        live = self.live(t)
        pos = np.array([self._where(r, t, p) for r in self.robots], dtype=np.int64)
        active = np.array([r in live and pos[i] >= 0 for i, r in enumerate(self.robots)])
        pos = np.where(pos >= 0, pos, p)
        return int(self._team_plan(t, b, pos, active)[self.index]), mode

    def link_counts(self) -> tuple[int, int]:
        """(teammates' observations heard in time for the decision at their step, sent) in this
        mission: a teammate's are counted as sent up to its latest step heard, so that a withdrawn
        teammate's silence is not taken for loss."""
        return self.messages_heard, sum(last + 1 for last in self.last_heard.values())

    def link_quality(self) -> float:
        """The share of the teammates' observations that arrived in time, over the earlier
        missions (``link_history``) and this one, counting one such message before the first."""
        heard, sent = self.link_counts()
        return (self.link_history.heard + heard + 1) / (self.link_history.sent + sent + 1)

    def _own(self, p: int, mates: np.ndarray) -> tuple[int, str]:
        """Its own policy on its own belief; the general policy also reads ``mates``, the teammates'
        latest known node rows."""
        self.steps["own"] += 1
        return self.own.act(p, mates=mates), "own"

    def _mates(self, t: int) -> np.ndarray:
        """The node rows of the teammates not withdrawn at their latest observations up to step
        ``t``, those heard at all."""
        rows = [self._where(r, t, -1) for r in self.robots if r != self.me and r not in self.withdrawn]
        return np.array([row for row in rows if row >= 0], dtype=np.int64)

    def _team_plan(self, t: int, b: np.ndarray, pos: np.ndarray, active: np.ndarray) -> np.ndarray:
        """FHPE-SA's moves for the whole team; its ties are broken by a generator seeded by the
        mission and the step, the same on every robot."""
        assert self.planner is not None
        cache = self.plan_cache
        key = (t, b.tobytes(), pos.tobytes(), active.tobytes())
        if cache is not None and key in cache:
            return cache[key]
        plan = self.planner.plan(b, pos, active, np.random.default_rng([self.seed, t]))
        if cache is not None:
            cache[key] = plan
        return plan

    def _where(self, robot: str, t: int, p: int) -> int:
        if robot == self.me:
            return p
        last = self.collective.position(robot, t)
        return -1 if last is None else last[1]

    def summary(self) -> dict[str, Any]:
        """This robot's decisions by how they were made (``act``), what its links delivered
        (``link_counts``), the teammates that dropped out and the team size its own policy was
        built for at the end (``withdraw``), as its record reports them."""
        return {
            "team_steps": self.steps["team"],
            "partial_steps": self.steps["partial"],
            "own_steps": self.steps["own"],
            "observations_heard": self.link_counts()[0],
            "observations_sent": self.link_counts()[1],
            "teammates_dropped": len(self.withdrawn),
            "flown_for": self.flown_for,
        }

"""Every searcher by name: the reference searchers (shared/engine), the paper's planners
(shared/planners) and trained teams (``policy:DIR``, shared/learning). It sits above those
packages, so none of them imports another's searchers."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from shared.core.clock import TravelTimes
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.engine.searchers import REFERENCE_SEARCHERS, GreedySearcher, RandomSearcher, Searcher
from shared.planners import BASELINES, make_baseline

SEARCHERS = REFERENCE_SEARCHERS + BASELINES  # plus the trained ones, POLICY_NAMES
POLICY_NAMES = ("general", "general:DIR", "policy:DIR")  # the shipped general policy, another one, a team


def _general_factory(
    name: str,
    graph: Graph,
    model: TargetModel,
    sensor: Sensor,
    n_robots: int,
    device: torch.device | str,
    clock: TravelTimes | None,
) -> Callable[[int], Searcher]:
    """`general` (the shipped general policy) or `general:DIR`: every robot flies it on its own
    belief with ``model``, as `greedy` does (shared/learning/general.py)."""
    from shared.core.snapshot_format import load_general, shipped_general_path
    from shared.learning.general import GeneralSearcher

    if clock is not None:
        raise ValueError("the general policy decides in steps: evaluate it without --clock")
    policy = load_general(shipped_general_path() if name == "general" else name.removeprefix("general:"))
    return lambda seed: GeneralSearcher(policy, graph, model, sensor, n_robots, seed=seed, device=device)


def make_searcher(
    name: str,
    graph: Graph,
    model: TargetModel,
    sensor: Sensor,
    seed: int = 0,
    device: torch.device | str = "cpu",
    n_robots: int = 1,
) -> Searcher:
    """Build a named searcher (not ``policy:DIR``: see ``searcher_factory``)."""
    if name in BASELINES:
        return make_baseline(name, graph, model, sensor, n_robots, seed=seed)
    if name == "random":
        return RandomSearcher(graph, seed=seed, device=device)
    if name == "greedy":
        return GreedySearcher(graph, model, sensor, seed=seed, device=device)
    raise ValueError(f"unknown searcher {name!r} (expected one of {', '.join((*SEARCHERS, *POLICY_NAMES))})")


def searcher_factory(
    name: str,
    graph: Graph,
    model: TargetModel,
    sensor: Sensor,
    n_robots: int,
    device: torch.device | str = "cpu",
    note: Callable[[str], None] | None = None,
    team: TeamFlight | None = None,
    clock: TravelTimes | None = None,
) -> Callable[[int], Searcher]:
    """seed -> searcher, for the evaluator. Checks the name, loads a ``policy:DIR`` snapshot and
    runs the searcher's own checks (the oracle's N <= 2, fhpe's node detection) once, before any
    simulation; raises ValueError (SnapshotError for a bad snapshot) with the reason. With ``team``,
    a ``policy:DIR`` is flown as robot agents fly it in a team (``LinkedTeamSearcher``: the agents'
    own decision code, over a simulated network).

    ``clock``: the evaluation runs on travel times (``model`` is then the model per tick): random,
    greedy and ``policy:DIR`` decide on arrival; a team trained in steps has its model made a tick's
    worth, one trained on the clock must have been trained with the same tick. A team trained on
    the clock is refused without one."""
    if clock is not None and name in BASELINES:
        raise ValueError(f"travel times fly random, greedy and policy:DIR (alone or as a team), not {name!r}")
    if name.startswith("policy:") and team is not None:
        return _team_factory(name.removeprefix("policy:"), graph, n_robots, team, note, clock)
    if name.startswith("policy:"):
        from shared.learning.team_snapshot import PolicySearcher, load_snapshot

        snap = load_snapshot(name.removeprefix("policy:"), graph, device=device)
        team_note = snap.team_note(n_robots)
        if team_note and note:
            note(team_note)
        trained = snap.clock
        if clock is None and trained is not None:
            raise ValueError(
                f"{name} was trained on the clock ({trained[0]:g} m/s, ticks of {trained[1]:g} s): its model is per "
                "tick; evaluate it on travel times (--clock)"
            )
        if clock is not None and trained is None:  # a team of steps on the clock: its model a tick's worth
            snap = dataclasses.replace(snap, model=clock.model(snap.model))
        elif clock is not None and trained is not None and abs(trained[1] - clock.tick_s) > 1e-9:
            raise ValueError(
                f"{name} was trained with ticks of {trained[1]:g} s, this evaluation's are {clock.tick_s:g} s"
            )
        return lambda seed: PolicySearcher(snap, graph, sensor, n_robots, seed=seed, device=device)
    if team is not None:
        raise ValueError(f"team flight (--team-searcher, --link-loss, --link-delay) flies a policy:DIR, not {name!r}")
    if name == "general" or name.startswith("general:"):
        return _general_factory(name, graph, model, sensor, n_robots, device, clock)

    def make(seed: int) -> Searcher:
        if name == "greedy" and clock is not None:  # its choice looks a step's worth of ticks ahead
            return GreedySearcher(graph, model, sensor, seed, device, lookahead=round(clock.ticks_per_step))
        return make_searcher(name, graph, model, sensor, seed=seed, device=device, n_robots=n_robots)

    if name not in SEARCHERS:
        raise ValueError(f"unknown searcher {name!r} (expected one of {', '.join((*SEARCHERS, *POLICY_NAMES))})")
    try:
        make(0)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None
    return make


@dataclass(frozen=True)
class TeamFlight:
    """How `mures evaluate` flies a snapshot as a team of agents (shared/engine/linked_team.py):
    its team searcher (None: the snapshot's own, see ``team_searcher_of``; "none": each robot on
    its own policy), each observation message's loss probability and delay in steps, and the
    incomplete steps before a robot falls back to its own policy, the model the team plans on.
    ``steps`` counts the robot-steps
    flown on the team's plan ("team"; "partial" with a teammate's step missing) and on a robot's own
    policy ("own") over the evaluation."""

    searcher: str | None = None
    link_loss: float = 0.0
    link_delay: int = 0
    fallback_after: int | None = None
    model: TargetModel | None = None  # the team's model (None: the snapshot's)
    steps: dict[str, int] = field(default_factory=lambda: {"team": 0, "partial": 0, "own": 0})


def _team_factory(
    path: str,
    graph: Graph,
    n_robots: int,
    team: TeamFlight,
    note: Callable[[str], None] | None,
    clock: TravelTimes | None = None,
) -> Callable[[int], Searcher]:
    """A team flight's searchers: robot agents' ``TeamAgent``s in steps, or their ``TimedTeamAgent``s
    on the ``clock`` (shared/engine/linked_team.py)."""
    from shared.core.snapshot_format import read_snapshot
    from shared.core.team import team_searcher_of
    from shared.engine.linked_team import linked_team
    from shared.learning.team_snapshot import torch_weights

    snap = read_snapshot(path, graph, legacy=torch_weights)
    searcher = team_searcher_of(snap) if team.searcher is None else team.searcher
    searcher = None if searcher == "none" else searcher
    team_note = snap.team_note(n_robots)
    if team_note and note:
        note(team_note)

    if clock is None and snap.clock is not None:
        raise ValueError(
            f"policy:{path} was trained on the clock ({snap.clock[0]:g} m/s): fly its team on travel times (--clock)"
        )

    def make(seed: int) -> Searcher:
        return linked_team(
            snap,
            graph,
            n_robots,
            seed,
            searcher,
            clock,
            link_loss=team.link_loss,
            link_delay=team.link_delay,
            fallback_after=team.fallback_after,
            counter=team.steps,
            team_model=team.model,
        )

    make(0)  # its checks (the link's loss and delay), once, before any simulation
    return make

"""Every searcher by name: the reference searchers (shared/engine), the paper's planners
(shared/planners) and trained teams (``policy:DIR``, shared/learning). It sits above those
packages, so none of them imports another's searchers."""

from __future__ import annotations

from collections.abc import Callable

import torch

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.engine.searchers import REFERENCE_SEARCHERS, GreedySearcher, RandomSearcher, Searcher
from shared.planners import BASELINES, make_baseline

SEARCHERS = REFERENCE_SEARCHERS + BASELINES  # plus policy:DIR


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
    raise ValueError(f"unknown searcher {name!r} (expected one of {', '.join((*SEARCHERS, 'policy:DIR'))})")


def searcher_factory(
    name: str,
    graph: Graph,
    model: TargetModel,
    sensor: Sensor,
    n_robots: int,
    device: torch.device | str = "cpu",
    note: Callable[[str], None] | None = None,
) -> Callable[[int], Searcher]:
    """seed -> searcher, for the evaluator. Checks the name, loads a ``policy:DIR`` snapshot and
    runs the searcher's own checks (the oracle's N <= 2, fhpe's node detection) once, before any
    simulation; raises ValueError (SnapshotError for a bad snapshot) with the reason."""
    if name.startswith("policy:"):
        from shared.learning.team_snapshot import PolicySearcher, load_snapshot

        snap = load_snapshot(name.removeprefix("policy:"), graph, device=device)
        team = snap.team_note(n_robots)
        if team and note:
            note(team)
        return lambda seed: PolicySearcher(snap, graph, sensor, n_robots, seed=seed, device=device)

    def make(seed: int) -> Searcher:
        return make_searcher(name, graph, model, sensor, seed=seed, device=device, n_robots=n_robots)

    if name not in SEARCHERS:
        raise ValueError(f"unknown searcher {name!r} (expected one of {', '.join((*SEARCHERS, 'policy:DIR'))})")
    try:
        make(0)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None
    return make

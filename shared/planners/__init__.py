"""The paper's comparison planners (section V): fhpe, fhpe-sa, milp, d-milp and the oracle, as
batched searchers for the evaluator. ``make_baseline`` builds one by name; the registry of every
searcher (shared/registry.py) sits above this package."""

from __future__ import annotations

from typing import Any

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.planners.fhpe import Fhpe, FhpeSA
from shared.planners.milp import Milp
from shared.planners.oracle import OracleSearcher

BASELINES = ("fhpe", "fhpe-sa", "milp", "d-milp", "oracle")


def make_baseline(
    name: str, graph: Graph, model: TargetModel, sensor: Sensor, n_robots: int, seed: int = 0, **kw: float
) -> Any:
    if name == "fhpe":
        return Fhpe(graph, model, sensor, seed)
    if name == "fhpe-sa":
        return FhpeSA(graph, model, sensor, seed, horizon=int(kw.get("horizon", 5)))
    if name in ("milp", "d-milp"):
        return Milp(
            graph,
            model,
            sensor,
            seed,
            horizon=int(kw.get("horizon", 5)),
            time_limit=float(kw.get("time_limit", 2.0)),
            distributed=name == "d-milp",
        )
    if name == "oracle":
        return OracleSearcher(graph, model, sensor, n_robots, seed)
    raise ValueError(f"unknown baseline {name!r}")

"""The mission clock's units: ticks of ``tick_s`` seconds, each move of the graph a whole number of
ticks, and the target's step model made a tick's worth (docs/continuous-world.md, "The time model").

Shared by the agents' teamwork on the clock (shared/core/timed_team.py), the continuous world
(shared/world/continuous.py) and the engine's travel times (shared/engine/sim.py ``move_ticks``).
One step of the paper's model lasts ``step_s`` seconds: the graph's median move at the robot's
speed. A graph whose every move is one tick is the paper's model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from shared.core.graph import Graph
from shared.core.models import TargetModel

TICK_S = 1.0  # the mission clock's tick
MAX_MOVE_TICKS = 100_000  # a move longer than this many ticks is a speed given in the wrong unit


def has_edge_lengths(graph: Graph) -> bool:
    """Whether the graph holds its edges' lengths (a graph from `mures map import`), which the
    mission clock needs."""
    return graph.edge_lengths is not None and len(graph.edge_lengths) > 0


def edge_lengths(graph: Graph) -> np.ndarray:
    """(m,) the graph's edge lengths in metres; ValueError for a graph without them."""
    if not has_edge_lengths(graph):
        raise ValueError(
            f"{graph.name} has no edge lengths: the mission clock needs a graph from `mures map import` "
            "(edge_lengths_m)"
        )
    return np.asarray(graph.edge_lengths)


def move_seconds(graph: Graph, speed: float) -> float:
    """The seconds one step of the model lasts: the graph's median edge length (along free space)
    over the robot's speed. ValueError for a graph without edge lengths."""
    return float(np.median(edge_lengths(graph))) / speed


def default_time_limit_s(graph: Graph, speed: float) -> float:
    """A mission's default limit on the mission clock: the step limit's horizon (3 n steps) as 3 n
    moves of the median edge at ``speed``, to 0.1 s. ValueError for a graph without edge lengths."""
    return round(3 * graph.n * move_seconds(graph, speed), 1)


def tick_model(model: TargetModel, step_s: float, tick_s: float = TICK_S) -> TargetModel:
    """The step model made one tick's worth (module docstring): Gamma_tick = I + a (Gamma - I),
    a = tick_s / step_s (at most 1); b0 unchanged. Gamma's support holds every self-loop."""
    a = min(1.0, tick_s / step_s)
    prob = a * model.prob + (1.0 - a) * (model.src == model.dst)
    return TargetModel(model.n, model.src, model.dst, prob, model.b0, f"{model.kind} per {tick_s:g} s tick")


def step_model(model: TargetModel, step_s: float, tick_s: float = TICK_S) -> TargetModel:
    """A model per tick made a step's worth, the inverse of ``tick_model``: Gamma_step = I + (step_s /
    tick_s)(Gamma_tick - I), where a row's stay would fall below 0 it is clipped to 0 and the row
    renormalised (a model per tick learned by EM can move faster than uniformization allows). What
    a planner that moves once a step (FHPE-SA) needs from a team trained on the clock."""
    r = max(1.0, step_s / tick_s)
    stay = model.src == model.dst
    prob = np.clip(r * model.prob + (1.0 - r) * stay, 0.0, None)
    prob = prob / np.bincount(model.src, weights=prob, minlength=model.n)[model.src]
    return TargetModel(model.n, model.src, model.dst, prob, model.b0, f"{model.kind} per {step_s:.3g} s step")


def move_ticks(graph: Graph, speed: float, tick_s: float = TICK_S) -> np.ndarray:
    """(n, n) int64: the ticks each move of N[p] takes at ``speed`` m/s, its edge's length over the
    speed rounded to whole ticks and at least one (a stay: one tick); 0 where a is not in N[p].
    ValueError for a graph without edge lengths or a speed or tick that is not above 0."""
    if not speed > 0 or not tick_s > 0:
        raise ValueError(f"speed and tick must be above 0, got {speed} m/s and {tick_s} s")
    per_move = edge_lengths(graph) / (speed * tick_s)
    if not np.isfinite(per_move).all() or per_move.max() > MAX_MOVE_TICKS:
        raise ValueError(
            f"at {speed:g} m/s a move of {graph.name} would take up to {per_move.max():.3g} ticks of {tick_s:g} s "
            f"(at most {MAX_MOVE_TICKS:,}): give a robot's real speed"
        )
    ticks = np.zeros((graph.n, graph.n), dtype=np.int64)
    np.fill_diagonal(ticks, 1)
    k = np.maximum(1, np.rint(per_move)).astype(np.int64)
    u, v = graph.edges[:, 0], graph.edges[:, 1]
    ticks[u, v] = k
    ticks[v, u] = k
    return ticks


@dataclass(frozen=True)
class TravelTimes:
    """A graph's moves on the mission clock at one speed: what the engine's travel times need."""

    ticks: np.ndarray  # (n, n) int64: ``move_ticks``
    tick_s: float  # the clock's tick
    step_s: float  # the seconds one step of the model lasts (``move_seconds``)
    speed: float  # the robots' speed, m/s

    @classmethod
    def of(cls, graph: Graph, speed: float, tick_s: float = TICK_S) -> TravelTimes:
        """ValueError for a graph without edge lengths or a speed or tick not above 0."""
        return cls(move_ticks(graph, speed, tick_s), tick_s, move_seconds(graph, speed), speed)

    @property
    def ticks_per_step(self) -> float:
        """Ticks one step of the model lasts (at least one)."""
        return max(1.0, self.step_s / self.tick_s)

    def summary(self) -> dict[str, float]:
        """What a run's or an evaluation's JSON says of the clock: speed, tick and step, in m/s and s."""
        return {"speed_m_s": self.speed, "tick_s": self.tick_s, "step_s": round(self.step_s, 3)}

    def t_max(self, n: int) -> int:
        """The paper's T_max = 3n steps, in ticks."""
        return 3 * n * round(self.ticks_per_step)

    def model(self, step_model: TargetModel) -> TargetModel:
        """A model of the target per step made one tick's worth (``tick_model``)."""
        return tick_model(step_model, self.step_s, self.tick_s)

"""Searchers: decision rules that map the simulator's observations to actions, batched.

A searcher sees ``Obs`` (positions, z, t, the ``new`` mask of fresh episodes) and returns
actions (B, N) in N[p]. Robots never share information unless a searcher says so (the
reference searchers do not). Exact definitions of the reference searchers: docs/SPEC.md section 4.
"""

from __future__ import annotations

from typing import Protocol

import torch

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.engine.batched_belief import BatchedBelief, BeliefTracker
from shared.engine.sim import Obs


class Searcher(Protocol):
    name: str

    def act(self, obs: Obs) -> torch.Tensor:
        """(B, N) actions (node rows in N[p]) for the current observations."""
        ...


class _Neighbourhoods:
    """Shared tables of N[p] for choosing among neighbours."""

    def __init__(self, graph: Graph, device: torch.device) -> None:
        self.nbr = torch.as_tensor(graph.nbr, device=device)  # (n, d)
        self.deg = torch.as_tensor(graph.deg_closed, device=device)  # (n,)
        d = self.nbr.shape[1]
        self.valid = torch.arange(d, device=device).unsqueeze(0) < self.deg.unsqueeze(1)  # (n, d)


class RandomSearcher:
    """`random`: every robot picks uniformly from N[p] (docs/SPEC.md section 4)."""

    name = "random"

    def __init__(self, graph: Graph, seed: int = 0, device: torch.device | str = "cpu") -> None:
        self.device = torch.device(device)
        self.tab = _Neighbourhoods(graph, self.device)
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(seed)

    def act(self, obs: Obs) -> torch.Tensor:
        u = torch.rand(obs.pos.shape, generator=self.gen, device=self.device)
        k = (u * self.tab.deg[obs.pos]).long().clamp_max(self.tab.nbr.shape[1] - 1)
        return self.tab.nbr[obs.pos, k]


class GreedySearcher:
    """`greedy`: each robot keeps its own belief (true Gamma) and moves to the node of N[p]
    with the largest predicted mass (Gamma^T b)(v); ties broken uniformly at random. With travel
    times (``model`` per tick) ``lookahead`` ticks, one step's worth: ((Gamma^k)^T b)(v).

    Nothing is shared between robots, so from one start node they tend to move as a pack.
    """

    name = "greedy"
    TIE_RTOL = 1e-5  # float32 beliefs: masses within this relative distance are a tie

    def __init__(
        self,
        graph: Graph,
        model: TargetModel,
        sensor: Sensor,
        seed: int = 0,
        device: torch.device | str = "cpu",
        lookahead: int = 1,
    ) -> None:
        self.device = torch.device(device)
        self.tab = _Neighbourhoods(graph, self.device)
        self.beliefs = BeliefTracker(BatchedBelief(graph, model, sensor, self.device))
        self.lookahead = lookahead  # on the clock (``model`` per tick): a move's worth of ticks ahead, (Gamma^k)^T b
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(seed)

    def act(self, obs: Obs) -> torch.Tensor:
        lik = self.beliefs.belief.likelihood(obs.pos, obs.z, obs.ready)  # (B, N, n); in transit: no reading
        _b, pred = self.beliefs.update(lik, obs.new)  # pred (B, N, n): (Gamma^T b_t)(v), own beliefs
        for _ in range(self.lookahead - 1):
            pred = self.beliefs.belief.predict(pred)
        cand = self.tab.nbr[obs.pos]  # (B, N, d)
        valid = self.tab.valid[obs.pos]
        mass = torch.gather(pred, 2, cand).masked_fill(~valid, -1.0)
        best = mass.max(dim=2, keepdim=True).values
        ties = valid & (mass >= best * (1 - self.TIE_RTOL))
        r = torch.rand(ties.shape, generator=self.gen, device=self.device).masked_fill(~ties, -1.0)
        return torch.gather(cand, 2, r.argmax(dim=2, keepdim=True)).squeeze(2)


REFERENCE_SEARCHERS = ("random", "greedy")

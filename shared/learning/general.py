"""Training the general policy (shared/core/graph_policy.py) with CE-PG on many buildings, and flying
it as a batched searcher (docs/general-policy.md).

One network for every building and team size. ``GraphTeam`` binds it to one graph and team size N
with the interface the CE-PG rollout and loss expect of a team (shared/learning/cepg.py: ``N``,
``slot_logits``, ``slot_allowed``, ``slot_nodes``, ``cross_probs``), so the update is Eq. 9-13 as
written there, over the slots of N[p] rather than the n nodes: robot i's policy is the network
with role i, pi_j(. | s^i) in the cross-entropy term is the network with role j on robot i's state
(a constant for robot i's gradient, Eq. 10), and J's units are divided by the building's own scale
(``j_unit``: the running mean capture time of that building and team), so that buildings of 30 and
of 300 rooms weigh alike in one update.

Recipe (``GeneralConfig``): a pool of generated office floors (``office_graph``, sizes log-uniform
in [min_nodes, max_nodes], N in [1, max_robots]; the paper's maps are never in it). First an
imitation phase (``imitate``, R2PS's pull toward a planner, as a start): FHPE-SA, which plans on
every robot's observations with the true model, flies ``imitation_episodes`` episodes on each pool
building and the network is fitted to its moves by cross-entropy (each robot's features on the
collective belief, with its role). Then CE-PG: each update draws one building and team size from
the pool (``floors_per_update`` distinct ones, their gradients averaged), flies a batch of episodes
with the network's stochastic policy, each robot on its own belief, and takes one Adam step; the
rollouts and the imitation phase's planner may run on a Dask cluster (``FloorWorkers``), with the
same numbers. The target is the uniform walk and the robots' beliefs use it; a
fleet's robots later keep theirs with the model EM learned, and the network reads whatever belief
it is given. The skip connection starts at "move toward the most likely node" (weight
``-SKIP_INIT`` on ``mode_distance_change``), so the first rollouts end; RL changes it from there.

Checkpoints (``checkpoint.pt`` in the output directory, every ``checkpoint_every`` seconds; removed
once the policy is written) hold the network, the optimiser, the update count and the random state:
the same command started again after a kill goes on from the last one.
"""

from __future__ import annotations

import math
import random
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from shared.core.fhpe_sa import FhpeSAPlanner
from shared.core.graph import Graph, office_graph
from shared.core.graph_policy import FEATURES, PARAMS, distances_of, feature_count, move_features, roles
from shared.core.models import Sensor, TargetModel, uniform_walk
from shared.core.snapshot_format import GeneralPolicy, load_general, save_general
from shared.engine.batched_belief import BatchedBelief, BeliefTracker
from shared.engine.sim import Obs, SearchSim
from shared.learning.cepg import cepg_loss, rollout
from shared.learning.policy import NEG_INF, sample

SKIP_INIT = 3.0
FEATURE_CHUNK = 1 << 22  # rows x d x n elements of hop distances gathered at once (16 MB of float32)
CHECKPOINT = "checkpoint.pt"


class GeneralNet(nn.Module):
    """The general policy's network in torch (``graph_policy.scores`` is its numpy twin):
    (..., d, F) -> (..., d), an MLP k -> H -> H -> 1 plus a linear skip on the first k = ``features``
    of the F features (``FEATURE_COUNTS``)."""

    def __init__(self, hidden: int = 64, features: int = len(FEATURES)) -> None:
        super().__init__()
        F = features
        k1, k2 = 1 / math.sqrt(F), 1 / math.sqrt(hidden)
        self.w1 = nn.Parameter(torch.empty(F, hidden).uniform_(-k1, k1))
        self.b1 = nn.Parameter(torch.zeros(hidden))
        self.w2 = nn.Parameter(torch.empty(hidden, hidden).uniform_(-k2, k2))
        self.b2 = nn.Parameter(torch.zeros(hidden))
        self.w3 = nn.Parameter(torch.empty(hidden).uniform_(-k2, k2) * 0.1)
        skip = torch.zeros(F)
        skip[FEATURES.index("mode_distance_change")] = -SKIP_INIT
        self.skip = nn.Parameter(skip)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        feats = feats[..., : self.w1.shape[0]]
        h = torch.relu(feats @ self.w1 + self.b1)
        h = torch.relu(h @ self.w2 + self.b2)
        return h @ self.w3 + feats @ self.skip

    def numpy_weights(self) -> dict[str, np.ndarray]:
        return {k: getattr(self, k).detach().cpu().numpy().astype(np.float32) for k in PARAMS}

    @classmethod
    def from_weights(cls, weights: dict[str, np.ndarray]) -> GeneralNet:
        """The network with these float32 weights (a snapshot's or a general policy's)."""
        net = cls(int(weights["b1"].shape[0]), feature_count(weights))
        with torch.no_grad():
            for k in PARAMS:
                getattr(net, k).copy_(torch.as_tensor(np.ascontiguousarray(weights[k])))
        return net


class GraphTeam:
    """The network bound to one graph and a team of N: the team interface of shared/learning/cepg.py.
    Features are computed without gradient (they hold no parameters), in chunks; the network runs
    on them with gradient.

    ``node_bias`` (N, n), from a fine-tune on this map (shared/core/graph_policy.py ``NODE_BIAS``):
    robot i's score of a move to a gains node_bias[i, a]. With ``bias_rate`` > 0 it is learned too
    (a fine-tune; zeros when none is given): held as node_bias / bias_rate, so that Adam's steps of
    about the learning rate move it ``bias_rate`` times as fast as the network's weights."""

    def __init__(
        self,
        net: GeneralNet,
        graph: Graph,
        n_robots: int,
        device: torch.device | str = "cpu",
        node_bias: np.ndarray | None = None,
        bias_rate: float = 0.0,
    ) -> None:
        graph.require_dense("the general policy's batched features")
        self.net, self.graph, self.N, self.n = net, graph, n_robots, graph.n
        self.bias_rate = float(bias_rate)
        self.bias: torch.Tensor | None = None  # (N, n), node_bias / bias_rate when learned
        if node_bias is not None or self.bias_rate > 0:
            start = torch.zeros(n_robots, graph.n) if node_bias is None else torch.as_tensor(node_bias).float()
            if start.shape != (n_robots, graph.n):
                raise ValueError(f"node_bias has shape {tuple(start.shape)}, expected ({n_robots}, {graph.n})")
            self.bias = nn.Parameter(start / self.bias_rate) if self.bias_rate > 0 else start.clone()
        self.device = torch.device(device)
        self.dist = distances_of(graph)
        self.nbr = torch.as_tensor(graph.nbr, device=self.device)  # (n, d)
        self.valid = torch.arange(graph.nbr.shape[1], device=self.device) < torch.as_tensor(
            graph.deg_closed, device=self.device
        ).unsqueeze(1)  # (n, d): slot k of N[p] holds a move (padding repeats p)
        self.role = torch.as_tensor(roles(n_robots))  # (N,)

    @property
    def H(self) -> int:
        return int(self.net.b1.shape[0])

    def parameters(self) -> Iterator[nn.Parameter]:
        yield from self.net.parameters()
        if isinstance(self.bias, nn.Parameter):
            yield self.bias

    def node_bias(self) -> torch.Tensor | None:
        """node_bias (N, n) as the scores add it, or None."""
        if self.bias is None:
            return None
        return self.bias * self.bias_rate if isinstance(self.bias, nn.Parameter) else self.bias

    def to(self, device: torch.device | str) -> GraphTeam:
        """The network on ``device`` (its features are computed in numpy and moved there)."""
        self.device = torch.device(device)
        self.net.to(self.device)
        for name in ("nbr", "valid", "role"):
            setattr(self, name, getattr(self, name).to(self.device))
        if self.bias is not None:  # the same tensor (an optimiser holding it keeps it), its data moved
            self.bias.data = self.bias.data.to(self.device)
        return self

    def _scores(self, feats: torch.Tensor, nets: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """The network's slot scores (..., k, d) of robot slots with networks (roles) ``nets`` (k,)
        at nodes pos (..., k), each with its node_bias row where the team has one."""
        out = self.net(feats)
        bias = self.node_bias()
        if bias is None:
            return out
        cand = self.nbr[pos]  # (..., k, d)
        return out + bias[nets.view(*([1] * (cand.dim() - 2)), -1, 1).expand_as(cand), cand]

    def features(
        self,
        pos: torch.Tensor,
        belief: torch.Tensor,
        role: torch.Tensor | None = None,
        team: torch.Tensor | None = None,
        active: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """pos (S, k), belief (S, k, n) -> (S, k, d, F); robot slot j has role ``role[j]`` (or
        ``role[s, j]``; default: i / (N - 1)) in a team of ``team[s]`` (default: N), and its
        teammates are the other slots (those ``active`` (S, k), default all: known where they are)."""
        S, k = pos.shape
        role = (self.role if role is None else role).expand(S, k)
        size = torch.full((S, 1), self.N) if team is None else team.reshape(S, 1)
        p, b, r, t = pos.cpu().numpy(), belief.detach().cpu().numpy(), role.cpu().numpy(), size.cpu().numpy()
        others = np.array([[j for j in range(k) if j != i] for i in range(k)], dtype=np.int64).reshape(k, k - 1)
        mates = p[:, others]  # (S, k, k - 1): slot i's teammates' nodes
        if active is not None:
            mates = np.where(active.cpu().numpy()[:, others], mates, -1)
        rows = max(1, FEATURE_CHUNK // (k * self.graph.nbr.shape[1] * self.n))
        out = [
            move_features(self.graph, self.dist, *(x[a : a + rows] for x in (p, b, r, t, mates)))
            for a in range(0, S, rows)
        ]
        if not out:  # no states (the cross-entropy term found no shared ones)
            return torch.zeros(0, k, self.graph.nbr.shape[1], len(FEATURES), device=self.device)
        return torch.from_numpy(np.concatenate(out)).to(self.device)

    def scatter_logits(self, pos: torch.Tensor, slot_scores: torch.Tensor) -> torch.Tensor:
        """Slot scores (..., d) at nodes pos (...) -> logits over the n nodes, NEG_INF outside N[p]."""
        s = slot_scores.masked_fill(~self.valid[pos], NEG_INF)
        out = torch.full((*pos.shape, self.n), NEG_INF, dtype=s.dtype, device=s.device)
        return out.scatter_reduce(-1, self.nbr[pos], s, reduce="amax")  # padded slots repeat p: keep the largest

    def slot_logits(self, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """Each robot's policy on its own state, over the slots of N[p] (the CE-PG rollout's and loss's
        action space, shared/learning/cepg.py): pos (S, N), belief (S, N, n) -> (S, N, d), NEG_INF
        on padding. O(d) a decision where node logits are O(n): what keeps a fine-tune's memory
        linear in n."""
        return self._scores(self.features(pos, belief), self._own, pos).masked_fill(~self.valid[pos], NEG_INF)

    @property
    def _own(self) -> torch.Tensor:
        """Robot slot i flies network (role) i: (N,)."""
        return torch.arange(self.N, device=self.device)

    def slot_allowed(self, pos: torch.Tensor) -> torch.Tensor:
        """pos (...) -> (..., d) bool: the slots of N[p] that hold a move."""
        return self.valid[pos]

    def slot_nodes(self, pos: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
        """The node rows of the slots chosen at ``pos``: (...), (...) -> (...)."""
        return self.nbr[pos].gather(-1, slot.unsqueeze(-1)).squeeze(-1)

    def logits(self, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """Each robot's policy on its own state over the n nodes: pos (S, N), belief (S, N, n) -> (S, N, n)."""
        return self.scatter_logits(pos, self._scores(self.features(pos, belief), self._own, pos))

    def logits_for(self, nets: torch.Tensor, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """Robot slot k flies with role ``nets[k]``: pos (B, k), belief (B, k, n) -> (B, k, n)."""
        return self.scatter_logits(pos, self._scores(self.features(pos, belief, self.role[nets]), nets, pos))

    @torch.no_grad()
    def cross_probs(self, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """pi_j(. | s^i) for every pair, over the slots of N[p_i]: (K, N) , (K, N, n) -> (K, N_i, N_j, d)."""
        K, N = pos.shape
        feats = self.features(pos, belief).unsqueeze(2).repeat(1, 1, N, 1, 1)  # (K, N_i, N_j, d, F)
        feats[..., FEATURES.index("role")] = self.role.view(1, 1, N, 1).to(feats)
        pos_ij = pos.unsqueeze(2).expand(K, N, N)
        return torch.softmax(self._scores(feats, self._own, pos_ij).masked_fill(~self.valid[pos_ij], NEG_INF), dim=-1)


class GeneralSearcher:
    """`general`: every robot flies the general policy on its own belief (Eq. 1 with ``model``, as
    `greedy` does), sampling its move (or the most likely with ``greedy_actions``). Robots left
    after others are withdrawn keep the same network as a team of the robots left (robot i's role
    its rank among them), as robot agents do."""

    name = "general"

    def __init__(
        self,
        policy: GeneralPolicy,
        graph: Graph,
        model: TargetModel,
        sensor: Sensor,
        n_robots: int,
        seed: int = 0,
        device: torch.device | str = "cpu",
        greedy_actions: bool = False,
    ) -> None:
        self.team = GraphTeam(GeneralNet.from_weights(policy.weights).to(device), graph, n_robots, device)
        self.beliefs = BeliefTracker(BatchedBelief(graph, model, sensor, device))
        self.greedy_actions = greedy_actions
        self.gen = torch.Generator(device=torch.device(device))
        self.gen.manual_seed(seed)

    @torch.no_grad()
    def act(self, obs: Obs) -> torch.Tensor:
        lik = self.beliefs.belief.likelihood(obs.pos, obs.z, obs.ready)
        b, _pred = self.beliefs.update(lik, obs.new)  # (B, N, n)
        act = obs.pos.clone()  # finished episodes (frozen) need no decision
        live = obs.alive.nonzero().squeeze(1)
        if live.numel() == 0:
            return act
        pos, active = obs.pos[live], obs.active[live]
        left = active.sum(1)  # the robots not withdrawn
        role = (active.cumsum(1) - 1).float() / (left - 1).clamp_min(1).unsqueeze(1)  # each one's rank among them
        feats = self.team.features(pos, b[live], role, left.clamp_min(1), active)
        logits = self.team.scatter_logits(pos, self.team.net(feats))
        if self.greedy_actions:
            act[live] = logits.argmax(-1)
        else:
            act[live] = sample(torch.softmax(logits, dim=-1), self.gen)
        return act


@dataclass
class GeneralConfig:
    """`mures train --general`'s recipe (module docstring)."""

    episodes: int = 60_000
    min_nodes: int = 20
    max_nodes: int = 240
    max_robots: int = 8
    pool: int = 48  # generated buildings in the pool
    batch_elements: int = 24_000  # episodes per update: this over n, within [16, 256]
    lr: float = 3e-3
    lr_final: float = 0.1  # the learning rate decays linearly to this share of lr
    beta: float = 0.9  # Eq. 9: weight of J against the cross-entropy term
    eps: float = 0.1  # the smoothing of pi_i inside the cross entropy (shared/learning/cepg.py)
    hidden: int = 64
    imitation_episodes: int = 32  # per pool building, flown by FHPE-SA for the imitation phase (0: none)
    imitation_epochs: int = 20
    seed: int = 0
    checkpoint_every: float = 300.0
    init: str = ""  # a general policy directory to go on from (its weights; no imitation phase)
    floors_per_update: int = 1  # pool entries flown per update, gradients averaged (side by side on a cluster)

    def check(self) -> None:
        if not 2 <= self.min_nodes <= self.max_nodes:
            raise ValueError(f"expected 2 <= min_nodes <= max_nodes, got {self.min_nodes} and {self.max_nodes}")
        if self.max_robots < 1 or self.pool < 1 or self.episodes < 1:
            raise ValueError("episodes, pool and max_robots must be at least 1")
        if not 1 <= self.floors_per_update <= self.pool:
            raise ValueError(f"floors_per_update must be 1 to the pool's {self.pool}, got {self.floors_per_update}")
        if self.imitation_episodes < 0 or self.imitation_epochs < 0:
            raise ValueError("imitation_episodes and imitation_epochs must be at least 0")
        if not 0.0 < self.beta <= 1.0:
            raise ValueError(f"beta must be in (0, 1], got {self.beta}")


@dataclass(frozen=True)
class FloorSpec:
    """A pool entry as the numbers that make it, so that a Dask worker builds the same one."""

    nodes: int
    graph_seed: int
    robots: int
    batch: int  # episodes per rollout
    sim_seed: int

    def build(self, net: GeneralNet, device: torch.device | str = "cpu") -> _Building:
        """The entry's floor, simulator, beliefs and team, their tensors on ``device``."""
        graph = office_graph(self.nodes, seed=self.graph_seed)
        target, sensor = uniform_walk(graph), Sensor()
        sim = SearchSim(
            graph, target, sensor, self.robots, self.batch, seed=self.sim_seed, auto_reset=False,
            check_actions=False, details=False, device=device,
        )  # fmt: skip
        belief = BatchedBelief(graph, target, sensor, device)
        team = GraphTeam(net, graph, self.robots, device)
        return _Building(self, graph, self.robots, target, sim, belief, team)


@dataclass
class _Building:
    """One pool entry: a generated floor and team size, with its simulator, beliefs and scale."""

    spec: FloorSpec
    graph: Graph
    robots: int
    target: TargetModel  # the uniform walk: the simulated target's and the robots' beliefs' model
    sim: SearchSim
    belief: BatchedBelief
    team: GraphTeam
    scale: float | None = None  # running mean capture time (J's unit for this entry)


def training_pool(cfg: GeneralConfig, net: GeneralNet, device: torch.device | str = "cpu") -> list[_Building]:
    """The pool of generated buildings: seeds 10_000 + k (the evaluations use other seeds), their
    tensors on ``device``."""
    rng = np.random.default_rng(cfg.seed)
    pool = []
    for k in range(cfg.pool):
        n = round(math.exp(rng.uniform(math.log(cfg.min_nodes), math.log(cfg.max_nodes))))
        robots = int(rng.integers(1, cfg.max_robots + 1))
        batch = int(np.clip(cfg.batch_elements // n, 16, 256))
        pool.append(FloorSpec(n, 10_000 + k, robots, batch, cfg.seed * 7_919 + k).build(net, device))
    return pool


@torch.no_grad()
def imitation_data(b: _Building, episodes: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """FHPE-SA's decisions on one pool building (shared/core/fhpe_sa.py: sequential allocation of
    5-step paths on the collective belief, Eq. 6, with the true model), as the network sees them:
    each robot's features on that belief with its role, and the slot of N[p] FHPE-SA chose for it.
    Returns features (M, d, F), target slots (M,) and valid slots (M, d) over the M robot-decisions
    of ``episodes`` episodes, on the CPU (the planner's numpy walks are)."""
    graph, sensor, target = b.graph, b.sim.sensor, b.target
    team = GraphTeam(b.team.net, graph, b.robots)  # the features, on the CPU whatever the entry's device
    planner = FhpeSAPlanner(graph, target, sensor)
    sim = SearchSim(graph, target, sensor, b.robots, episodes, seed=seed, auto_reset=False, details=False)
    tracker = BeliefTracker(BatchedBelief(graph, target, sensor, dtype=torch.float64))
    rng = np.random.default_rng(seed)
    pos_log, bel_log, act_log = [], [], []
    obs = sim.reset()
    while True:
        lik = tracker.belief.collective_likelihood(obs.pos, obs.z, obs.active).unsqueeze(1)  # (B, 1, n)
        bel, _pred = tracker.update(lik, obs.new)
        going = (sim.alive & ~sim.pending).nonzero().squeeze(1)
        if going.numel() == 0:
            break
        act = obs.pos.clone()
        for e in going.tolist():
            act[e] = torch.as_tensor(planner.plan(bel[e, 0].numpy(), obs.pos[e].numpy(), obs.active[e].numpy(), rng))
        pos_log.append(obs.pos[going])
        bel_log.append(bel[going, 0].float())
        act_log.append(act[going])
        obs, _res = sim.step(act)
    pos, act = torch.cat(pos_log), torch.cat(act_log)  # (M', N)
    belief = torch.cat(bel_log).unsqueeze(1).expand(-1, b.robots, -1)  # every robot on the collective belief
    feats = team.features(pos, belief).flatten(0, 1)  # (M' N, d, F)
    cand, valid = team.nbr[pos].flatten(0, 1), team.valid[pos].flatten(0, 1)  # (M, d)
    slot = ((cand == act.reshape(-1, 1)) & valid).float().argmax(1)  # the first slot holding the teacher's move
    return feats, slot, valid


def imitate(
    net: GeneralNet,
    pool: list[_Building],
    cfg: GeneralConfig,
    say: Callable[[str], None],
    workers: FloorWorkers | None = None,
) -> dict[str, Any]:
    """The imitation phase (R2PS's pull toward a planner, as a start): FHPE-SA flies
    ``imitation_episodes`` episodes on every pool building (on the ``workers`` when given), and the
    network is fitted to its moves by cross-entropy for ``imitation_epochs`` epochs. Returns the
    phase's figures."""
    t0 = time.perf_counter()
    seeds = [cfg.seed * 7_919 + 50_000 + k for k in range(len(pool))]
    flown: Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
    if workers is None:
        flown = (imitation_data(b, cfg.imitation_episodes, seed) for b, seed in zip(pool, seeds, strict=True))
    else:
        flown = workers.imitation([b.spec for b in pool], cfg.hidden, cfg.imitation_episodes, seeds)
    parts = []
    for k, (b, part) in enumerate(zip(pool, flown, strict=True)):
        parts.append(part)
        say(f"imitation: FHPE-SA on building {k + 1}/{len(pool)} ({b.graph.n} nodes, N = {b.robots})")
    d = max(p[0].shape[1] for p in parts)  # buildings differ in their largest |N[p]|: pad to the largest
    device = net.w1.device  # the decisions fitted where the network is
    feats = torch.cat([nn.functional.pad(p[0], (0, 0, 0, d - p[0].shape[1])) for p in parts]).to(device)
    slot = torch.cat([p[1] for p in parts]).to(device)
    valid = torch.cat([nn.functional.pad(p[2], (0, d - p[2].shape[1])) for p in parts]).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    gen = torch.Generator()
    gen.manual_seed(cfg.seed)
    loss = torch.tensor(0.0)
    for epoch in range(cfg.imitation_epochs):
        order = torch.randperm(slot.shape[0], generator=gen).to(device)
        for a in range(0, slot.shape[0], 2048):
            i = order[a : a + 2048]
            logits = net(feats[i]).masked_fill(~valid[i], NEG_INF)
            loss = nn.functional.cross_entropy(logits, slot[i])
            opt.zero_grad()
            loss.backward()
            opt.step()
        say(f"imitation: epoch {epoch + 1}/{cfg.imitation_epochs}, cross-entropy {float(loss.detach()):.3f}")
    with torch.no_grad():
        agree = float((net(feats).masked_fill(~valid, NEG_INF).argmax(1) == slot).float().mean())
    return {
        "decisions": int(slot.shape[0]),
        "agreement": round(agree, 4),
        "seconds": round(time.perf_counter() - t0, 1),
    }


def floor_gradients(
    b: _Building, net: GeneralNet, gen: torch.Generator, cfg: GeneralConfig
) -> tuple[list[torch.Tensor], float, int]:
    """One pool entry's share of an update: a batch of episodes flown with the network's stochastic
    policy (``gen`` draws its actions), each robot on its own belief, and the gradient of the CE-PG
    loss (Eq. 9-13) on it, J in units of the entry's running mean capture time (updated here).
    Returns (one gradient per parameter of ``net``, the batch's mean capture time, its episodes)."""
    ro = rollout(b.sim, b.team, b.belief, False, gen)  # type: ignore[arg-type]  # B episodes on one building
    mean_ct = float(ro.capture_time.float().mean())
    b.scale = mean_ct if b.scale is None else 0.9 * b.scale + 0.1 * mean_ct
    beta = torch.full((b.robots,), cfg.beta, device=b.sim.device)
    terms = cepg_loss(b.team, ro, beta, cfg.eps, j_unit=max(b.scale, 1.0))  # type: ignore[arg-type]  # Eq. 9-13
    net.zero_grad()
    (terms.loss / b.robots).backward()
    grads = [torch.zeros_like(p) if p.grad is None else p.grad.detach().clone() for p in net.parameters()]
    return grads, mean_ct, int(ro.length.numel())


# a Dask worker's own copies of the pool entries it has flown, built once per worker process
_WORKER_FLOORS: dict[tuple[FloorSpec, int, int], tuple[GeneralNet, _Building]] = {}


def _worker_floor(
    spec: FloorSpec, hidden: int, threads: int, features: int = len(FEATURES)
) -> tuple[GeneralNet, _Building]:
    """The worker's copy of a pool entry with a network of the training run's shape (``features``:
    a run going on from a policy of fewer features keeps them)."""
    torch.set_num_threads(threads)  # the training process's: floating-point sums depend on it
    key = (spec, hidden, features)
    if key not in _WORKER_FLOORS:
        net = GeneralNet(hidden, features)
        _WORKER_FLOORS[key] = (net, spec.build(net))
    return _WORKER_FLOORS[key]


def _remote_gradients(
    spec: FloorSpec,
    cfg: GeneralConfig,
    weights: dict[str, torch.Tensor],
    scale: float | None,
    sim_state: torch.Tensor,
    gen_state: torch.Tensor,
    threads: int,
) -> dict[str, Any]:
    """``floor_gradients`` on a worker, from the training process's weights and random states;
    returns what it changed (the entry's scale, the simulator's and the actions' random states)."""
    net, b = _worker_floor(spec, cfg.hidden, threads, int(weights["w1"].shape[0]))
    net.load_state_dict(weights)
    b.scale = scale
    b.sim.gen.set_state(sim_state)
    gen = torch.Generator()
    gen.set_state(gen_state)
    grads, mean_ct, episodes = floor_gradients(b, net, gen, cfg)
    return {"grads": grads, "mean_ct": mean_ct, "episodes": episodes, "scale": b.scale,
            "sim_state": b.sim.gen.get_state(), "gen_state": gen.get_state()}  # fmt: skip


def _remote_imitation(
    spec: FloorSpec, hidden: int, episodes: int, seed: int, threads: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return imitation_data(_worker_floor(spec, hidden, threads)[1], episodes, seed)


class FloorWorkers:
    """The pool entries' rollouts on a Dask distributed cluster (`dask scheduler` / `dask worker`,
    the ``cluster`` extra; shared/tools/runner.py's ``local_dask_cluster`` on one machine): each
    update's entries fly side by side, each worker keeping its own copy of the entries it has
    flown. The weights and every random state go out with each task and come back with its result,
    so the run's numbers are the same as in one process."""

    def __init__(self, scheduler: str) -> None:
        try:
            from distributed import Client
        except ModuleNotFoundError:
            raise ValueError("a Dask cluster needs dask and distributed: pip install 'mures-fleet[cluster]'") from None
        try:
            self.client = Client(scheduler, timeout=15)
        except OSError as exc:
            raise ValueError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        self.where = f"{len(self.client.scheduler_info()['workers'])} Dask workers at {scheduler}"

    def gradients(
        self, net: GeneralNet, floors: list[_Building], gens: list[torch.Generator], cfg: GeneralConfig
    ) -> list[tuple[list[torch.Tensor], float, int]]:
        """``floor_gradients`` of each entry with its generator, on the cluster; the entries'
        scales and random states (and the generators') move on as if they had run here."""
        weights = {k: v.detach().clone() for k, v in net.state_dict().items()}
        threads = torch.get_num_threads()
        futures = [
            self.client.submit(
                _remote_gradients,
                b.spec,
                cfg,
                weights,
                b.scale,
                b.sim.gen.get_state(),
                gen.get_state(),
                threads,
                pure=False,
            )
            for b, gen in zip(floors, gens, strict=True)
        ]
        out = []
        for b, gen, r in zip(floors, gens, self.client.gather(futures), strict=True):
            b.scale = r["scale"]
            b.sim.gen.set_state(r["sim_state"])
            gen.set_state(r["gen_state"])
            out.append((r["grads"], r["mean_ct"], r["episodes"]))
        return out

    def imitation(
        self, specs: list[FloorSpec], hidden: int, episodes: int, seeds: list[int]
    ) -> Iterator[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """``imitation_data`` of every entry, all at once on the cluster, in the pool's order."""
        futures = [
            self.client.submit(_remote_imitation, spec, hidden, episodes, seed, torch.get_num_threads(), pure=False)
            for spec, seed in zip(specs, seeds, strict=True)
        ]
        for fut in futures:
            yield fut.result()

    def close(self) -> None:
        self.client.close()


def _update_generators(gen: torch.Generator, seed: int, update: int, floors: int) -> list[torch.Generator]:
    """The generators drawing the actions of an update's ``floors`` entries: the run's own for the
    first, one seeded by the run's seed, the update and the entry's place for each other (on the
    run's device)."""
    out = [gen]
    for j in range(1, floors):
        g = torch.Generator(device=gen.device)
        g.manual_seed(int(np.random.SeedSequence([seed, update, j]).generate_state(1)[0]))
        out.append(g)
    return out


def train_general(
    cfg: GeneralConfig,
    out: str | Path,
    progress: Callable[[dict[str, Any]], None] | None = None,
    command: str = "",
    say: Callable[[str], None] = lambda _text: None,
    scheduler: str | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, Any]:
    """Train the general policy into ``out`` (module docstring); returns the training summary.
    ``progress`` gets the learning curve's points, ``say`` the imitation phase's lines. With
    ``scheduler`` (a Dask scheduler's address) the imitation phase's planner runs and each update's
    ``floors_per_update`` rollouts fly on that cluster (``FloorWorkers``), with the same numbers.
    ``device``: where the rollouts, beliefs and network run in this process (a GPU: "cuda"; the
    imitation phase's planner stays on the CPU); the random draws then differ from the CPU's."""
    cfg.check()
    device = torch.device(device)
    if scheduler and device.type != "cpu":
        raise ValueError(f"device {device} goes without a Dask cluster (the workers' rollouts run on their CPUs)")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    net = GeneralNet(cfg.hidden)
    state: dict[str, Any] = {"episodes": 0, "updates": 0, "wall_seconds": 0.0, "curve": []}
    if cfg.init:
        start = load_general(cfg.init)
        if start.hidden != cfg.hidden:
            raise ValueError(f"init {cfg.init} has {start.hidden} hidden units, this run {cfg.hidden}")
        net = GeneralNet.from_weights(start.weights)
        state["imitation"] = {"from": cfg.init, "training": start.meta.get("training", {}).get("command")}
    net.to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    pool = training_pool(cfg, net, device)
    pick = random.Random(cfg.seed)
    gen = torch.Generator(device=device)
    gen.manual_seed(cfg.seed * 104_729)
    ckpt = out / CHECKPOINT
    if ckpt.is_file():  # go on from the last checkpoint
        saved = torch.load(ckpt, weights_only=False, map_location="cpu")  # random states are CPU tensors
        began_on = saved.get("device", "cpu")
        if began_on != device.type:
            raise ValueError(f"{ckpt} was written by a run on {began_on}: go on there, or remove it to start afresh")
        if saved["config"] != asdict(cfg):
            raise ValueError(f"{ckpt} was written by a run with other settings: remove it or use another directory")
        net.load_state_dict(saved["net"])
        opt.load_state_dict(saved["opt"])
        state = saved["state"]
        pick.setstate(saved["pick"])
        gen.set_state(saved["gen"])
        for b, (scale, sim_state) in zip(pool, saved["pool"], strict=True):
            b.scale = scale
            b.sim.gen.set_state(sim_state)
    t0, last_ckpt = time.perf_counter() - state["wall_seconds"], time.perf_counter()
    window: list[float] = []

    def checkpoint() -> None:
        state["wall_seconds"] = time.perf_counter() - t0
        blob = {
            "config": asdict(cfg),
            "net": net.state_dict(),
            "opt": opt.state_dict(),
            "state": state,
            "pick": pick.getstate(),
            "gen": gen.get_state(),
            "pool": [(b.scale, b.sim.gen.get_state()) for b in pool],
            "device": device.type,  # random states are per device: a run goes on where it began
        }
        torch.save(blob, ckpt.with_suffix(".tmp"))
        ckpt.with_suffix(".tmp").replace(ckpt)

    workers = FloorWorkers(scheduler) if scheduler else None
    try:
        if workers is not None:
            say(f"rollouts on {workers.where}")
        if cfg.imitation_episodes and cfg.imitation_epochs and "imitation" not in state:
            state["imitation"] = imitate(net, pool, cfg, say, workers)
            opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)  # RL starts with fresh moments
            checkpoint()
        while state["episodes"] < cfg.episodes:
            k = cfg.floors_per_update
            picked = [pick.randrange(len(pool))] if k == 1 else pick.sample(range(len(pool)), k)  # k distinct entries
            floors = [pool[i] for i in picked]
            gens = _update_generators(gen, cfg.seed, state["updates"], k)
            if workers is None:
                shares = [floor_gradients(b, net, g, cfg) for b, g in zip(floors, gens, strict=True)]
            else:
                shares = workers.gradients(net, floors, gens, cfg)
            lr = cfg.lr * (1.0 - (1.0 - cfg.lr_final) * min(1.0, state["episodes"] / cfg.episodes))
            for group in opt.param_groups:
                group["lr"] = lr
            for j, p in enumerate(net.parameters()):  # the entries' gradients averaged
                p.grad = torch.stack([share[0][j] for share in shares]).sum(0) / k
            nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
            state["episodes"] += sum(share[2] for share in shares)
            state["updates"] += 1
            window.extend(share[1] / max(b.graph.n, 1) for b, share in zip(floors, shares, strict=True))
            if state["updates"] % 20 == 0 or state["episodes"] >= cfg.episodes:
                point = {
                    "episodes": state["episodes"],
                    "updates": state["updates"],
                    "capture_time_per_node": round(float(np.mean(window)), 4),
                    "wall_seconds": round(time.perf_counter() - t0, 1),
                    "total": cfg.episodes,
                }
                state["curve"].append(point)
                window.clear()
                if progress:
                    progress(point)
            if time.perf_counter() - last_ckpt > cfg.checkpoint_every:
                checkpoint()
                last_ckpt = time.perf_counter()
    finally:
        if workers is not None:
            workers.close()
    summary = {
        "config": asdict(cfg),
        "episodes": state["episodes"],
        "updates": state["updates"],
        "wall_seconds": round(time.perf_counter() - t0, 1),
        "pool": [{"nodes": b.graph.n, "robots": b.robots, "name": b.graph.name} for b in pool],
        "learning_curve": state["curve"],
        "imitation": state.get("imitation"),
        "command": command,
        "ran_on": ("this process" if device.type == "cpu" else f"this process on {device}")
        if workers is None
        else workers.where,
    }
    save_general(out, net.numpy_weights(), {"training": summary})
    ckpt.unlink(missing_ok=True)  # done: the same command trains afresh
    return summary

"""The paper setup as a multi-agent environment, batched: what both public interfaces wrap.

``Scenario`` is a map with its true target model, the sensor, the robots' belief model and N;
``EnvCore`` runs B episodes of it side by side on the engine's simulator (shared/engine/sim.py)
and keeps each robot's own belief (Eq. 1) with the belief model, exactly as a robot agent does.
``mures_v0.parallel_env`` (PettingZoo) runs one episode on it, ``mures_v0.torchrl_env`` (TorchRL)
B of them; docs/SPEC.md section 11 is the contract.

Per robot i (shapes for B episodes, N robots, n nodes, d = max |N[p]|):

    observation  (B, N, 2n) float32   onehot(p^i) followed by the robot's own belief b^i_t
    action_mask  (B, N, d)  bool      flag k: the k-th entry of N[p^i] exists
    action       (B, N)     long      an index k into N[p^i] in the graph's order: p itself first,
                                      then its neighbours by increasing row; an index beyond
                                      |N[p^i]| is masked and, if taken anyway, means staying (k = 0)
    reward       (B, N)     float32   -1 per step for every robot while the search goes on, 0 for the
                                      step that reports a capture at t = 0; the return is -t_cap
    state        (B, S)     float32   for centralised critics in training only: every robot's
                                      onehot(p) (N * n), onehot(target) (n), on the clock every
                                      robot's onehot(goal) (N * n) and ticks left / ticks a step (N),
                                      then t / T_max (1); a critic that wants the beliefs too reads
                                      the robots' observations

An episode terminates at capture and is truncated at T_max = 3n (docs/SPEC.md section 1).

On the mission clock (``make_scenario(speed=...)``, docs/continuous-world.md "Training on the
clock") a step is one tick: a move takes its edge's travel time in ticks (shared/core/clock.py),
the target moves once a tick on its model made a tick's worth, and a robot in transit (``ready``
False) reads nothing and has one action, index 0 (its action is ignored: it goes on to its goal);
it decides again when it arrives, so the robots of a team decide at different ticks. Beliefs
predict every tick and take each reading at the tick it was made. The reward is -1 / (ticks a step
lasts) a tick, so the return is still minus the capture time in steps' worth (as CE-PG's J on the
clock), and T_max is 3n steps' worth of ticks.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from shared.core.clock import TICK_S, TravelTimes
from shared.core.graph import Graph, builtin_graph, load_graph_file
from shared.core.models import Sensor, TargetModel, identity_model, load_model_file, parse_target
from shared.engine.batched_belief import BatchedBelief
from shared.engine.sim import SearchSim

BELIEF_MODELS = ("true", "identity")  # or a model.json path / a TargetModel


@dataclass(frozen=True)
class Scenario:
    """A map, the true target model, the sensor, the robots' belief model (Gamma_hat, b0) and N."""

    graph: Graph
    target: TargetModel
    sensor: Sensor
    belief_model: TargetModel
    robots: int
    clock: TravelTimes | None = None  # the mission clock (module docstring); None: the paper's steps

    @property
    def t_max(self) -> int:
        """The paper's T_max = 3n steps (in ticks on the clock)."""
        return 3 * self.graph.n if self.clock is None else self.clock.t_max(self.graph.n)

    @property
    def ticks_per_step(self) -> float:
        """The ticks one step of the model lasts (1 without a clock): the reward's unit."""
        return 1.0 if self.clock is None else self.clock.ticks_per_step

    @property
    def d(self) -> int:
        """Actions per robot: the largest closed neighbourhood."""
        return int(self.graph.nbr.shape[1])

    @property
    def state_size(self) -> int:
        clocked = 0 if self.clock is None else self.robots * (self.graph.n + 1)  # goals and ticks left
        return (self.robots + 1) * self.graph.n + clocked + 1


def make_scenario(
    map: str | Graph = "office",
    robots: int = 4,
    eta_fn: float = 0.0,
    eta_fp: float = 0.0,
    detection: str = "node",
    target: str | TargetModel = "uniform",
    belief_model: str | TargetModel = "true",
    speed: float | None = None,
    tick: float = TICK_S,
    models_per_tick: bool = False,
) -> Scenario:
    """The same options as `mures evaluate`: ``map`` a built-in name or a graph file's path;
    ``target`` uniform, lazy:STAY or a model.json path; ``belief_model`` the robots' Gamma_hat and
    b0: "true" (the target's own), "identity" (Gamma_hat_0 = I and a uniform b0, where CE-PG
    starts), or a model.json path.

    ``speed`` (m/s): the mission clock (module docstring), ticks of ``tick`` s, on a graph with
    edge lengths (a ValueError otherwise); the target and belief models, given per step, are made
    a tick's worth, unless ``models_per_tick`` (a model EM fitted per tick)."""
    if isinstance(map, Graph):
        graph = map
    elif isinstance(map, str) and (map.endswith(".json") or Path(map).exists()):
        graph = load_graph_file(map)
    else:
        graph = builtin_graph(str(map))
    graph.require_dense("the environments")
    if not isinstance(robots, int) or isinstance(robots, bool) or robots < 1:
        raise ValueError(f"robots must be a positive integer, got {robots!r}")
    true_model = target if isinstance(target, TargetModel) else parse_target(graph, target)
    sensor = Sensor(eta_fn=eta_fn, eta_fp=eta_fp, detection=detection)
    if sensor.detection == "custom":
        graph.detection_sets("custom")  # a clear error when the graph has no sensing table
    if isinstance(belief_model, TargetModel):
        model = belief_model
    elif belief_model == "true":
        model = true_model
    elif belief_model == "identity":
        model = identity_model(graph)
    elif isinstance(belief_model, str) and belief_model.endswith(".json"):
        model = load_model_file(graph, belief_model)
    else:
        raise ValueError(f"belief_model must be true, identity or a model.json path, got {belief_model!r}")
    for m, what in ((true_model, "target"), (model, "belief_model")):
        if m.n != graph.n:
            raise ValueError(f"{what} has {m.n} nodes, the map {graph.n}")
    clock = None if speed is None else TravelTimes.of(graph, speed, tick)
    if clock is not None and not models_per_tick:
        same = model is true_model
        true_model = clock.model(true_model)
        model = true_model if same else clock.model(model)
    return Scenario(graph, true_model, sensor, model, robots, clock)


class EnvCore:
    """B episodes of a scenario with every robot's own belief (module docstring for the shapes).

    Episodes start with ``reset(mask)``; ``step`` advances the running ones; finished slots freeze
    until they are reset. Deterministic for a seed: the simulator's generator is the only source
    of randomness.
    """

    def __init__(self, scenario: Scenario, batch: int, seed: int = 0, device: torch.device | str = "cpu") -> None:
        self.scenario = scenario
        g = scenario.graph
        self.n, self.N, self.B, self.d = g.n, scenario.robots, batch, scenario.d
        self.device = torch.device(device)
        self.sim = SearchSim(
            g,
            scenario.target,
            scenario.sensor,
            scenario.robots,
            batch,
            seed=seed,
            device=device,
            auto_reset=False,
            # ``destinations`` only leads into N[p], and nothing here reads false alarms or who
            # captured: the simulator's own action check and that bookkeeping are skipped
            check_actions=False,
            details=False,
            move_ticks=None if scenario.clock is None else scenario.clock.ticks,
            t_max=scenario.t_max,
        )
        self.reward_per_step = -1.0 / scenario.ticks_per_step  # (module docstring)
        self.belief = BatchedBelief(g, scenario.belief_model, scenario.sensor, self.device)
        self.nbr = torch.as_tensor(g.nbr, device=self.device)  # (n, d)
        deg = torch.as_tensor(g.deg_closed, device=self.device)
        self.valid = torch.arange(self.d, device=self.device) < deg.unsqueeze(1)  # (n, d)
        # (n d,) entry p d + k: the node action k leads to from p; a masked k means staying (N[p]'s
        # first entry, p itself): one gather turns actions into destinations
        self.dest_flat = torch.where(self.valid, self.nbr, self.nbr[:, :1]).reshape(-1)
        self.eye = torch.eye(self.n, dtype=torch.float32, device=self.device)  # onehot(p) rows
        self.offsets = torch.arange(self.N + 1, device=self.device) * self.n  # state's onehot blocks
        # on the clock, each robot's onehot(goal) block of the state, after the target's
        self.goal_offsets = (torch.arange(self.N, device=self.device) + self.N + 1) * self.n
        self.b = torch.zeros(batch, self.N, self.n, device=self.device)  # (B, N, n) beliefs
        self.last_reset = torch.arange(batch, device=self.device)  # (k,) the slots the last reset started
        # per slot since the last take_stats: episodes ended, their summed capture times, censored
        self._ended = torch.zeros(3, batch, dtype=torch.long, device=self.device)

    def seed(self, seed: int) -> None:
        self.sim.gen.manual_seed(int(seed))

    def state_dict(self) -> dict[str, Any]:
        """Everything a step depends on: the simulator's episodes and generator, the beliefs, the
        belief model's Gamma_hat and b0 (EM changes them during training) and the episode counts
        not yet taken. ``load_state_dict`` on a core of the same scenario and B continues exactly."""
        return {
            "sim": self.sim.state_dict(),
            "b": self.b.clone(),
            "last_reset": self.last_reset.clone(),
            "ended": self._ended.clone(),
            "gamma": self.belief.dense_gamma().clone(),
            "b0": self.belief.b0.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from ``state_dict()``'s output (a ValueError names a mismatching entry)."""
        gamma = self.belief.dense_gamma()
        for key, mine in (("b", self.b), ("ended", self._ended), ("gamma", gamma), ("b0", self.belief.b0)):
            theirs = state.get(key)
            if not isinstance(theirs, torch.Tensor) or theirs.shape != mine.shape:
                raise ValueError(f"environment state {key!r}: expected a tensor of shape {tuple(mine.shape)}")
        self.sim.load_state_dict(state["sim"])
        self.b = state["b"].to(self.device).clone()
        self.last_reset = state["last_reset"].to(self.device).clone()
        self._ended = state["ended"].to(self.device).clone()
        self.belief.gamma = state["gamma"].to(self.device, self.belief.dtype).clone()
        self.belief.b0 = state["b0"].to(self.device, self.belief.dtype).clone()

    def set_belief_model(self, model: TargetModel) -> None:
        """Use another Gamma_hat, b0 for the robots' beliefs from the next update on (EM during training)."""
        self.belief = BatchedBelief(self.scenario.graph, model, self.scenario.sensor, self.device)

    def reset(self, mask: torch.Tensor | None = None) -> None:
        """Start fresh episodes in the slots of ``mask`` (B,) bool (all when None): e_0 ~ b0,
        robots on the start node, z_0 observed, b_0 ∝ Lambda_0 b0 (Theorem 1 at t = 0)."""
        if mask is None:
            mask = torch.ones(self.B, dtype=torch.bool, device=self.device)
        self.sim._start_episodes(mask)
        rows = self.last_reset = mask.nonzero().squeeze(1)
        lik = self.belief.likelihood(self.sim.pos[rows], self.sim.z[rows])
        self.b[rows] = self.belief.initial(lik)

    def step(self, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Move every robot of the running episodes: action (B, N) indices into N[p].

        Returns reward (B,), terminated (B,) and truncated (B,) (True only at the step that ends
        an episode). A finished slot's ``sim.t`` is its capture time (or T_max when truncated)
        until the slot is reset."""
        if action.shape != (self.B, self.N):
            raise ValueError(f"expected actions of shape {(self.B, self.N)}, got {tuple(action.shape)}")
        action = action.to(device=self.device, dtype=torch.long)
        lo, hi = (int(x) for x in torch.aminmax(action))
        if lo < 0 or hi >= self.d:
            raise ValueError(f"action indices must be in [0, {self.d}), got {lo}..{hi}")
        obs, res = self.sim.step(self.destinations(self.sim.pos, action))
        moving = self.sim.moving
        lik = self.belief.likelihood(obs.pos, obs.z, obs.ready)  # in transit: no reading (Lambda = I)
        b = self.belief.update(self.b, lik)  # Eq. 1
        self.b = b if bool(moving.all()) else torch.where(moving.view(-1, 1, 1), b, self.b)
        reward = moving.to(torch.float32) * self.reward_per_step
        truncated = res.censored  # a censored episode is done
        terminated = res.done ^ truncated
        ended, ct_sum, censored = self._ended
        ended += res.done
        ct_sum += res.capture_time * res.done
        censored += truncated
        return reward, terminated, truncated

    def destinations(self, pos: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The nodes that action indices lead to: pos, action (...) -> node rows (...); a masked
        index means staying (index 0, p itself)."""
        flat = torch.add(action, pos, alpha=self.d)  # entries p d + k of the (n, d) table
        return self.dest_flat.index_select(0, flat.reshape(-1)).view(flat.shape)

    def take_stats(self) -> tuple[int, float, int]:
        """(episodes ended, their summed capture times, how many were censored) since the last call."""
        e, ct, c = self._ended.sum(1).tolist()
        self._ended.zero_()
        return int(e), float(ct), int(c)

    # ------------------------------------------------------------------ views
    def observation(self) -> torch.Tensor:
        """(B, N, 2n): onehot(p^i) and b^i."""
        return self.encode_observation(self.sim.pos, self.b)

    def encode_observation(self, pos: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Positions (M, N) and beliefs (M, N, n) as observations (M, N, 2n)."""
        onehot = self.eye.index_select(0, pos.reshape(-1)).view(*pos.shape, self.n)
        return torch.cat([onehot, b], dim=-1)

    def action_mask(self) -> torch.Tensor:
        """(B, N, d) bool; on the clock a robot in transit has index 0 only."""
        return self.encode_action_mask(self.sim.pos, None if self.scenario.clock is None else self.sim.ready)

    def encode_action_mask(self, pos: torch.Tensor, ready: torch.Tensor | None = None) -> torch.Tensor:
        """Positions (M, N) as action masks (M, N, d); where ``ready`` (M, N) is False (in transit on
        the clock) index 0 only."""
        mask = self.valid.index_select(0, pos.reshape(-1)).view(*pos.shape, self.d)
        if ready is not None:
            mask = mask & (ready.unsqueeze(-1) | (torch.arange(self.d, device=self.device) == 0))
        return mask

    def state(self) -> torch.Tensor:
        """(B, S) the global state for centralised critics (module docstring)."""
        return self.encode_state(self.sim.pos, self.sim.target, self.sim.t, self.sim.goal, self.sim.left)

    def encode_state(
        self,
        pos: torch.Tensor,
        target: torch.Tensor,
        t: torch.Tensor,
        goal: torch.Tensor | None = None,
        left: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Positions (M, N), target rows (M,) and times (M,) as global states (M, S); on the clock
        also every robot's goal (M, N) and ticks left (M, N) (read only there)."""
        where = torch.cat([pos, target.unsqueeze(1)], dim=1) + self.offsets  # (M, N + 1) columns of the ones
        out = torch.zeros(len(where), self.scenario.state_size, device=self.device)
        torch.div(t, self.scenario.t_max, out=out.select(1, -1))  # true division: t.float() / T_max
        if self.scenario.clock is not None:
            if goal is None or left is None:
                raise ValueError("on the mission clock the state needs every robot's goal and ticks left")
            where = torch.cat([where, goal + self.goal_offsets], dim=1)
            start = (2 * self.N + 1) * self.n
            out[:, start : start + self.N] = left / self.scenario.ticks_per_step
        return out.scatter_(1, where, 1.0)

"""What the MARL baselines share: the decentralised actor, the critics' inputs, hyperparameters,
the training loop's bookkeeping (budget, learning curve, progress, EM, stop) and the result.

Decentralised execution, as CE-PG: robot i's actor is network i of a ``TeamPolicy`` (an MLP
2n -> H -> n on its own onehot(p) and belief, masked to N[p]), so every method's team is saved in
the snapshot format that `mures evaluate`, the experiments and the robot agents run. In the
environment's action space (an index k into N[p], shared/envs/core.py) the actor's logits are the
network's logits gathered at N[p]; indices beyond |N[p]| are masked, so the distribution over
nodes is the one the agent samples. Critics see the global state (every robot's position, the
target's, t / T_max) and robots' observations: training only.

On the mission clock (``cfg.speed``, docs/continuous-world.md "Training on the clock") the
environment's step is a tick (shared/envs/core.py): a robot in transit has one action, the reward
is a step's worth of -1 spread over its ticks, and ``MarlRun.gamma`` is the discount per tick that
makes ``hyper.gamma`` the discount per step's worth of ticks. EM then fits Gamma_hat per tick from
the missions' timestamped records, as CE-PG's on the clock does.

Shapes: B episodes side by side, N robots, n nodes, d = max |N[p]|, S = state size.
"""

from __future__ import annotations

import hashlib
import math
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MultiAgentMLP, ProbabilisticActor

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel, identity_model
from shared.envs.core import make_scenario
from shared.envs.mures_v0 import MuresTorchEnv
from shared.learning.config import CHECKPOINT_EVERY_S, TrainConfig
from shared.learning.marl.checkpoint import Checkpointer, StateHolder
from shared.learning.policy import NEG_INF, TeamPolicy
from shared.learning.train import TrainResult, em_update

Progress = Callable[[dict[str, Any]], None]


# ---------------------------------------------------------------------- hyperparameters
@dataclass
class MarlHyper:
    """Hyperparameters every MARL baseline has (each method's class adds its own). ``episodes``
    and ``envs`` come from `mures train --episodes/--batch` when given."""

    episodes: int = 100_000  # training budget in episodes
    envs: int = 128  # B episodes simulated side by side
    lr: float = 3e-4  # actor learning rate (Adam)
    critic_lr: float = 1e-3  # critic learning rate (Adam)
    gamma: float = 0.99  # discount of the -1 per step reward (per step's worth of ticks on the clock)
    critic_hidden: int = 128  # critic MLP width (2 hidden layers)
    max_grad_norm: float = 10.0  # gradient clipping

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def apply_overrides(hyper: MarlHyper, items: list[str]) -> MarlHyper:
    """Set hyperparameters from ``KEY=VALUE`` strings (`mures train --hp`), typed by the field;
    a ValueError names an unknown key or a value of the wrong type."""
    known = {f.name: f for f in fields(hyper)}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in known:
            raise ValueError(
                f"--hp {item!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(known))}"
                if sep
                else f"--hp {item!r}: expected KEY=VALUE"
            )
        typ = type(getattr(hyper, key))
        try:
            value = typ(text) if typ is not bool else text.lower() in ("1", "true", "yes")
        except ValueError:
            raise ValueError(f"--hp {key}: expected a {typ.__name__}, got {text!r}") from None
        if isinstance(value, (int, float)) and not isinstance(value, bool) and (math.isnan(value) or value < 0):
            raise ValueError(f"--hp {key}: expected a non-negative number, got {text!r}")
        setattr(hyper, key, value)
    if hyper.episodes < 1 or hyper.envs < 1:
        raise ValueError("episodes and envs must be positive")
    return hyper


# ---------------------------------------------------------------------- networks
class TeamActor(nn.Module):
    """Robot i's network i of a TeamPolicy, in the environment's action space:
    observation (..., N, 2n), action_mask (..., N, d) -> logits (..., N, d), NEG_INF where masked."""

    nbr: torch.Tensor  # (n, d) N[p] in the environment's action order

    def __init__(self, policy: TeamPolicy, graph: Graph) -> None:
        super().__init__()
        self.policy = policy
        self.n, self.N = graph.n, policy.N
        self.register_buffer("nbr", torch.as_tensor(graph.nbr))

    def split(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(M, N, 2n) -> positions (M, N) and beliefs (M, N, n)."""
        return observation[..., : self.n].argmax(-1), observation[..., self.n :]

    def forward(self, observation: torch.Tensor, action_mask: torch.Tensor) -> torch.Tensor:
        lead = observation.shape[:-2]
        obs = observation.reshape(-1, self.N, 2 * self.n)
        pos, bel = self.split(obs)
        node_logits = self.policy.logits(pos, bel)  # (M, N, n)
        logits = torch.gather(node_logits, 2, self.nbr[pos])  # (M, N, d)
        logits = logits.masked_fill(~action_mask.reshape(logits.shape), NEG_INF)
        return logits.reshape(*lead, self.N, -1)


def make_actor(
    graph: Graph, robots: int, hidden: int | None, device: torch.device
) -> tuple[TeamPolicy, TensorDictModule, ProbabilisticActor]:
    """The team's networks, the logits module (("agents", "observation"), ("agents", "action_mask"))
    -> ("agents", "logits"), and the stochastic actor sampling ("agents", "action") with its
    ("agents", "action_log_prob")."""
    policy = TeamPolicy(graph.n, robots, torch.as_tensor(graph.adjacency()), hidden=hidden).to(device)
    logits = TensorDictModule(
        TeamActor(policy, graph).to(device),
        in_keys=[("agents", "observation"), ("agents", "action_mask")],
        out_keys=[("agents", "logits")],
    )
    actor = ProbabilisticActor(
        logits,
        in_keys={"logits": ("agents", "logits")},
        out_keys=[("agents", "action")],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
        log_prob_key=("agents", "action_log_prob"),
    )
    return policy, logits, actor


def central_input(state: torch.Tensor, observation: torch.Tensor) -> torch.Tensor:
    """What a centralised critic reads: the state (..., S) and every robot's observation
    (..., N, 2n), as (..., S + 2nN)."""
    return torch.cat([state, observation.flatten(-2)], dim=-1)


def agent_input(state: torch.Tensor, observation: torch.Tensor, *extra: torch.Tensor) -> torch.Tensor:
    """Per robot, the state and its own observation (and ``extra`` (..., N, k) inputs):
    (..., S), (..., N, 2n) -> (..., N, S + 2n + k)."""
    s = state.unsqueeze(-2).expand(*state.shape[:-1], observation.shape[-2], state.shape[-1])
    return torch.cat([s, observation, *extra], dim=-1)


def mlp(inputs: int, outputs: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, outputs)
    )


def robot_mlps(inputs: int, outputs: int, robots: int, hidden: int) -> MultiAgentMLP:
    """One MLP per robot (inputs -> hidden -> hidden -> outputs, ReLU, nothing shared), evaluated
    for the team at once by TorchRL's MultiAgentMLP: (..., N, inputs) -> (..., N, outputs)."""
    return MultiAgentMLP(
        n_agent_inputs=inputs,
        n_agent_outputs=outputs,
        n_agents=robots,
        centralized=False,
        share_params=False,
        depth=2,
        num_cells=hidden,
        activation_class=nn.ReLU,
    )


def clip_step(
    opt: torch.optim.Optimizer, loss: torch.Tensor, params: list[torch.nn.Parameter], max_norm: float
) -> None:
    """One optimiser step on ``loss`` with the gradient's norm clipped to ``max_norm``."""
    opt.zero_grad()
    loss.backward()
    torch.nn.utils.clip_grad_norm_(params, max_norm)
    opt.step()


def soft_update(target: nn.Module, source: nn.Module, tau: float) -> None:
    """Polyak averaging of target networks: target <- (1 - tau) target + tau source."""
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(source.parameters()), tau)


def agents_done(td: TensorDictBase) -> TensorDictBase:
    """Copy the team's ("next", "done"/"terminated") (..., 1) to every robot (..., N, 1), where
    TorchRL's per-agent value estimators look for them."""
    N = td.get(("agents", "observation")).shape[-2]
    for key in ("done", "terminated"):
        flag = td.get(("next", key))
        td.set(("next", "agents", key), flag.unsqueeze(-2).expand(*flag.shape[:-1], N, 1))
    return td


# ---------------------------------------------------------------------- the run
class MarlRun:
    """One training run's environment, the team's actor and the bookkeeping: the budget, the
    learning curve, progress, the stop request and Algorithm 2's EM updates of the robots' belief
    model (as CE-PG's: Gamma_hat_0 = I and a uniform b0, re-estimated from missions flown with
    the current actors). ``policy``, ``logits`` and ``actor`` are ``make_actor``'s three views."""

    def __init__(
        self,
        name: str,
        graph: Graph,
        target: TargetModel,
        sensor: Sensor,
        cfg: TrainConfig,
        hyper: MarlHyper,
        init_model: TargetModel | None = None,
        progress: Progress | None = None,
        should_stop: Callable[[], bool] | None = None,
        checkpoint: str | Path | None = None,
        checkpoint_every: float = CHECKPOINT_EVERY_S,
        models_per_tick: bool = False,
    ) -> None:
        self.name, self.sensor = name, sensor
        self.cfg, self.hyper = cfg, hyper
        self.device = torch.device(cfg.device)
        torch.manual_seed(cfg.seed)
        model = target if cfg.belief == "true" else (init_model or identity_model(graph))
        scenario = make_scenario(
            graph,
            cfg.robots,
            sensor.eta_fn,
            sensor.eta_fp,
            sensor.detection,
            target,
            model,
            speed=cfg.speed,
            tick=cfg.tick,
            models_per_tick=models_per_tick,
        )
        # on the clock the simulator's target (and so EM's reference) is the model per tick
        self.graph, self.target, self.clock = graph, scenario.target, scenario.clock
        self.env = MuresTorchEnv(scenario, hyper.envs, seed=cfg.seed * 7_919, device=self.device)
        self.model_kind = model.kind
        self.progress, self.should_stop = progress, should_stop
        self.episodes = self.env_steps = self.updates = 0
        self.next_em = cfg.em_first if cfg.belief == "em" else math.inf
        self.em_log: list[dict[str, Any]] = []
        self.curve: list[dict[str, Any]] = []
        self.curve_every = max(1, hyper.episodes // 200)
        self.next_curve = self.curve_every
        self._window = [0, 0.0, 0]
        self.t0 = time.perf_counter()
        self.interrupted = False
        self.policy, self.logits, self.actor = make_actor(graph, cfg.robots, cfg.hidden, self.device)
        self.resumed: list[dict[str, Any]] = []  # where each resumption took the run up
        self.checkpointer: Checkpointer | None = None
        if checkpoint is not None:
            self.checkpointer = Checkpointer(checkpoint, self._identity(init_model), checkpoint_every)
            self.track("run", StateHolder(self._bookkeeping, self._set_bookkeeping))
            self.track("torch_rng", torch.default_generator)  # actions, minibatches, Gumbel noise
            self.track("env", self.env.core)
            self.track("policy", self.policy)

    # ------------------------------------------------------------------ checkpoints
    def _identity(self, init_model: TargetModel | None) -> dict[str, Any]:
        """What a checkpoint must match to be resumed by this run."""

        def model_id(m: TargetModel | None) -> str | None:
            if m is None:
                return None
            blob = b"".join(np.ascontiguousarray(a).tobytes() for a in (m.src, m.dst, m.prob, m.b0))
            return f"{m.kind}:{hashlib.sha256(blob).hexdigest()[:16]}"

        return {
            "algorithm": self.name,
            "hyperparameters": self.hyper.to_dict(),
            "config": self.cfg.to_dict(),
            "graph_id": self.graph.graph_id,
            "sensor": [self.sensor.eta_fn, self.sensor.eta_fp, self.sensor.detection],
            "target": model_id(self.target),
            "init_model": model_id(init_model),
        }

    def _bookkeeping(self) -> dict[str, Any]:
        return {
            "episodes": self.episodes,
            "env_steps": self.env_steps,
            "updates": self.updates,
            "next_em": self.next_em,
            "em_log": self.em_log,
            "model_kind": self.model_kind,
            "curve": self.curve,
            "next_curve": self.next_curve,
            "window": list(self._window),
            "wall_seconds": time.perf_counter() - self.t0,
            "resumed": self.resumed,
        }

    def _set_bookkeeping(self, b: dict[str, Any]) -> None:
        self.episodes, self.env_steps, self.updates = b["episodes"], b["env_steps"], b["updates"]
        self.next_em, self.em_log, self.model_kind = b["next_em"], list(b["em_log"]), b["model_kind"]
        self.curve, self.next_curve, self._window = list(b["curve"]), b["next_curve"], list(b["window"])
        self.resumed = list(b["resumed"])
        self.t0 = time.perf_counter() - b["wall_seconds"]  # wall_seconds: training time, summed over the pieces

    def track(self, name: str, obj: Any) -> None:
        """Save ``obj`` (a module, optimiser, generator, replay buffer, collector, ...) in this run's
        checkpoints (shared/learning/marl/checkpoint.py); nothing without a checkpoint directory."""
        if self.checkpointer is not None:
            self.checkpointer.track(name, obj)

    def resume(self) -> bool:
        """Continue from the checkpoint directory's last checkpoint, if there is one: called by a
        method's ``train`` once everything is built and tracked, before its loop. True if resumed."""
        if self.checkpointer is None or not self.checkpointer.load():
            return False
        self.resumed.append({"episodes": self.episodes, "wall_seconds": round(time.perf_counter() - self.t0, 3)})
        print(
            f"{self.name}: continuing from the checkpoint in {self.checkpointer.path}, "
            f"{self.episodes:,} of {self.hyper.episodes:,} episodes done",
            file=sys.stderr,
            flush=True,
        )
        return True

    @property
    def belief(self) -> Any:
        return self.env.core.belief

    @property
    def gamma(self) -> float:
        """The discount per environment step: ``hyper.gamma`` per step, or on the clock per tick
        (hyper.gamma ** (1 / ticks a step lasts), so that a step's worth of ticks discounts as much)."""
        return self.hyper.gamma ** (1.0 / self.env.scenario.ticks_per_step)

    def after_steps(self, steps: int) -> bool:
        """Account ``steps`` team steps (B per environment step) and the episodes they ended;
        run EM when due; log. True when training should end (budget spent or stop asked)."""
        self.env_steps += steps
        eps, ct, cens = self.env.core.take_stats()
        self.episodes += eps
        self._window[0] += eps
        self._window[1] += ct
        self._window[2] += cens
        if self.episodes >= self.next_em:
            self.em_log.append(
                em_update(
                    self.graph,
                    self.target,
                    self.sensor,
                    self.cfg,
                    self.policy,
                    self.belief,
                    self.episodes,
                    0,
                    1,
                    self.device,
                    self.clock,
                )
            )
            self.model_kind = "em"
            self.next_em = self.episodes + self.cfg.em_every
        stop = bool(self.should_stop and self.should_stop())
        over = self.episodes >= self.hyper.episodes
        if (self.episodes >= self.next_curve or over) and self._window[0] > 0:
            self._log_point()
        # a checkpoint between batches, as the run would go on (a stop's partial point comes after)
        if self.checkpointer is not None and not over and (stop or self.checkpointer.due()):
            self.checkpointer.save()
        if stop and not over:
            if self._window[0] > 0:
                self._log_point()
            self.interrupted = True
        return over or stop

    def _log_point(self) -> None:
        """A learning curve point over the episodes since the last one; progress told."""
        n_eps, ct_sum, cens_sum = self._window
        point = {
            "episodes": self.episodes,
            "mean_capture_time": ct_sum / n_eps,
            "censored_fraction": cens_sum / n_eps,
            "wall_seconds": round(time.perf_counter() - self.t0, 3),
        }
        self.curve.append(point)
        self._window = [0, 0.0, 0]
        self.next_curve = self.episodes + self.curve_every
        if self.progress:
            elapsed = time.perf_counter() - self.t0
            self.progress(
                {
                    **point,
                    "total": self.hyper.episodes,
                    "updates": self.updates,
                    "env_steps": self.env_steps,
                    "episodes_per_second": self.episodes / max(elapsed, 1e-9),
                }
            )

    def result(self, extra: dict[str, Any] | None = None) -> TrainResult:
        wall = time.perf_counter() - self.t0
        model = self.belief.model(self.graph, self.model_kind) if self.cfg.belief == "em" else self.target
        summary = {
            "algorithm": self.name,
            "episodes": self.episodes,
            "env_steps": self.env_steps,
            "updates": self.updates,
            "wall_seconds": round(wall, 3),
            "episodes_per_second": round(self.episodes / max(wall, 1e-9), 1),
            "env_steps_per_second": round(self.env_steps / max(wall, 1e-9), 1),
            "processes": 1,
            "interrupted": self.interrupted,
            "resumed": self.resumed,
            "final_mean_capture_time": self.curve[-1]["mean_capture_time"] if self.curve else None,
            "belief_model": model.kind,
            "clock": None
            if self.clock is None
            else {**self.clock.summary(), "unit": "ticks", "gamma_per_tick": self.gamma},
            "hyperparameters": self.hyper.to_dict(),
            "em_updates": self.em_log,
            "learning_curve": self.curve,
            **(extra or {}),
        }
        return TrainResult(policy=self.policy, model=model, summary=summary, interrupted=self.interrupted)

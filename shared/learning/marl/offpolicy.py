"""The loop the off-policy baselines share (MASAC, MADDPG, FACMAC, MAMBPO): a TorchRL collector
fills a TorchRL replay buffer with transitions of ``envs`` episodes run side by side, and after
every ``collect`` environment steps the method takes ``updates`` gradient steps on minibatches
sampled from it. The first ``warmup`` episodes are flown by the untrained actors before updates
begin. Each method supplies a ``Learner`` with ``update(batch)``.
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Protocol

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler

from shared.learning.marl.common import MarlHyper, MarlRun, agents_done, clip_step, soft_update

logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines (buffer set-up) would interleave with progress


@dataclass
class OffPolicyHyper(MarlHyper):
    envs: int = 32
    collect: int = 8  # environment steps between rounds of updates (envs * collect transitions)
    updates: int = 4  # gradient steps per round
    minibatch: int = 256  # transitions per gradient step
    buffer: int = 200_000  # replay capacity in transitions
    warmup: int = 1_000  # episodes before the first update
    tau: float = 0.01  # Polyak rate of the target networks


class Learner(Protocol):
    def update(self, batch: TensorDictBase) -> None: ...

    def stateful(self) -> dict[str, Any]:
        """What a checkpoint saves of the learner: {name: module, optimiser, generator, buffer}."""
        ...


class TargetActorCritic:
    """The team's actor and a critic, each with a Polyak-averaged target copy and an Adam
    optimiser (MADDPG and FACMAC): ``critic_step`` then ``actor_step`` per minibatch."""

    def __init__(self, actor: torch.nn.Module, critic: torch.nn.Module, hyper: OffPolicyHyper, gamma: float) -> None:
        self.actor, self.critic, self.hyper, self.gamma = actor, critic, hyper, gamma  # gamma: MarlRun.gamma
        self.actor_target = copy.deepcopy(actor).requires_grad_(False)
        self.critic_target = copy.deepcopy(critic).requires_grad_(False)
        self.opt_actor = torch.optim.Adam(actor.parameters(), lr=hyper.lr)
        self.opt_critic = torch.optim.Adam(critic.parameters(), lr=hyper.critic_lr)

    def stateful(self) -> dict[str, Any]:
        return {
            "actor": self.actor,
            "critic": self.critic,
            "actor_target": self.actor_target,
            "critic_target": self.critic_target,
            "opt_actor": self.opt_actor,
            "opt_critic": self.opt_critic,
        }

    def critic_step(self, q: torch.Tensor, target: torch.Tensor) -> None:
        """TD regression of ``q`` on ``target`` (computed without gradient)."""
        loss = torch.nn.functional.mse_loss(q, target)
        clip_step(self.opt_critic, loss, list(self.critic.parameters()), self.hyper.max_grad_norm)

    @contextmanager
    def frozen_critic(self) -> Iterator[None]:
        """The critic's parameters out of autograd while inside: the actors' loss reads the critic
        only for its gradient with respect to the actions, and the critic's own parameter
        gradients from that pass were computed and then discarded (the critic's next step zeroes
        them first). The actors' gradients are the same to the bit, the backward pass is shorter."""
        params = [p for p in self.critic.parameters() if p.requires_grad]
        for p in params:
            p.requires_grad_(False)
        try:
            yield
        finally:
            for p in params:
                p.requires_grad_(True)

    def actor_step(self, loss: torch.Tensor) -> None:
        """The actors' step on ``loss``, then both target networks follow."""
        clip_step(self.opt_actor, loss, list(self.actor.parameters()), self.hyper.max_grad_norm)
        soft_update(self.critic_target, self.critic, self.hyper.tau)
        soft_update(self.actor_target, self.actor, self.hyper.tau)


def run_offpolicy(
    run: MarlRun,
    learner: Learner,
    hyper: OffPolicyHyper,
    on_batch: Callable[[TensorDictBase], None] | None = None,
) -> None:
    """Collect, store, update, until the run's budget is spent or a stop is asked.
    ``on_batch(data)`` (optional) sees every collected batch (MAMBPO trains its model on it)."""
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(hyper.buffer, device=run.device),
        sampler=RandomSampler(),
        batch_size=hyper.minibatch,
    )
    collector = Collector(
        run.env,
        run.actor,
        frames_per_batch=hyper.envs * hyper.collect,
        total_frames=-1,
        auto_register_policy_transforms=False,
    )
    run.track("buffer", buffer)
    run.track("collector", collector)
    for name, obj in learner.stateful().items():
        run.track(f"learner.{name}", obj)
    run.resume()
    try:
        for data in collector:
            data = agents_done(data).reshape(-1)
            buffer.extend(data.exclude(("agents", "logits"), ("next", "agents", "logits")))
            if on_batch is not None:
                on_batch(data)
            if run.episodes >= hyper.warmup:
                for _ in range(hyper.updates):
                    learner.update(buffer.sample())
                    run.updates += 1
                collector.update_policy_weights_()
            if run.after_steps(data.numel()):
                break
    finally:
        collector.shutdown()


def mean_log_degree(valid: torch.Tensor) -> float:
    """Mean over nodes of log |N[p]|: the entropy of a uniform move (valid: (n, d) bool)."""
    return float(torch.log(valid.sum(1).double()).mean()) if valid.numel() else math.nan


def unpack(batch: TensorDictBase) -> dict[str, torch.Tensor]:
    """A minibatch of M transitions as plain tensors: obs (M, N, 2n), mask (M, N, d), state (M, S),
    action (M, N), reward (M, 1) (the team's), terminated (M, 1) float, and the same ``next_``."""
    return {
        "obs": batch.get(("agents", "observation")),
        "mask": batch.get(("agents", "action_mask")),
        "state": batch.get("state"),
        "action": batch.get(("agents", "action")),
        "reward": batch.get(("next", "agents", "reward"))[..., 0, :],
        "terminated": batch.get(("next", "terminated")).float(),
        "next_obs": batch.get(("next", "agents", "observation")),
        "next_mask": batch.get(("next", "agents", "action_mask")),
        "next_state": batch.get(("next", "state")),
    }


def gumbel_actions(logits: torch.Tensor, tau: float) -> torch.Tensor:
    """A straight-through Gumbel-softmax sample (Jang et al. 2017): one-hot forward, the relaxed
    softmax's gradient backward. logits (..., d) with masked entries at NEG_INF -> (..., d)."""
    return torch.nn.functional.gumbel_softmax(logits, tau=tau, hard=True)


def valid_logit_penalty(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared logit over the allowed actions (MADDPG's regulariser of the actor's output)."""
    return (logits.square() * mask).sum() / mask.sum().clamp_min(1)

"""FACMAC: Peng et al., "FACMAC: Factored Multi-Agent Centralised Policy Gradients" (NeurIPS
2021), for discrete moves with Gumbel-softmax actions, on TorchRL's ``QMixer`` and
``MultiAgentMLP``.

Each robot's utility Q_i(o_i, a_i) (decentralised: its own observation and move) is mixed into
Q_tot = QMIX(Q_1..Q_N; s), a monotonic mixing network conditioned on the global state (Rashid et
al. 2018; TorchRL's QMixer). The critic learns Q_tot by TD(0) against target utilities, target
mixer and the target actors' next actions. The actors are updated with the paper's centralised
policy gradient: every robot's action is taken from its current policy at once (straight-through
Gumbel-softmax, Jang et al. 2017) and the team ascends the mixed Q_tot. This actor update has no
TorchRL loss and is written here.

What differs: feed-forward utilities on the belief observation (no RNN), one network per robot
instead of a shared one with an agent id, no off-policy TD(lambda).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.modules import QMixer

from shared.learning.marl.common import MarlRun, robot_mlps
from shared.learning.marl.offpolicy import (
    OffPolicyHyper,
    TargetActorCritic,
    gumbel_actions,
    run_offpolicy,
    unpack,
    valid_logit_penalty,
)
from shared.learning.train import TrainResult


@dataclass
class FacmacHyper(OffPolicyHyper):
    # OFFICE, N = 4, on the same episodes (results/marl/plateau-facmac.json): 2x10^5 episodes
    # against 10^5 -1.06 +- 0.62 steps, 4x10^5 against 2x10^5 +0.74 +- 0.62 (its curve flat over its
    # second half), so 2x10^5 is FACMAC's plateau
    episodes: int = 200_000
    lr: float = 1e-3
    critic_lr: float = 1e-3
    gumbel_tau: float = 1.0  # Gumbel-softmax temperature
    mixing_embed: int = 32  # QMIX hidden width
    logit_penalty: float = 1e-3  # weight of the mean squared logit


class FactoredCritic(nn.Module):
    """Q_tot(s, o, a) = QMIX(Q_1(o_1, a_1), .., Q_N(o_N, a_N); s): (M, S), (M, N, 2n), (M, N, d) -> (M, 1)."""

    def __init__(self, state_size: int, obs_size: int, d: int, robots: int, hidden: int, embed: int) -> None:
        super().__init__()
        self.utility = robot_mlps(obs_size + d, 1, robots, hidden)
        self.mixer = QMixer(state_shape=(state_size,), mixing_embed_dim=embed, n_agents=robots, device="cpu")

    def forward(self, state: torch.Tensor, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        q = self.utility(torch.cat([obs, actions], dim=-1))  # (M, N, 1)
        return self.mixer(q, state)


class FacmacLearner(TargetActorCritic):
    hyper: FacmacHyper

    def __init__(self, run: MarlRun, hyper: FacmacHyper) -> None:
        N, n, d = run.cfg.robots, run.graph.n, run.env.scenario.d
        critic = FactoredCritic(run.env.scenario.state_size, 2 * n, d, N, hyper.critic_hidden, hyper.mixing_embed)
        super().__init__(run.logits.module, critic.to(run.device), hyper, run.gamma)
        self.d = d

    def update(self, batch: TensorDictBase) -> None:
        b, h = unpack(batch), self.hyper
        a = torch.nn.functional.one_hot(b["action"], self.d).float()
        with torch.no_grad():
            a_next = gumbel_actions(self.actor_target(b["next_obs"], b["next_mask"]), h.gumbel_tau)
            y = b["reward"] + self.gamma * (1 - b["terminated"]) * self.critic_target(
                b["next_state"], b["next_obs"], a_next
            )
        self.critic_step(self.critic(b["state"], b["obs"], a), y)

        logits = self.actor(b["obs"], b["mask"])
        with self.frozen_critic():  # all robots' policies at once
            q_pi = self.critic(b["state"], b["obs"], gumbel_actions(logits, h.gumbel_tau))
        self.actor_step(-q_pi.mean() + h.logit_penalty * valid_logit_penalty(logits, b["mask"]))


def train(run: MarlRun, hyper: FacmacHyper) -> TrainResult:
    run_offpolicy(run, FacmacLearner(run, hyper), hyper)
    return run.result()

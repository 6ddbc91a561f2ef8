"""MADDPG: Lowe et al., "Multi-Agent Actor-Critic for Mixed Cooperative-Competitive Environments"
(NeurIPS 2017), for discrete moves as in the authors' code: Gumbel-softmax actions.

Robot i's critic Q_i(s, o_i, a_1..a_N) (a TorchRL ``MultiAgentMLP``, one network per robot)
learns by TD(0) against target networks, with the next actions drawn from the target actors;
its actor (network i of a TeamPolicy, on o_i only) ascends Q_i with the other robots' actions
from the replay buffer and its own replaced by a straight-through Gumbel-softmax sample
(Jang et al. 2017), plus the authors' small penalty on the logits. TorchRL has no MADDPG loss for
discrete actions, so this update is written here; the replay, collector and critic networks are
TorchRL's (shared/learning/marl/offpolicy.py).

What differs: the critics read the global state and the robot's own observation instead of all
observations (the state holds every position); the robots share the team reward, so the N
critics learn the same target from different inputs' networks; no policy ensembles.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from shared.learning.marl.common import MarlRun
from shared.learning.marl.masac import CentralQ
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
class MaddpgHyper(OffPolicyHyper):
    # its plateau on OFFICE, N = 4: 9.92 at 3x10^5 episodes, 10.33 at 6x10^5 (results/marl/plateau.json)
    episodes: int = 300_000
    lr: float = 1e-3  # the paper's Table II value for MADDPG
    critic_lr: float = 1e-3
    gumbel_tau: float = 1.0  # Gumbel-softmax temperature
    logit_penalty: float = 1e-3  # weight of the mean squared logit


class MaddpgLearner(TargetActorCritic):
    hyper: MaddpgHyper

    def __init__(self, run: MarlRun, hyper: MaddpgHyper) -> None:
        N, n, d = run.cfg.robots, run.graph.n, run.env.scenario.d
        critic = CentralQ(run.env.scenario.state_size + 2 * n + N * d, N, 1, hyper.critic_hidden).to(run.device)
        super().__init__(run.logits.module, critic, hyper, run.gamma)
        self.N, self.d = N, d
        self.eye = torch.eye(N, device=run.device).view(1, N, N, 1)

    def joint(self, actions: torch.Tensor) -> torch.Tensor:
        """Every robot's critic sees the joint action: (M, N, d) one-hot -> (M, N, N d)."""
        M = actions.shape[0]
        return actions.reshape(M, 1, self.N * self.d).expand(M, self.N, self.N * self.d)

    def update(self, batch: TensorDictBase) -> None:
        b, h = unpack(batch), self.hyper
        a = torch.nn.functional.one_hot(b["action"], self.d).float()  # (M, N, d)
        with torch.no_grad():
            a_next = gumbel_actions(self.actor_target(b["next_obs"], b["next_mask"]), h.gumbel_tau)
            q_next = self.critic_target(b["next_state"], b["next_obs"], self.joint(a_next))  # (M, N, 1)
            y = b["reward"].unsqueeze(1) + self.gamma * (1 - b["terminated"]).unsqueeze(1) * q_next
        self.critic_step(self.critic(b["state"], b["obs"], self.joint(a)), y)

        logits = self.actor(b["obs"], b["mask"])  # (M, N, d)
        g = gumbel_actions(logits, h.gumbel_tau)
        # robot i's critic: the buffer's joint action with robot i's own replaced by g_i
        mixed = self.eye * g.unsqueeze(1) + (1 - self.eye) * a.unsqueeze(1)  # (M, N_i, N_j, d)
        with self.frozen_critic():
            q_pi = self.critic(b["state"], b["obs"], mixed.flatten(-2))
        self.actor_step(-q_pi.mean() + h.logit_penalty * valid_logit_penalty(logits, b["mask"]))


def train(run: MarlRun, hyper: MaddpgHyper) -> TrainResult:
    run_offpolicy(run, MaddpgLearner(run, hyper), hyper)
    return run.result()

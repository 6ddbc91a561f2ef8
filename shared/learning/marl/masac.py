"""MASAC: multi-agent soft actor-critic with centralised critics and decentralised actors, the
paper's [47] baseline, built on TorchRL's ``DiscreteSACLoss`` (Christodoulou 2019's discrete SAC:
exact expectations over the discrete actions, twin Q networks, a learned temperature alpha) and
its ``MultiAgentMLP`` critics.

Robot i's critic Q_i(s, o_i, .) gives a value for each of its d actions from the global state
and its own observation (training only); its actor is network i of a TeamPolicy on its own
observation. Off-policy loop: shared/learning/marl/offpolicy.py.

What differs: the temperature's entropy target is ``target_entropy`` times the mean over nodes
of log |N[p]| (a masked action set makes TorchRL's default, 0.98 log d, unreachable at nodes of
low degree); each critic conditions on the state, not on the other robots' actions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import DiscreteSACLoss, SoftUpdate, ValueEstimators

from shared.learning.marl.common import MarlRun, agent_input, robot_mlps
from shared.learning.marl.offpolicy import OffPolicyHyper, clip_step, mean_log_degree, run_offpolicy
from shared.learning.train import TrainResult


@dataclass
class MasacHyper(OffPolicyHyper):
    # its plateau on OFFICE, N = 4: 8.11 at 10^5 episodes, 7.31 at 3x10^5 (results/marl/plateau.json); 6x10^5
    # against 3x10^5 +0.57 +- 0.32 steps on the same episodes (results/marl/plateau-masac.json)
    episodes: int = 300_000
    lr: float = 3e-4
    critic_lr: float = 1e-3
    target_entropy: float = 0.3  # entropy target as a share of a uniform move's entropy
    alpha_init: float = 0.1  # initial temperature


class CentralQ(nn.Module):
    """Robot i's critic on the global state and its own observation (and ``extra`` inputs, such
    as actions): (..., S), (..., N, 2n), (..., N, k)... -> (..., N, outputs)."""

    def __init__(self, inputs: int, robots: int, outputs: int, hidden: int) -> None:
        super().__init__()
        self.N = robots
        self.net = robot_mlps(inputs, outputs, robots, hidden)

    def forward(self, state: torch.Tensor, observation: torch.Tensor, *extra: torch.Tensor) -> torch.Tensor:
        return self.net(agent_input(state, observation, *extra))


class SacLearner:
    """One optimiser step of TorchRL's DiscreteSACLoss on a minibatch, then the target update."""

    def __init__(self, loss: DiscreteSACLoss, hyper: MasacHyper) -> None:
        self.loss, self.hyper = loss, hyper
        self.actor_params = list(loss.actor_network_params.flatten_keys().values())
        self.critic_params = list(loss.qvalue_network_params.flatten_keys().values())
        self.opt_actor = torch.optim.Adam(self.actor_params, lr=hyper.lr)
        self.opt_critic = torch.optim.Adam(self.critic_params, lr=hyper.critic_lr)
        self.opt_alpha = torch.optim.Adam([loss.log_alpha], lr=hyper.lr)
        self.target = SoftUpdate(loss, tau=hyper.tau)

    def stateful(self) -> dict[str, Any]:
        # the loss module holds the actor's and critics' parameters, their targets and log alpha
        return {
            "loss": self.loss,
            "opt_actor": self.opt_actor,
            "opt_critic": self.opt_critic,
            "opt_alpha": self.opt_alpha,
        }

    def update(self, batch: TensorDictBase) -> None:
        terms = self.loss(batch)
        clip_step(self.opt_critic, terms["loss_qvalue"], self.critic_params, self.hyper.max_grad_norm)
        clip_step(self.opt_actor, terms["loss_actor"], self.actor_params, self.hyper.max_grad_norm)
        clip_step(self.opt_alpha, terms["loss_alpha"], [self.loss.log_alpha], self.hyper.max_grad_norm)
        self.target.step()


def sac_loss(run: MarlRun, hyper: MasacHyper) -> DiscreteSACLoss:
    """TorchRL's discrete SAC loss over the team's actor and per-robot central critics."""
    env, N, n, d = run.env, run.cfg.robots, run.graph.n, run.env.scenario.d
    q = TensorDictModule(
        CentralQ(env.scenario.state_size + 2 * n, N, d, hyper.critic_hidden).to(run.device),
        in_keys=["state", ("agents", "observation")],
        out_keys=[("agents", "action_value")],
    )
    loss = DiscreteSACLoss(
        actor_network=run.actor,
        qvalue_network=q,
        action_space="categorical",
        num_actions=d,
        num_qvalue_nets=2,
        alpha_init=hyper.alpha_init,
        # on the clock a robot chooses about once a step's worth of ticks and has one action in
        # between (entropy 0), so the target per tick is a step's over the ticks a step lasts
        target_entropy=hyper.target_entropy * mean_log_degree(env.core.valid) / env.scenario.ticks_per_step,
        loss_function="l2",
    )
    loss.set_keys(
        action=("agents", "action"),
        action_value=("agents", "action_value"),
        reward=("agents", "reward"),
        done=("agents", "done"),
        terminated=("agents", "terminated"),
        value=("agents", "state_value"),
    )
    loss.make_value_estimator(ValueEstimators.TD0, gamma=run.gamma)
    return loss


def train(run: MarlRun, hyper: MasacHyper) -> TrainResult:
    run_offpolicy(run, SacLearner(sac_loss(run, hyper), hyper), hyper)
    return run.result()

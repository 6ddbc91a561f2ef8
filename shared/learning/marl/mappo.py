"""MAPPO: Yu et al., "The Surprising Effectiveness of PPO in Cooperative Multi-Agent Games"
(NeurIPS 2022 Datasets and Benchmarks), on TorchRL: its collector, GAE and ``ClipPPOLoss``.

Decentralised actors (network i of a TeamPolicy per robot, shared/learning/marl/common.py) and
one centralised value function V(s, o_1..o_N) shared by the team (the reward is the team's).
Each iteration collects ``steps`` steps of ``envs`` episodes side by side, computes GAE(gamma,
lambda) advantages, and runs ``epochs`` passes of clipped-surrogate updates over minibatches.

What differs from the paper's implementation: no recurrent networks (the belief is the robot's
memory), no value normalisation (PopArt), separate actor/critic optimisers with the same
clipping; the actor's architecture is CE-PG's (2n -> 2n -> n), so that the team runs on robots.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from shared.learning.marl.common import MarlHyper, MarlRun, agents_done, central_input, clip_step, mlp
from shared.learning.train import TrainResult


@dataclass
class MappoHyper(MarlHyper):
    # its plateau on OFFICE, N = 4: 7.88 at 4x10^5 episodes, 7.82 at 8x10^5 (results/marl/plateau.json)
    episodes: int = 400_000
    envs: int = 128
    lr: float = 1e-3
    critic_lr: float = 1e-3
    steps: int = 32  # environment steps per iteration (B * steps team steps per batch)
    lmbda: float = 0.95  # GAE lambda
    clip: float = 0.2  # PPO clip epsilon
    epochs: int = 4  # passes over each batch
    minibatch: int = 1024  # team steps per minibatch
    entropy: float = 0.01  # entropy bonus coefficient


class CentralValue(nn.Module):
    """V(s, o_1..o_N): (..., S), (..., N, 2n) -> (..., N, 1), the team's value for every robot."""

    def __init__(self, inputs: int, robots: int, hidden: int) -> None:
        super().__init__()
        self.N = robots
        self.net = mlp(inputs, 1, hidden)

    def forward(self, state: torch.Tensor, observation: torch.Tensor) -> torch.Tensor:
        v = self.net(central_input(state, observation))
        return v.unsqueeze(-2).expand(*v.shape[:-1], self.N, 1)


def train(run: MarlRun, hyper: MappoHyper) -> TrainResult:
    env, dev, N, n, actor = run.env, run.device, run.cfg.robots, run.graph.n, run.actor
    S = env.scenario.state_size
    critic = TensorDictModule(
        CentralValue(S + 2 * n * N, N, hyper.critic_hidden).to(dev),
        in_keys=["state", ("agents", "observation")],
        out_keys=[("agents", "state_value")],
    )
    loss = ClipPPOLoss(
        actor_network=actor,
        critic_network=critic,
        clip_epsilon=hyper.clip,
        entropy_bonus=hyper.entropy > 0,
        entropy_coeff=hyper.entropy,
        normalize_advantage=True,
        normalize_advantage_exclude_dims=(-2,),  # per robot (identical here: one team reward)
    )
    loss.set_keys(
        reward=("agents", "reward"),
        action=("agents", "action"),
        sample_log_prob=("agents", "action_log_prob"),
        value=("agents", "state_value"),
        done=("agents", "done"),
        terminated=("agents", "terminated"),
    )
    loss.make_value_estimator(ValueEstimators.GAE, gamma=run.gamma, lmbda=hyper.lmbda)
    opt = torch.optim.Adam(
        [
            {"params": list(actor.parameters()), "lr": hyper.lr},
            {"params": list(critic.parameters()), "lr": hyper.critic_lr},
        ]
    )
    collector = Collector(
        env, actor, frames_per_batch=hyper.envs * hyper.steps, total_frames=-1, auto_register_policy_transforms=False
    )
    run.track("collector", collector)
    run.track("loss", loss)  # the actor's and the critic's parameters
    run.track("opt", opt)
    run.resume()
    try:
        for data in collector:
            data = agents_done(data)
            with torch.no_grad():
                loss.value_estimator(
                    data, params=loss.critic_network_params, target_params=loss.target_critic_network_params
                )
            flat = data.reshape(-1)
            for _ in range(hyper.epochs):
                perm = torch.randperm(flat.shape[0], device=dev)
                for a in range(0, flat.shape[0], hyper.minibatch):
                    mb = flat[perm[a : a + hyper.minibatch]]
                    terms = loss(mb)
                    total = terms["loss_objective"] + terms["loss_critic"] + terms.get("loss_entropy", 0.0)
                    clip_step(opt, total, list(loss.parameters()), hyper.max_grad_norm)
                    run.updates += 1
            collector.update_policy_weights_()
            if run.after_steps(data.numel()):
                break
    finally:
        collector.shutdown()
    return run.result()

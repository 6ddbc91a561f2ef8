"""MAMBPO: Willemsen, Coppola and de Croon, "MAMBPO: Sample-efficient multi-robot reinforcement
learning using learned world models" (IROS 2021): MASAC (shared/learning/marl/masac.py, TorchRL's
DiscreteSACLoss) trained on a mix of real transitions and short branched rollouts in a learned
model (MBPO, Janner et al. 2019). TorchRL has no model-based MARL component, so the model and
the rollouts are written here.

The learned model is an ensemble of K networks for the target's motion, P(e' | e), each trained
by maximum likelihood on the real transitions' true states (training is centralised: the
simulator's state is at hand). A branched rollout starts from real states of the latest batch and
runs ``horizon`` steps with the current actors: the robots' moves are applied as given (they are
the actions), the next target is drawn from a randomly chosen ensemble member, each robot's z from
the known sensor model (its belief filter uses that model), capture and truncation as in the
simulator, each belief updated by Eq. 1, reward -1 per step. These transitions fill a model
buffer; every SAC minibatch mixes ``real_ratio`` real transitions with model ones.

On the mission clock (shared/envs/core.py) a model step is a tick, as the environment's is: the
ensemble learns the target's motion per tick from consecutive ticks' states; a robot on a node
(no ticks left) sets off for the node its action leads to, taking the move's travel time in ticks
(the scenario's table), one in transit goes on with its one action; only robots on a node read z
and update their beliefs with it (the others predict, Lambda = I); the reward is the environment's
-1 / (ticks a step lasts); the state carries every robot's goal and ticks left.

What differs from the paper: the learned part is the target's motion only (the robots' own moves
and their sensor are known to them, so they are not learned), and the ensemble's members are
sampled per rollout rather than per step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.data.replay_buffers import RandomSampler

from shared.learning.marl.common import MarlRun, mlp
from shared.learning.marl.masac import MasacHyper, SacLearner, sac_loss
from shared.learning.marl.offpolicy import run_offpolicy
from shared.learning.train import TrainResult


@dataclass
class MambpoHyper(MasacHyper):
    # its plateau on OFFICE, N = 4: 2x10^5 against 10^5 -0.45 +- 0.32 steps, 4x10^5 against 2x10^5
    # -0.01 +- 0.28 on the same episodes (results/marl/plateau-mambpo.json)
    episodes: int = 200_000
    ensemble: int = 3  # K target-motion networks
    model_lr: float = 1e-3
    model_hidden: int = 128
    model_steps: int = 2  # gradient steps on the model per collected batch
    horizon: int = 3  # branched rollout length
    rollout_starts: int = 256  # real states each round's rollouts start from
    real_ratio: float = 0.5  # share of real transitions in a minibatch
    model_buffer: int = 100_000


class TargetMotionEnsemble(nn.Module):
    """K networks onehot(e) (M, n) -> logits of e' (K, M, n)."""

    def __init__(self, n: int, k: int, hidden: int) -> None:
        super().__init__()
        self.members = nn.ModuleList(mlp(n, n, hidden) for _ in range(k))

    def forward(self, onehot_e: torch.Tensor) -> torch.Tensor:
        return torch.stack([m(onehot_e) for m in self.members])


class WorldModel:
    """The ensemble, its training on real transitions, and branched rollouts (module docstring)."""

    def __init__(self, run: MarlRun, hyper: MambpoHyper) -> None:
        self.run, self.actor, self.hyper = run, run.actor, hyper
        core = run.env.core
        self.core, self.n, self.N = core, core.n, core.N
        self.net = TargetMotionEnsemble(self.n, hyper.ensemble, hyper.model_hidden).to(run.device)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=hyper.model_lr)
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(hyper.model_buffer, device=run.device), sampler=RandomSampler()
        )
        self.gen = torch.Generator(device=run.device).manual_seed(run.cfg.seed + 17)
        clock = core.scenario.clock
        self.move_ticks = None if clock is None else torch.as_tensor(clock.ticks, dtype=torch.long, device=run.device)
        self.last_loss = float("nan")

    def _target(self, state: torch.Tensor) -> torch.Tensor:
        """The target's row from the state's last onehot block: (M, S) -> (M,)."""
        n, N = self.n, self.N
        return state[:, N * n : (N + 1) * n].argmax(-1)

    def _robots_move(
        self, state: torch.Tensor, pos: torch.Tensor, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]:
        """Where the robots are after one model step: (M, S) states, (M, N) nodes and actions ->
        (positions, goals, ticks left, on a node) (M, N) each; in steps every robot moves to its
        action's node at once (goals, ticks left and on a node None). On the clock the simulator's
        rule (shared/engine/sim.py): a robot on a node sets off for its action's node, its ticks
        left the move's travel time, a robot in transit goes on; each loses a tick, and one with
        none left stands on its goal."""
        core, n, N = self.core, self.n, self.N
        if self.move_ticks is None:  # in steps
            return core.destinations(pos, action), None, None, None
        goal = state[:, (N + 1) * n : (2 * N + 1) * n].view(-1, N, n).argmax(-1)
        start = (2 * N + 1) * n
        left = torch.round(state[:, start : start + N] * core.scenario.ticks_per_step).long()
        on_node = left == 0
        goal = torch.where(on_node, core.destinations(pos, action), goal)
        left = torch.where(on_node, self.move_ticks[pos, goal], left) - 1  # a move takes >= 1 tick: left >= 0
        ready = left == 0
        return torch.where(ready, goal, pos), goal, left, ready

    def fit(self, data: TensorDictBase) -> None:
        e = self._target(data.get("state"))
        e_next = self._target(data.get(("next", "state")))
        moved = (data.get(("next", "state"))[:, -1] > data.get("state")[:, -1]).float()  # not a t = 0 capture
        x = torch.nn.functional.one_hot(e, self.n).float()
        for _ in range(self.hyper.model_steps):
            logits = self.net(x)  # (K, M, n)
            nll = torch.nn.functional.cross_entropy(
                logits.flatten(0, 1), e_next.repeat(self.hyper.ensemble), reduction="none"
            ).view(self.hyper.ensemble, -1)
            loss = (nll * moved).sum() / moved.sum().clamp_min(1) / self.hyper.ensemble
            self.opt.zero_grad()
            loss.backward()
            self.opt.step()
        self.last_loss = float(loss.detach())

    @torch.no_grad()
    def rollout(self, data: TensorDictBase) -> None:
        """Branched rollouts from the states of ``data`` (the latest real batch) into the buffer."""
        core, h, n, N = self.core, self.hyper, self.n, self.N
        start = data[torch.randperm(data.shape[0], generator=self.gen, device=data.device)[: h.rollout_starts]]
        start = start[~start.get(("next", "done")).squeeze(-1)]
        td = start.get("next").select(("agents", "observation"), ("agents", "action_mask"), "state")
        if td.shape[0] == 0:
            return
        member = torch.randint(0, h.ensemble, (td.shape[0],), generator=self.gen, device=td.device)
        t_max = core.scenario.t_max
        belief = core.belief
        for _ in range(h.horizon):
            obs, mask, state = td.get(("agents", "observation")), td.get(("agents", "action_mask")), td.get("state")
            td = self.actor(td)
            a = td.get(("agents", "action"))  # (M, N)
            pos = obs[..., :n].argmax(-1)
            b = obs[..., n:]
            e = self._target(state)
            t = torch.round(state[:, -1] * t_max)
            pos_next, goal, left, ready = self._robots_move(state, pos, a)
            logits = self.net(torch.nn.functional.one_hot(e, n).float())  # (K, M, n)
            probs = torch.softmax(logits[member, torch.arange(len(e), device=e.device)], -1)
            e_next = torch.multinomial(probs, 1, generator=self.gen).squeeze(1)
            in_d = (core.sim.dsets[pos_next] == e_next.view(-1, 1, 1)).any(-1)  # (M, N): e in D(p)
            u = torch.rand(in_d.shape, generator=self.gen, device=in_d.device)
            sensor = core.scenario.sensor
            z = torch.where(in_d, u >= sensor.eta_fn, u < sensor.eta_fp)
            if ready is not None:  # in transit: no reading
                in_d, z = in_d & ready, z & ready
            captured = (z & in_d).any(1)
            t_next = t + 1
            truncated = ~captured & (t_next >= t_max)
            b_next = belief.update(b, belief.likelihood(pos_next, z, ready))  # Eq. 1
            obs_next = core.encode_observation(pos_next, b_next)
            state_next = core.encode_state(pos_next, e_next, t_next, goal, left)
            mask_next = core.encode_action_mask(pos_next, ready)  # in transit: action 0 only
            M = len(e)
            term = captured.unsqueeze(1)
            done = (captured | truncated).unsqueeze(1)
            nxt = TensorDict(
                {
                    "agents": TensorDict(
                        {
                            "observation": obs_next,
                            "action_mask": mask_next,
                            "reward": torch.full((M, N, 1), core.reward_per_step, device=obs.device),
                            "done": done.unsqueeze(1).expand(M, N, 1),
                            "terminated": term.unsqueeze(1).expand(M, N, 1),
                        },
                        batch_size=[M, N],
                    ),
                    "state": state_next,
                    "done": done,
                    "terminated": term,
                    "truncated": truncated.unsqueeze(1),
                },
                batch_size=[M],
            )
            step = TensorDict(
                {
                    "agents": TensorDict({"observation": obs, "action_mask": mask, "action": a}, batch_size=[M, N]),
                    "state": state,
                    "next": nxt,
                },
                batch_size=[M],
            )
            self.buffer.extend(step)
            keep = ~done.squeeze(1)
            if not bool(keep.any()):
                break
            td = nxt.select(("agents", "observation"), ("agents", "action_mask"), "state")[keep]
            member = member[keep]


class MambpoLearner:
    """SAC updates on minibatches of real and model transitions."""

    def __init__(self, sac: SacLearner, model: WorldModel, hyper: MambpoHyper) -> None:
        self.sac, self.model, self.hyper = sac, model, hyper

    def stateful(self) -> dict[str, Any]:
        m = self.model
        return {**self.sac.stateful(), "model": m.net, "model_opt": m.opt, "model_buffer": m.buffer, "model_gen": m.gen}

    def update(self, batch: TensorDictBase) -> None:
        M = batch.shape[0]
        k = max(1, round(self.hyper.real_ratio * M))
        if len(self.model.buffer) > 0 and k < M:
            fake = self.model.buffer.sample(M - k)
            keys = list(fake.keys(True, True))
            batch = torch.cat([batch[:k].select(*keys), fake.select(*keys)], 0)
        self.sac.update(batch)


def train(run: MarlRun, hyper: MambpoHyper) -> TrainResult:
    model = WorldModel(run, hyper)
    learner = MambpoLearner(SacLearner(sac_loss(run, hyper), hyper), model, hyper)

    def on_batch(data: TensorDictBase) -> None:
        model.fit(data)
        if run.episodes >= hyper.warmup:
            model.rollout(data)

    run_offpolicy(run, learner, hyper, on_batch=on_batch)
    return run.result({"model_nll": round(model.last_loss, 4)})

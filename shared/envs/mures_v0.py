"""MuRES as a PettingZoo ParallelEnv and as a batched TorchRL environment (docs/SPEC.md section 11).

    from shared.envs import mures_v0
    env = mures_v0.parallel_env(map="office", robots=4, seed=0)         # PettingZoo, one episode
    env = mures_v0.torchrl_env(map="office", robots=4, batch_size=[256])  # TorchRL, B episodes

Both run the engine's simulator with every robot's own belief (shared/envs/core.py has the
observation, action, reward and state definitions). Options are those of `mures evaluate`:
eta_fn, eta_fp, detection, target (uniform, lazy:STAY, model.json) and belief_model (the robots'
Gamma_hat: true, identity or model.json); ``speed`` (m/s, and ``tick`` s) puts a graph with edge
lengths on the mission clock: a step is a tick, and a robot in transit has one action
(shared/envs/core.py).
"""

from __future__ import annotations

import functools
from typing import Any, ClassVar

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from shared.core.graph import Graph
from shared.engine.memory import keep_freed_memory
from shared.envs.core import EnvCore, Scenario, make_scenario

__all__ = ["MuresParallelEnv", "MuresTorchEnv", "parallel_env", "torchrl_env"]


_DONE = ("done", "terminated", "truncated")
_AGENT_OBS = ("observation", "action_mask")  # what a reset makes afresh, per robot
_ROOT_OBS = ("agents", "state", *_DONE)  # root entries a reset makes afresh ("agents" is rebuilt)


def _agent(i: int) -> str:
    return f"robot_{i}"


class MuresParallelEnv(ParallelEnv):
    """One episode at a time, PettingZoo's parallel API. Agents ``robot_0`` .. ``robot_{N-1}``."""

    metadata: ClassVar[dict[str, Any]] = {"name": "mures_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, scenario: Scenario, seed: int | None = None) -> None:
        self.scenario = scenario
        self.possible_agents = [_agent(i) for i in range(scenario.robots)]
        self.agents: list[str] = []
        self.render_mode = None
        self._seed = seed
        self.core = EnvCore(scenario, batch=1, seed=0 if seed is None else seed)
        if seed is None:
            self.core.seed(int(np.random.SeedSequence().generate_state(1)[0]))
        n, d = scenario.graph.n, scenario.d
        self._obs_space = spaces.Dict(
            {
                "observation": spaces.Box(0.0, 1.0, shape=(2 * n,), dtype=np.float32),
                "action_mask": spaces.Box(0, 1, shape=(d,), dtype=np.int8),
            }
        )
        self._act_space = spaces.Discrete(d)
        self.state_space = spaces.Box(0.0, 1.0, shape=(scenario.state_size,), dtype=np.float32)
        self.steps = 0

    @functools.cache  # noqa: B019 - PettingZoo's idiom: one space object per agent
    def observation_space(self, agent: str) -> spaces.Space:
        return self._obs_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Space:
        return self._act_space

    def _observations(self) -> dict[str, dict[str, np.ndarray]]:
        obs = self.core.observation()[0].numpy()
        mask = self.core.action_mask()[0].numpy().astype(np.int8)
        return {a: {"observation": obs[i], "action_mask": mask[i]} for i, a in enumerate(self.possible_agents)}

    def reset(self, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        if seed is not None:
            self.core.seed(seed)
        self.core.reset()
        self.agents = list(self.possible_agents)
        self.steps = 0
        return self._observations(), {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise RuntimeError("step() after the episode ended: call reset()")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"no action for {', '.join(missing)}")
        act = torch.tensor([[int(actions[a]) for a in self.possible_agents]], dtype=torch.long)
        reward, term, trunc = self.core.step(act)
        self.steps += 1
        obs = self._observations()
        r, te, tr = float(reward[0]), bool(term[0]), bool(trunc[0])
        infos: dict[str, dict[str, Any]] = {a: {} for a in self.agents}
        if te or tr:
            for a in self.agents:
                infos[a] = {"capture_time": int(self.core.sim.t[0]), "captured": te}
                if self.scenario.clock is not None:  # capture_time counts ticks
                    infos[a]["capture_time_s"] = int(self.core.sim.t[0]) * self.scenario.clock.tick_s
        out = (
            obs,
            {a: r for a in self.agents},
            {a: te for a in self.agents},
            {a: tr for a in self.agents},
            infos,
        )
        if te or tr:
            self.agents = []
        return out

    def state(self) -> np.ndarray:
        return self.core.state()[0].numpy()

    def render(self) -> None:
        return None

    def close(self) -> None:
        return None


class MuresTorchEnv(EnvBase):
    """B episodes in one TorchRL environment (batch_size [B]). Keys: ("agents", "observation")
    (B, N, 2n), ("agents", "action_mask") (B, N, d), ("agents", "action") (B, N) index into
    N[p], ("agents", "reward") (B, N, 1), "state" (B, S), and "done", "terminated",
    "truncated" (B, 1) for the whole team. Finished episodes are restarted by ``reset`` with a
    "_reset" mask, as TorchRL's rollouts and collectors do."""

    batch_locked = True

    def __init__(self, scenario: Scenario, batch_size: int, seed: int = 0, device: torch.device | str = "cpu") -> None:
        super().__init__(device=device, batch_size=torch.Size([batch_size]))
        self.scenario = scenario
        self.core = EnvCore(scenario, batch_size, seed=seed, device=device)
        B, N, n, d = batch_size, scenario.robots, scenario.graph.n, scenario.d
        agents = Composite(
            observation=Unbounded(shape=(B, N, 2 * n), dtype=torch.float32, device=device),
            action_mask=Binary(n=d, shape=(B, N, d), dtype=torch.bool, device=device),
            shape=(B, N),
        )
        self.observation_spec = Composite(
            agents=agents,
            state=Unbounded(shape=(B, scenario.state_size), dtype=torch.float32, device=device),
            shape=(B,),
        )
        self.action_spec = Composite(
            agents=Composite(action=Categorical(n=d, shape=(B, N), device=device), shape=(B, N)), shape=(B,)
        )
        self.reward_spec = Composite(
            agents=Composite(reward=Unbounded(shape=(B, N, 1), dtype=torch.float32, device=device), shape=(B, N)),
            shape=(B,),
        )
        self.done_spec = Composite(
            done=Categorical(n=2, shape=(B, 1), dtype=torch.bool, device=device),
            terminated=Categorical(n=2, shape=(B, 1), dtype=torch.bool, device=device),
            truncated=Categorical(n=2, shape=(B, 1), dtype=torch.bool, device=device),
            shape=(B,),
        )

    @property
    def graph(self) -> Graph:
        return self.scenario.graph

    def _observe(self, reward: torch.Tensor | None = None, **done: torch.Tensor) -> TensorDict:
        """Observations of every slot (after a partial reset TorchRL reads the restarted slots'
        only, ``_update_during_reset``), with the team's ``reward`` (B,) and the done flags (B,)
        when given."""
        core = self.core
        obs, mask, state = core.observation(), core.action_mask(), core.state()
        agents = {"observation": obs, "action_mask": mask}
        if reward is not None:
            agents["reward"] = reward.view(-1, 1, 1).expand(-1, core.N, 1).clone()
        # the device on both levels: a nested TensorDict without one costs a .to() per entry.
        # Every entry is made here with its spec's shape, dtype and device, so the checks of
        # TensorDict's constructor are skipped (as TorchRL's own gym-like environments do)
        return TensorDict._new_unsafe(
            {
                "agents": TensorDict._new_unsafe(agents, batch_size=obs.shape[:2], device=self.device),
                "state": state,
                **{k: v.view(-1, 1) for k, v in done.items()},
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDict:
        mask = None
        if tensordict is not None and "_reset" in tensordict.keys():  # noqa: SIM118 - a TensorDict's keys
            mask = tensordict.get("_reset").reshape(self.core.B)
        self.core.reset(mask)
        flags = torch.zeros(3, self.core.B, dtype=torch.bool, device=self.device)
        return self._observe(done=flags[0], terminated=flags[1], truncated=flags[2])

    def _step(self, tensordict: TensorDictBase) -> TensorDict:
        reward, term, trunc = self.core.step(tensordict.get(("agents", "action")))
        return self._observe(reward=reward, done=term | trunc, terminated=term, truncated=trunc)

    def maybe_reset(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Restart the finished episodes of a step_mdp'd tensordict: what ``EnvBase.maybe_reset``
        does through ``reset`` (a "_reset" mask, ``_reset``, then a masked merge of every entry),
        done directly. The observation, mask and state are built afresh for every slot (the old
        tensors are shared with the step's "next" data, which must keep the final observations;
        a running slot's entries come out as they were, since its position and belief did not
        change). Same result, entry by entry (tests/test_envs.py), with a fraction of the tensor
        operations. A TransformedEnv around this one takes the generic path."""
        done = tensordict.get("done", None)
        if done is None or not bool(done.any()):
            return tensordict
        core = self.core
        core.reset(done.reshape(core.B))
        # reset's merge: a full reset updates the reset entries only; a partial one also pads
        # every other entry (the last action, ...) with 0 in the restarted slots. The result is
        # a new TensorDict of the same entries (its observation, mask, state and flags made
        # afresh to their specs), so no entry is set and checked one at a time
        rows = core.last_reset
        partial = len(rows) < core.B

        def kept(value: Any) -> Any:  # a tensor or a nested TensorDict (a policy's outputs, ...)
            if not partial:
                return value
            if isinstance(value, TensorDictBase):
                return value.apply(lambda x: x.index_fill(0, rows, 0))
            return value.index_fill(0, rows, 0)

        agents = {k: kept(v) for k, v in tensordict.get("agents").items() if k not in _AGENT_OBS}
        agents["observation"], agents["action_mask"] = core.observation(), core.action_mask()
        flags = torch.zeros(3, core.B, 1, dtype=torch.bool, device=self.device)  # no slot is done now
        root = {k: kept(v) for k, v in tensordict.items() if k not in _ROOT_OBS}
        root["state"] = core.state()
        root.update(zip(_DONE, flags, strict=True))
        root["agents"] = TensorDict._new_unsafe(agents, batch_size=(core.B, core.N), device=self.device)
        return TensorDict._new_unsafe(root, batch_size=self.batch_size, device=self.device)

    def _step_proc_data(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        """``_step`` makes every entry to its spec (reward (B, N, 1), the three flags (B, 1)), so
        the generic reshaping and completing of rewards and flags has nothing to do; with
        ``run_type_checks`` on, the generic checks run."""
        if self.run_type_checks:
            return super()._step_proc_data(next_tensordict)
        return next_tensordict

    def _set_seed(self, seed: int | None) -> None:
        self.core.seed(0 if seed is None else seed)


def parallel_env(
    map: str | Graph = "office", robots: int = 4, seed: int | None = None, **options: Any
) -> MuresParallelEnv:
    """The PettingZoo ParallelEnv (module docstring); ``options`` as ``make_scenario``'s."""
    return MuresParallelEnv(make_scenario(map, robots, **options), seed=seed)


def torchrl_env(
    map: str | Graph = "office",
    robots: int = 4,
    batch_size: list[int] | tuple[int, ...] | int = (256,),
    device: torch.device | str = "cpu",
    seed: int = 0,
    tune_malloc: bool = True,
    **options: Any,
) -> MuresTorchEnv:
    """The batched TorchRL environment (module docstring); ``options`` as ``make_scenario``'s.

    ``tune_malloc`` (default on): set the process's malloc to keep the few-MiB blocks a step's
    tensors take instead of mapping and unmapping them every step
    (``shared.engine.memory.keep_freed_memory``: process-wide, glibc only)."""
    dims = [batch_size] if isinstance(batch_size, int) else list(batch_size)
    if len(dims) != 1 or dims[0] < 1:
        raise ValueError(f"batch_size must be [B] with B >= 1, got {batch_size!r}")
    if tune_malloc:
        keep_freed_memory()
    return MuresTorchEnv(make_scenario(map, robots, **options), dims[0], seed=seed, device=device)

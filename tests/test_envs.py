"""The environment interfaces (docs/SPEC.md section 11): PettingZoo's and TorchRL's own checkers,
the same dynamics as the engine's simulator (a random team gives `mures evaluate --searcher
random`'s capture times), determinism for a seed, and clear errors."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test
from torchrl.envs.utils import check_env_specs

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.engine.evaluate import evaluate, mean_ci95, means_differ
from shared.engine.searchers import RandomSearcher
from shared.envs import mures_v0


def test_parallel_env_passes_pettingzoo_api_test():
    env = mures_v0.parallel_env(map="office", robots=3, seed=0)
    parallel_api_test(env, num_cycles=400)
    noisy = mures_v0.parallel_env(map="museum", robots=2, seed=1, eta_fn=0.1, eta_fp=0.05, target="lazy:0.5")
    parallel_api_test(noisy, num_cycles=200)


def test_torchrl_env_passes_check_env_specs():
    env = mures_v0.torchrl_env(map="office", robots=4, batch_size=[8], seed=0)
    check_env_specs(env)
    td = env.rollout(60, break_when_any_done=False)  # partial resets inside
    assert td["agents", "observation"].shape == (8, 60, 4, 120)
    assert td["next", "agents", "reward"].shape == (8, 60, 4, 1)
    assert td["state"].shape == (8, 60, env.scenario.state_size)
    obs = td["agents", "observation"]
    assert torch.allclose(obs[..., :60].sum(-1), torch.ones(8, 60, 4))  # onehot(p)
    assert torch.allclose(obs[..., 60:].sum(-1), torch.ones(8, 60, 4), atol=1e-4)  # beliefs sum to 1
    assert bool(td["next", "done"].any()), "60 steps of 8 random episodes should end some"


def test_torchrl_envs_own_maybe_reset_equals_torchrls_generic_one():
    """``MuresTorchEnv.maybe_reset`` (the fast path step_and_maybe_reset and the collectors take)
    gives, entry by entry, what EnvBase's reset-and-merge gives: full and partial resets, and the
    transitions in "next" keep their final observations; its ``_step_proc_data`` leaves a step's
    data as the generic one makes it."""
    from torchrl.envs import EnvBase

    for B in (1, 7):
        envs = [mures_v0.torchrl_env(map="office", robots=3, batch_size=[B], seed=3) for _ in range(2)]
        tds = [e.reset() for e in envs]
        gens = [torch.Generator().manual_seed(1) for _ in range(2)]
        resets = 0
        for step in range(150):
            out = []
            for k, (env, td) in enumerate(zip(envs, tds, strict=True)):
                deg = td["agents", "action_mask"].sum(-1)
                td["agents", "action"] = (torch.rand(deg.shape, generator=gens[k]) * deg).long()
                # a policy's other outputs ride along: padded with 0 where an episode restarts
                td["agents", "logits"] = torch.arange(float(deg.numel())).view(deg.shape) + step
                td["policy", "value"] = torch.full((B, 2), float(step + 1))
                data = env.step(td)
                final = data["next"].clone()
                # the env's own _step_proc_data (a no-op) leaves what the generic one would make
                generic = EnvBase._step_proc_data(env, final.clone())
                assert set(generic.keys(True, True)) == set(final.keys(True, True)) and (generic == final).all()
                nxt = env._step_mdp(data)
                nxt = env.maybe_reset(nxt) if k == 0 else EnvBase.maybe_reset(env, nxt)
                assert (data["next"] == final).all(), "the reset changed the step's data"
                out.append((data, nxt))
            (d0, n0), (d1, n1) = out
            resets += int(d0["next", "done"].sum())
            assert set(n0.keys(True, True)) == set(n1.keys(True, True))
            assert (d0 == d1).all() and (n0 == n1).all(), f"B={B} step {step}"
            tds = [n0, n1]
        assert resets > B, "the episodes should have ended and restarted"


def _pz_episode(env, seed, pick):
    """The last step's infos of one episode with actions ``pick(agent, observation)``."""
    obs, _ = env.reset(seed=seed)
    while env.agents:
        obs, _rewards, _terms, _truncs, infos = env.step({a: pick(a, obs[a]) for a in env.agents})
    return infos


def test_random_team_in_parallel_env_has_the_simulators_capture_times():
    """Exact: the env driven by the random searcher's own draws reproduces `evaluate` episode by
    episode (the same generator seeds, chunk = 1); in distribution: PettingZoo's masked
    action_space.sample() team against `mures evaluate --searcher random`."""
    g, sensor = builtin_graph("office"), Sensor()
    model = uniform_walk(g)
    K, seed = 40, 3
    ref = evaluate(g, model, sensor, 3, lambda s: RandomSearcher(g, seed=s), episodes=K, seed=seed, chunk=1)
    env = mures_v0.parallel_env(map="office", robots=3)
    nbr = g.nbr
    for c in range(K):
        chunk_seed = seed * 1_000_003 + c
        searcher = RandomSearcher(g, seed=chunk_seed + 7919)
        env.reset(seed=chunk_seed)
        while env.agents:
            moves = searcher.act(env.core.sim._obs())[0].numpy()  # node rows
            pos = env.core.sim.pos[0].numpy()
            actions = {a: int(np.flatnonzero(nbr[pos[i]] == moves[i])[0]) for i, a in enumerate(env.possible_agents)}
            *_, infos = env.step(actions)
        info = infos["robot_0"]
        assert info["capture_time"] == ref.capture_time[c], f"episode {c}"
        assert info["captured"] == (not ref.censored[c])

    rng = np.random.default_rng(0)
    env = mures_v0.parallel_env(map="office", robots=3, seed=11)
    for a in env.possible_agents:
        env.action_space(a).seed(int(rng.integers(1 << 31)))
    times = []
    for ep in range(400):
        infos = _pz_episode(env, None if ep else 11, lambda a, o: env.action_space(a).sample(o["action_mask"]))
        times.append(infos["robot_0"]["capture_time"])
    evaluated = evaluate(g, model, sensor, 3, lambda s: RandomSearcher(g, seed=s), episodes=1500, seed=5)
    differ, z = means_differ(times, evaluated.capture_time)
    assert not differ, (mean_ci95(times), mean_ci95(evaluated.capture_time), z)


def test_reward_is_minus_one_per_step_and_the_last_step_reports():
    env = mures_v0.parallel_env(map="office", robots=2, seed=4)
    env.reset(seed=4)
    total = 0.0
    while env.agents:
        _obs, rewards, terms, truncs, infos = env.step({a: 0 for a in env.agents})  # everyone stays
        total += rewards["robot_0"]
    info = infos["robot_0"]
    assert set(info) == {"capture_time", "captured"}
    assert total == -info["capture_time"]
    assert info["captured"] == terms["robot_0"] and truncs["robot_0"] == (not info["captured"])
    if not info["captured"]:
        assert info["capture_time"] == 3 * 60  # truncation at T_max = 3n


def test_same_seed_same_episodes():
    def run(seed):
        env = mures_v0.torchrl_env(map="museum", robots=3, batch_size=[4], seed=seed)
        torch.manual_seed(0)
        return env.rollout(40, break_when_any_done=False)

    a, b, c = run(7), run(7), run(8)
    assert torch.equal(a["next", "agents", "observation"], b["next", "agents", "observation"])
    assert torch.equal(a["next", "done"], b["next", "done"])
    assert not torch.equal(a["next", "state"], c["next", "state"])

    def episode(seed):
        env = mures_v0.parallel_env(map="office", robots=2, seed=seed)
        out = []
        obs, _ = env.reset()
        while env.agents:
            obs, *_ = env.step({a: int(np.argmax(o["action_mask"][::-1] == 1)) for a, o in obs.items()})
            out.append(obs["robot_1"]["observation"].copy())
        return np.stack(out)

    assert np.array_equal(episode(5), episode(5))


def test_belief_model_option_and_bad_options():
    env = mures_v0.parallel_env(map="office", robots=1, seed=0, belief_model="identity")
    obs, _ = env.reset()
    b = obs["robot_0"]["observation"][60:]
    assert np.allclose(b[b > 0], b[b > 0][0])  # uniform b0 over the nodes z_0 = 0 leaves possible
    with pytest.raises(ValueError, match="belief_model"):
        mures_v0.parallel_env(map="office", robots=1, belief_model="oracle")
    with pytest.raises(ValueError, match="robots"):
        mures_v0.parallel_env(map="office", robots=0)
    with pytest.raises(ValueError, match="batch_size"):
        mures_v0.torchrl_env(map="office", robots=2, batch_size=[2, 3])
    env = mures_v0.parallel_env(map="office", robots=2, seed=0)
    env.reset()
    with pytest.raises(ValueError, match="no action for robot_1"):
        env.step({"robot_0": 0})
    with pytest.raises(ValueError, match="action indices"):
        env.step({"robot_0": 0, "robot_1": 99})


def test_keep_freed_memory_sets_glibcs_malloc_and_refuses_bad_thresholds():
    import platform

    from shared.engine.memory import MMAP_MAX_MIB, keep_freed_memory

    if platform.libc_ver()[0] == "glibc":
        assert keep_freed_memory() is True  # mallopt accepted both thresholds
    for mmap_mib, trim_mib in ((0, 256), (MMAP_MAX_MIB + 1, 256), (16, 8)):
        with pytest.raises(ValueError, match="mmap_mib"):
            keep_freed_memory(mmap_mib, trim_mib)


def _with_lengths(name, lengths):
    g = builtin_graph(name)
    return dataclasses.replace(g, edge_lengths=np.broadcast_to(np.asarray(lengths, dtype=float), (g.m,)).copy())


def test_on_the_clock_with_every_move_one_tick_the_environment_is_the_step_one():
    g = _with_lengths("office", 1.0)  # 1 m edges at 1 m/s: every move one 1 s tick
    runs = []
    for speed in (None, 1.0):
        env = mures_v0.torchrl_env(map=g, robots=3, batch_size=[6], seed=2, speed=speed)
        torch.manual_seed(0)
        runs.append((env, env.rollout(90, break_when_any_done=False)))
    (step_env, a), (clock_env, b) = runs
    assert clock_env.scenario.clock is not None and clock_env.scenario.t_max == step_env.scenario.t_max
    for key in (("agents", "observation"), ("agents", "action_mask"), ("next", "agents", "reward"), ("next", "done")):
        assert torch.equal(a[key], b[key]), key
    assert bool(a["next", "done"].any())
    head = 4 * g.n  # every robot's onehot(p) and the target's; the clock's state adds goals and ticks left
    assert torch.equal(a["state"][..., :head], b["state"][..., :head])
    assert clock_env.scenario.state_size == step_env.scenario.state_size + 3 * (g.n + 1)


def test_on_the_clock_a_robot_in_transit_has_one_action_and_the_return_counts_steps_worth_of_ticks():
    g = _with_lengths("office", np.linspace(1.0, 3.0, builtin_graph("office").m))
    env = mures_v0.parallel_env(map=g, robots=2, seed=0, speed=0.5)  # moves of 2-6 ticks, a step 4 ticks
    parallel_api_test(env, num_cycles=300)
    check_env_specs(mures_v0.torchrl_env(map=g, robots=2, batch_size=[4], seed=0, speed=0.5))
    assert env.scenario.ticks_per_step == pytest.approx(4.0) and env.scenario.t_max == 3 * g.n * 4
    rng = np.random.default_rng(0)
    in_transit = decided = 0
    for ep in range(20):
        obs, _ = env.reset(seed=ep)
        total = 0.0
        while env.agents:
            ready = env.core.sim.ready[0].numpy()
            for i, a in enumerate(env.agents):
                mask = obs[a]["action_mask"]
                if ready[i]:
                    decided += 1
                    assert mask.sum() == g.deg_closed[int(env.core.sim.pos[0, i])]
                else:
                    in_transit += 1
                    assert mask.tolist() == [1] + [0] * (len(mask) - 1), "in transit: index 0 only"
            obs, rewards, _terms, _truncs, infos = env.step(
                {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"]))) for a in env.agents}
            )
            total += rewards["robot_0"]
        info = infos["robot_0"]
        assert info["capture_time_s"] == info["capture_time"] * 1.0  # 1 s ticks
        assert total == pytest.approx(-info["capture_time"] / 4.0)  # minus the capture time in steps' worth
    assert in_transit > decided > 0


def test_on_the_clock_models_per_step_are_made_a_ticks_worth_and_models_per_tick_kept():
    from shared.core.clock import TravelTimes
    from shared.envs.core import make_scenario

    g = _with_lengths("office", 2.0)  # at 0.5 m/s a step lasts 4 ticks
    walk = uniform_walk(g)
    per_step = make_scenario(g, 2, target=walk, speed=0.5)
    assert np.array_equal(per_step.target.prob, TravelTimes.of(g, 0.5).model(walk).prob)
    assert per_step.belief_model is per_step.target  # "true": the robots' model is the target's, per tick
    per_tick = make_scenario(g, 2, target=walk, belief_model="identity", speed=0.5, models_per_tick=True)
    assert per_tick.target is walk and per_tick.belief_model.kind == "identity"


def test_on_the_clock_a_graph_without_edge_lengths_is_refused():
    with pytest.raises(ValueError, match="no edge lengths"):
        mures_v0.parallel_env(map="office", robots=2, speed=0.5)

"""The MARL baselines: each learns what a tiny map makes obvious, runs are deterministic for a
seed, and a trained team is an ordinary snapshot (`mures evaluate`, the robot agent's numpy
decision step) with its algorithm in the metadata."""

from __future__ import annotations

import contextlib
import json

import numpy as np
import pytest
import torch

from shared.core.graph import grid_graph
from shared.core.models import Sensor, lazy_walk
from shared.core.snapshot import PolicyAgent, read_snapshot
from shared.engine.evaluate import evaluate
from shared.engine.searchers import RandomSearcher
from shared.learning.config import TrainConfig
from shared.learning.marl import MARL_ALGORITHMS, hyperparameters, train_marl
from shared.learning.marl.common import robot_mlps
from shared.learning.marl.offpolicy import OffPolicyHyper, TargetActorCritic
from shared.learning.snapshot import PolicySearcher, Snapshot
from shared.tools.cli import main

# A corridor of 6 rooms, both robots start in room 0, the target sits still in a uniformly drawn
# room: sweeping the corridor is obviously best (capture time 2.5 on average), a random walk
# takes 6.8 steps.
TINY_BUDGET = {
    "mappo": ["episodes=12000"],
    "maddpg": ["episodes=2500", "warmup=200"],
    "facmac": ["episodes=2500", "warmup=200"],
    "masac": ["episodes=2500", "warmup=200", "updates=16"],
    "mambpo": ["episodes=2500", "warmup=200", "updates=16"],
}


def _corridor():
    g = grid_graph(6, 1)
    return g, lazy_walk(g, 1.0), Sensor()


def _mean_capture(g, target, sensor, make):
    return float(evaluate(g, target, sensor, 2, make, episodes=1000, seed=1).capture_time.mean())


@pytest.mark.parametrize("algorithm", MARL_ALGORITHMS)
def test_each_baseline_learns_to_sweep_a_corridor(algorithm):
    g, target, sensor = _corridor()
    cfg = TrainConfig(robots=2, algorithm=algorithm, belief="true", seed=0)
    res = train_marl(algorithm, g, target, sensor, cfg, hyperparameters(algorithm, TINY_BUDGET[algorithm]))
    snap = Snapshot(meta={"variant": "cepg", "robots": 2}, policy=res.policy, model=res.model, sensor=sensor)
    learned = _mean_capture(g, target, sensor, lambda s: PolicySearcher(snap, g, sensor, 2, seed=s))
    random = _mean_capture(g, target, sensor, lambda s: RandomSearcher(g, seed=s))
    assert random > 6.0
    assert learned < 4.0, f"{algorithm}: {learned:.2f} steps after training (random {random:.2f}, sweep 2.5)"
    assert res.summary["algorithm"] == algorithm and res.summary["learning_curve"]


@pytest.mark.parametrize("algorithm", ["mappo", "maddpg"])
def test_same_seed_same_weights(algorithm):
    g, target, sensor = _corridor()
    # a few dozen gradient steps each: enough for any difference in seeding to show in the weights
    hp = ["episodes=600", "warmup=100"] if algorithm != "mappo" else ["episodes=300", "envs=32", "steps=8"]

    def weights(seed):
        cfg = TrainConfig(robots=2, algorithm=algorithm, belief="true", seed=seed)
        return [
            p.detach().clone()
            for p in train_marl(algorithm, g, target, sensor, cfg, hyperparameters(algorithm, hp)).policy.parameters()
        ]

    a, b, c = weights(3), weights(3), weights(4)
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True))
    assert not all(torch.equal(x, y) for x, y in zip(a, c, strict=True))


def test_the_actors_step_reads_the_critic_without_its_parameter_gradients():
    """MADDPG's and FACMAC's actor loss goes through the critic (a MultiAgentMLP, as theirs):
    inside ``frozen_critic`` the actors get the same gradient to the bit, the critic none, and
    its parameters are trainable again afterwards."""
    torch.manual_seed(0)
    actor = torch.nn.Linear(3, 2)
    critic = robot_mlps(2, 1, robots=2, hidden=8)
    tac = TargetActorCritic(actor, critic, OffPolicyHyper())
    x = torch.randn(16, 2, 3)

    def gradients(frozen: bool) -> tuple[list, list]:
        for p in (*actor.parameters(), *critic.parameters()):
            p.grad = None
        with tac.frozen_critic() if frozen else contextlib.nullcontext():
            q = critic(torch.tanh(actor(x)))
        (-q.mean()).backward()
        return [p.grad.clone() for p in actor.parameters()], [p.grad for p in critic.parameters()]

    (plain, critic_plain), (frozen, critic_frozen) = gradients(False), gradients(True)
    assert all(torch.equal(a, b) for a, b in zip(plain, frozen, strict=True))
    assert critic_plain and all(g is not None for g in critic_plain)
    assert all(g is None for g in critic_frozen)
    assert all(p.requires_grad for p in critic.parameters())


def test_cli_trains_a_baseline_into_a_snapshot_robots_can_fly(tmp_path, capsys):
    out = tmp_path / "mappo-team"
    assert (
        main(
            [
                "train",
                "--env",
                "office",
                "--robots",
                "3",
                "--algorithm",
                "mappo",
                "--episodes",
                "400",
                "--batch",
                "32",
                "--hp",
                "steps=8",
                "--em-first",
                "200",
                "--em-missions",
                "32",
                "--quiet",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    meta = json.loads((out / "policy.json").read_text())
    assert meta["algorithm"] == "mappo" and meta["variant"] == "cepg"
    assert meta["training"]["hyperparameters"]["steps"] == 8 and meta["training"]["batch"] == 32
    assert meta["summary"]["em_updates"], "the robots' belief model is re-estimated by EM, as CE-PG's"
    capsys.readouterr()
    assert (
        main(
            [
                "evaluate",
                "--env",
                "office",
                "--robots",
                "3",
                "--searcher",
                f"policy:{out}",
                "--episodes",
                "50",
                "--json",
            ]
        )
        == 0
    )
    assert json.loads(capsys.readouterr().out)["episodes"] == 50
    # the robot agent's numpy decision step runs it, with the moves the trained actor prefers
    from shared.core.graph import builtin_graph
    from shared.learning.marl.common import TeamActor
    from shared.learning.snapshot import load_snapshot

    g = builtin_graph("office")
    actor = TeamActor(load_snapshot(out, g).policy, g)
    agent = PolicyAgent(read_snapshot(out, g), g, robot=1, greedy_actions=True)
    agent.reset(g.start, 0)
    p = g.start
    for _ in range(20):
        obs = torch.zeros(1, 3, 2 * g.n)
        obs[0, 1, p] = 1.0
        obs[0, 1, g.n :] = torch.as_tensor(agent.belief, dtype=torch.float32)
        mask = torch.as_tensor(np.arange(g.nbr.shape[1]) < g.deg_closed[p]).expand(1, 3, -1)
        want = int(g.nbr[p, int(actor(obs, mask)[0, 1].argmax())])
        p = agent.act(p)
        assert p == want
        agent.observe(p, 0)


def test_bad_hyperparameters_are_clear_errors(tmp_path, capsys):
    base = ["train", "--env", "office", "--robots", "2", "--out", str(tmp_path / "x")]
    assert main([*base, "--algorithm", "mappo", "--hp", "clipp=0.3"]) == 2
    assert "clipp" in capsys.readouterr().err
    assert main([*base, "--algorithm", "mappo", "--hp", "clip=high"]) == 2
    assert "expected a float" in capsys.readouterr().err
    assert main([*base, "--hp", "clip=0.3"]) == 2
    assert "MARL" in capsys.readouterr().err
    assert main([*base, "--algorithm", "masac", "--variant", "c-cepg"]) == 2
    assert "own beliefs" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    with pytest.raises(ValueError, match="unknown MARL algorithm"):
        hyperparameters("qmix")
    assert np.isclose(hyperparameters("mappo", ["lr=0.002"]).lr, 0.002)


@pytest.mark.slow
def test_a_fleet_flies_a_mappo_team_as_it_flies_cepg(tmp_path):
    """A MAPPO snapshot as the server's first version: the server lists its algorithm, three
    robot-agent processes download and fly it, and their capture times agree with `evaluate`'s."""
    from fleet_checks import replay

    from shared.core.graph import builtin_graph
    from shared.core.models import uniform_walk
    from shared.engine.evaluate import mean_ci95, means_differ
    from shared.learning.snapshot import load_snapshot
    from shared.tools.fleetsim import launch

    team = tmp_path / "mappo-team"
    args = ["train", "--env", "office", "--robots", "3", "--algorithm", "mappo", "--episodes", "1000"]
    assert main([*args, "--belief", "true", "--quiet", "--out", str(team)]) == 0
    g = builtin_graph("office")
    fleet = launch(
        g,
        ["--env", "office"],
        uniform_walk(g),
        Sensor(),
        3,
        tmp_path / "fleet",
        server_extra=["--init-policy", str(team)],
    )
    try:
        assert fleet.api.get("/api/v1/policies/current")["meta"]["algorithm"] == "mappo"
        flown = []
        for s in range(60):
            m = fleet.fly(["r1", "r2", "r3"], seed=s)
            ct = m["outcome"]["capture_time"]
            flown.append(ct if ct is not None else m["params"]["max_steps"])
            if s < 10:  # each robot's moves follow from its own record and the MAPPO actors alone
                for robot in m["robots"]:
                    assert replay(fleet, robot, m)["policy_version"] == 1
    finally:
        fleet.close()
    snap = load_snapshot(team, g)
    res = evaluate(
        g, uniform_walk(g), Sensor(), 3, lambda s: PolicySearcher(snap, g, Sensor(), 3, seed=s), episodes=1500, seed=5
    )
    differ, z = means_differ(flown, res.capture_time)
    assert not differ, (mean_ci95(flown), mean_ci95(res.capture_time), z)

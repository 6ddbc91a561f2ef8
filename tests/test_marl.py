"""The MARL baselines: each learns what a tiny map makes obvious, runs are deterministic for a
seed, and a trained team is an ordinary snapshot (`mures evaluate`, the robot agent's numpy
decision step) with its algorithm in the metadata."""

from __future__ import annotations

import contextlib
import dataclasses
import json

import numpy as np
import pytest
import torch

from shared.core.graph import builtin_graph, grid_graph
from shared.core.models import Sensor, lazy_walk, uniform_walk
from shared.core.snapshot_format import PolicyAgent, read_snapshot
from shared.engine.evaluate import evaluate
from shared.engine.searchers import RandomSearcher
from shared.learning.config import TrainConfig
from shared.learning.marl import MARL_ALGORITHMS, hyperparameters, train_marl
from shared.learning.marl.common import robot_mlps
from shared.learning.marl.offpolicy import OffPolicyHyper, TargetActorCritic
from shared.learning.team_snapshot import PolicySearcher, Snapshot
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


@pytest.mark.parametrize("algorithm", ["mappo", "masac", "mambpo"])
def test_a_baseline_on_the_clock_learns_to_sweep_a_corridor_of_unequal_doors(algorithm):
    """On the mission clock (doors 1-3 m apart at 1 m/s: moves of 1-3 ticks, a step 2 ticks) the
    environment steps a tick at a time and a robot in transit has one action; the team still
    learns to sweep, in seconds, flown on the clock as `mures evaluate --clock` flies it."""
    from shared.core.clock import TravelTimes

    g, target, sensor = _corridor()
    g = dataclasses.replace(g, edge_lengths=np.array([1.0, 3.0, 2.0, 1.0, 3.0]))
    cfg = TrainConfig(robots=2, algorithm=algorithm, belief="true", seed=0, speed=1.0)
    res = train_marl(algorithm, g, target, sensor, cfg, hyperparameters(algorithm, TINY_BUDGET[algorithm]))
    clock = TravelTimes.of(g, 1.0)
    assert res.summary["clock"]["unit"] == "ticks" and res.summary["clock"]["gamma_per_tick"] == pytest.approx(
        0.99**0.5
    )
    assert "per 1 s tick" in res.model.kind  # the snapshot's model is per tick
    snap = Snapshot(meta={"variant": "cepg", "robots": 2}, policy=res.policy, model=res.model, sensor=sensor)

    def seconds(make):
        return float(
            evaluate(g, clock.model(target), sensor, 2, make, episodes=1000, seed=1, clock=clock).capture_time.mean()
        )

    learned = seconds(lambda s: PolicySearcher(snap, g, sensor, 2, seed=s))
    random = seconds(lambda s: RandomSearcher(g, seed=s))
    # a sweep by both robots from room 0 finds a still target in 4.5 s on average
    assert learned < 0.7 * random, f"{algorithm}: {learned:.2f} s after training (random {random:.2f} s)"


def test_mambpos_branched_rollouts_on_the_clock_move_robots_as_the_simulator_does(monkeypatch):
    """Every transition MAMBPO's learned model makes on the clock follows the simulator's rule: a
    robot on a node sets off for its action's node and arrives after the move's ticks, one in
    transit has action 0 only and goes on to its goal, a tick passes, and the reward is a step's
    worth of -1 spread over its ticks."""
    from shared.core.clock import TravelTimes
    from shared.learning.marl import mambpo

    g, target, sensor = _corridor()
    g = dataclasses.replace(g, edge_lengths=np.array([1.0, 3.0, 2.0, 1.0, 3.0]))
    models = []
    rollout = mambpo.WorldModel.rollout

    def keep(self, data):
        models.append(self)
        return rollout(self, data)

    monkeypatch.setattr(mambpo.WorldModel, "rollout", keep)
    cfg = TrainConfig(robots=2, algorithm="mambpo", belief="true", seed=0, speed=1.0)
    train_marl("mambpo", g, target, sensor, cfg, hyperparameters("mambpo", ["episodes=300", "warmup=100"]))
    model = models[-1]
    td = model.buffer.storage[: len(model.buffer)]
    n, N = g.n, 2
    clock = TravelTimes.of(g, 1.0)
    per_step = clock.ticks_per_step
    ticks = torch.as_tensor(clock.ticks)

    def decode(state):
        pos = state[:, : N * n].view(-1, N, n).argmax(-1)
        goal = state[:, (N + 1) * n : (2 * N + 1) * n].view(-1, N, n).argmax(-1)
        left = torch.round(state[:, (2 * N + 1) * n : (2 * N + 1) * n + N] * per_step).long()
        return pos, goal, left, state[:, -1]

    pos, goal, left, t = decode(td.get("state"))
    pos1, goal1, left1, t1 = decode(td.get(("next", "state")))
    action, mask = td.get(("agents", "action")), td.get(("agents", "action_mask"))
    assert len(td) > 100 and bool((left > 0).any()) and bool((left == 0).any())  # both kinds of robots seen
    transit = left > 0
    assert bool((mask[transit][:, 1:] == 0).all()) and bool(mask[transit][:, 0].all())
    dest = torch.as_tensor(g.nbr)[pos, action]
    want_goal = torch.where(transit, goal, dest)
    want_left = torch.where(transit, left, ticks[pos, want_goal]) - 1
    assert torch.equal(goal1, want_goal) and torch.equal(left1, want_left)
    assert torch.equal(pos1, torch.where(want_left == 0, want_goal, pos))
    assert torch.equal(td.get(("next", "agents", "observation"))[..., :n].argmax(-1), pos1)
    assert torch.allclose(t1 - t, torch.full_like(t, 1.0 / clock.t_max(g.n)))  # a tick of T_max
    assert torch.allclose(td.get(("next", "agents", "reward")), torch.tensor(-1.0 / per_step))


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
    tac = TargetActorCritic(actor, critic, OffPolicyHyper(), gamma=0.99)
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
    from shared.learning.team_snapshot import load_snapshot

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
    from shared.learning.team_snapshot import load_snapshot
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


@pytest.mark.parametrize("algorithm", MARL_ALGORITHMS)
def test_a_stopped_run_resumes_from_its_checkpoint_to_the_same_weights(algorithm, tmp_path):
    """A run with a checkpoint directory, stopped part-way and started again, ends with the same
    weights, learning curve and counts, bit for bit, as one never stopped (what a killed run's
    resumption rests on: the checkpoint holds all the next step depends on)."""
    g, target, sensor = _corridor()
    hp = (
        ["episodes=600", "envs=16", "steps=8"]
        if algorithm == "mappo"
        else ["episodes=400", "envs=8", "warmup=60", "buffer=2000", "minibatch=32"]
        + (["rollout_starts=16", "model_buffer=500"] if algorithm == "mambpo" else [])
    )
    cfg = TrainConfig(robots=2, algorithm=algorithm, belief="em", seed=5, em_first=150, em_every=150, em_missions=20)

    def run(stop_after=None, checkpoint=None):
        calls = [0]

        def should_stop():
            calls[0] += 1
            return stop_after is not None and calls[0] >= stop_after

        return train_marl(
            algorithm,
            g,
            target,
            sensor,
            cfg,
            hyperparameters(algorithm, hp),
            should_stop=should_stop,
            checkpoint=checkpoint,
            checkpoint_every=3600,
        )

    straight = run()
    ckpt = tmp_path / "ckpt"
    stopped = run(stop_after=12, checkpoint=ckpt)
    assert stopped.interrupted and (ckpt / "state.pt").is_file()
    assert 0 < stopped.summary["episodes"] < straight.summary["episodes"]
    resumed = run(checkpoint=ckpt)
    assert not resumed.interrupted
    assert resumed.summary["resumed"] == [
        {"episodes": stopped.summary["episodes"], "wall_seconds": resumed.summary["resumed"][0]["wall_seconds"]}
    ]
    for key in ("episodes", "env_steps", "updates"):
        assert resumed.summary[key] == straight.summary[key], key
    points = [{k: p[k] for k in ("episodes", "mean_capture_time")} for p in straight.summary["learning_curve"]]
    assert [{k: p[k] for k in ("episodes", "mean_capture_time")} for p in resumed.summary["learning_curve"]] == points
    em_at = [e["episodes"] for e in straight.summary["em_updates"]]
    assert [e["episodes"] for e in resumed.summary["em_updates"]] == em_at and em_at
    for x, y in zip(straight.policy.state_dict().values(), resumed.policy.state_dict().values(), strict=True):
        assert torch.equal(x, y)
    assert np.array_equal(straight.model.prob, resumed.model.prob)


@pytest.mark.slow
def test_cli_a_killed_run_continues_from_its_checkpoint(tmp_path, capsys):
    """`mures train --checkpoint DIR`: a run killed (SIGKILL, nothing saved on the way out) after
    some checkpoints, then given the same command, ends with the snapshot an uninterrupted run
    writes; the checkpoint directory is removed once the snapshot is written."""
    import signal
    import subprocess
    import sys
    import time

    ckpt = tmp_path / "ckpt"
    common = ["train", "--env", "office", "--robots", "2", "--algorithm", "maddpg", "--quiet", "--seed", "2"]
    common += ["--episodes", "300", "--batch", "8", "--hp", "warmup=50", "--hp", "buffer=4000"]
    common += ["--hp", "minibatch=32", "--hp", "updates=1"]
    common += ["--em-first", "150", "--em-missions", "16"]
    resumable = [*common, "--checkpoint", str(ckpt), "--checkpoint-every", "0.2"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "shared.tools.cli", *resumable, "--out", str(tmp_path / "killed")],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            if (ckpt / "state.pt").is_file() and torch.load(ckpt / "state.pt", weights_only=False)["state"]["run"][
                "episodes"
            ] >= 150:
                break
            time.sleep(0.2)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert not (tmp_path / "killed").exists(), "killed before its snapshot"
    assert (ckpt / "state.pt").is_file() or (tmp_path / "ckpt.old" / "state.pt").is_file()

    assert main([*resumable, "--out", str(tmp_path / "resumed")]) == 0
    assert "resumed at" in capsys.readouterr().out
    assert not ckpt.exists() and not (tmp_path / "ckpt.old").exists() and not (tmp_path / "ckpt.new").exists()
    assert main([*common, "--out", str(tmp_path / "straight")]) == 0
    resumed, straight = (json.loads((tmp_path / d / "policy.json").read_text()) for d in ("resumed", "straight"))
    assert resumed["summary"]["resumed"] and not straight["summary"]["resumed"]
    assert resumed["summary"]["episodes"] == straight["summary"]["episodes"]
    assert (tmp_path / "resumed" / "weights.safetensors").read_bytes() == (
        tmp_path / "straight" / "weights.safetensors"
    ).read_bytes()


def test_cli_checkpoint_errors_change_nothing(tmp_path, capsys):
    base = ["train", "--env", "office", "--robots", "2", "--quiet", "--episodes", "40", "--batch", "8"]
    base += ["--em-first", "1000"]
    assert main([*base, "--checkpoint", str(tmp_path / "c"), "--out", str(tmp_path / "x")]) == 2
    assert "CE-PG" in capsys.readouterr().err and not (tmp_path / "c").exists()
    marl = [*base, "--algorithm", "mappo", "--hp", "steps=4"]
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "todo.txt").write_text("mine")
    assert main([*marl, "--checkpoint", str(notes), "--out", str(tmp_path / "x")]) == 2
    assert "not a checkpoint directory" in capsys.readouterr().err
    assert [p.name for p in notes.iterdir()] == ["todo.txt"] and not (tmp_path / "x").exists()
    with pytest.raises(SystemExit):
        main([*marl, "--checkpoint", str(tmp_path / "c"), "--checkpoint-every", "-1", "--out", "y"])
    assert "seconds >= 0" in capsys.readouterr().err
    # a checkpoint of one run (stopped at once) is not resumed by another
    assert main([*marl, "--seed", "7", "--checkpoint", str(tmp_path / "c"), "--out", str(tmp_path / "s7")]) == 0
    capsys.readouterr()
    assert not (tmp_path / "c").exists(), "removed once the snapshot is written"
    g = builtin_graph("office")
    cfg = TrainConfig(robots=2, algorithm="mappo", seed=7, em_first=1000, episodes=40, batch=8)
    hyper = hyperparameters("mappo", ["steps=4", "episodes=40", "envs=8"])
    stopped = train_marl(
        "mappo", g, uniform_walk(g), Sensor(), cfg, hyper, should_stop=lambda: True, checkpoint=tmp_path / "c"
    )
    assert stopped.interrupted
    assert main([*marl, "--checkpoint", str(tmp_path / "c"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert "another run" in err and "config.seed: 7 there, 0 here" in err
    assert (tmp_path / "c" / "state.pt").is_file() and not (tmp_path / "x").exists()

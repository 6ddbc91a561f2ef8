"""The CE-PG trainer: the paper's toy (Fig. 4), learning, snapshots, the command line, scale-out."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from statistics import median

import numpy as np
import pytest
import torch

from shared.core.graph import builtin_graph, load_graph_file
from shared.core.models import Sensor, uniform_walk
from shared.core.snapshot_format import PolicyAgent, SnapshotError, read_snapshot
from shared.engine.evaluate import evaluate
from shared.engine.searchers import RandomSearcher
from shared.learning.config import TrainConfig
from shared.learning.team_snapshot import PolicySearcher, load_snapshot, save_snapshot
from shared.learning.train import train
from shared.tools.toy import toy_fig4

ROOT = Path(__file__).resolve().parents[1]


def split(p_a, at=0.9):
    """Each robot puts >= ``at`` on a different node."""
    (a, b) = p_a
    return (a >= at and b <= 1 - at) or (b >= at and a <= 1 - at)


def first_split(run):
    return next((k for k, p in enumerate(run.p_a) if split(p)), len(run.p_a))


def test_toy_fig4_own_rewards_beta_half_splits_and_pg_conglomerates_at_a():
    """Paper Fig. 4 (b), (c): each robot rewarded for its own meeting."""
    ce = [toy_fig4(0.5, seed=s, updates=150, reward="own").p_a[-1] for s in range(10)]
    pg = [toy_fig4(1.0, seed=s, updates=150, reward="own").p_a[-1] for s in range(10)]
    assert sum(split(p) for p in ce) >= 9, ce
    assert sum(min(p) >= 0.9 for p in pg) >= 9, pg  # both robots go to A


def test_toy_fig4_team_reward_cross_entropy_splits_sooner():
    """The toy of docs/SPEC.md section 3 (team reward): CE-PG splits in 9 of 10 seeds; PG reaches the split only by
    escaping the (0.6, 0.6) saddle, later."""
    ce = [toy_fig4(0.5, seed=s, updates=150) for s in range(10)]
    pg = [toy_fig4(1.0, seed=s, updates=150) for s in range(10)]
    assert sum(split(r.p_a[-1]) for r in ce) >= 9
    assert median(first_split(r) for r in ce) < median(first_split(r) for r in pg)


def small_cfg(**kw):
    base = dict(robots=2, episodes=8000, batch=128, em_first=2048, em_every=10**9, em_missions=128, seed=3)
    base.update(kw)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def trained_run():
    g = load_graph_file(ROOT / "examples" / "maps" / "warehouse.json")
    m, s = uniform_walk(g), Sensor()
    res = train(g, m, s, small_cfg())
    return g, m, s, res


def test_shared_state_cross_entropy_counts_only_where_robots_share_node_and_belief():
    from shared.learning.cepg import Rollout, cepg_loss
    from shared.learning.policy import TeamPolicy

    torch.manual_seed(0)
    adj = torch.ones(4, 4, dtype=torch.bool)
    policy = TeamPolicy(4, 3, adj)
    uniform = torch.full((4,), 0.25)
    # decision 0: robots 0 and 1 on node 0 with the same belief, robot 2 on node 1;
    # decision 1: robots 0 and 1 on node 2 with different beliefs, robot 2 on node 2 with robot 0's belief;
    # decision 2: every robot on a node of its own (no pair counts: its networks are not evaluated)
    pos = torch.tensor([[0, 0, 1], [2, 2, 2], [0, 1, 3]])
    belief = torch.stack(
        [
            uniform.expand(3, 4),
            torch.tensor([[0.7, 0.1, 0.1, 0.1], [0.1, 0.7, 0.1, 0.1], [0.7, 0.1, 0.1, 0.1]]),
            uniform.expand(3, 4),
        ]
    )
    ro = Rollout(
        pos=pos,
        belief=belief,
        action=pos.clone(),
        t=torch.tensor([0, 0, 0]),
        episode=torch.tensor([0, 1, 2]),
        ret=torch.zeros(3),
        length=torch.tensor([1, 1, 1]),
        capture_time=torch.ones(3, dtype=torch.long),
        censored=torch.zeros(3, dtype=torch.bool),
    )
    beta = torch.zeros(3)
    full = cepg_loss(policy, ro, beta, 0.1, ce_states="all").ce
    shared = cepg_loss(policy, ro, beta, 0.1, ce_states="shared").ce
    # the pairs counted: (0,1) and (1,0) at decision 0; (0,2) and (2,0) at decision 1
    with torch.no_grad():
        pi = torch.softmax(policy.logits(pos, belief), -1)  # (2, 3, 4): pi_i at robot i's own state
        pj = policy.cross_probs(pos, belief)  # (2, N_i, N_j, 4): pi_j at robot i's state
    logs = torch.log(0.9 * pi + 0.1 * 0.25)
    H = lambda k, i, j: float(-(pj[k, i, j] * logs[k, i]).sum())  # noqa: E731
    want = [(H(0, 0, 1) + H(1, 0, 2)) / 2, H(0, 1, 0) / 2, H(1, 2, 0) / 2]  # mean over N - 1 = 2 others, / B = 3
    assert torch.allclose(shared, torch.tensor(want) / 3, atol=1e-6)
    assert (full > shared).all()
    # its gradient is that of the same sum written out over every decision and pair
    policy.zero_grad()
    cepg_loss(policy, ro, beta, 0.1, ce_states="shared").loss.backward()
    got = [p.grad.clone() for p in policy.parameters()]
    policy.zero_grad()
    log_pi = torch.log_softmax(policy.logits(pos, belief), -1)
    smooth = torch.log(0.9 * log_pi.exp() + 0.1 * 0.25)
    pairs = [(0, 0, 1), (1, 0, 2), (0, 1, 0), (1, 2, 0)]
    (sum(-(pj[k, i, j] * smooth[k, i]).sum() for k, i, j in pairs) / 2 / 3).neg().backward()
    for g, p in zip(got, policy.parameters(), strict=True):
        assert torch.allclose(g, p.grad, atol=1e-6)


def test_training_learns_and_estimates_the_model(trained_run):
    g, m, s, res = trained_run
    snap_model = res.model
    assert res.summary["episodes"] >= 8000 and res.summary["env_steps"] > res.summary["episodes"]
    (em_info,) = res.summary["em_updates"]
    assert em_info["episodes"] >= 2048 and em_info["missions"] == 128
    # from 128 missions the estimate is much closer to the truth than Gamma_hat_0 = I is
    from shared.core.models import identity_model
    from shared.engine.estimate import mean_row_tv

    tv_identity = mean_row_tv(identity_model(g), m)
    assert em_info["mean_row_tv_to_true"] < tv_identity - 0.1 and snap_model.kind == "em"
    from shared.learning.team_snapshot import Snapshot

    snap = Snapshot(meta={"variant": "cepg", "robots": 2}, policy=res.policy, model=res.model, sensor=s)
    learned = evaluate(g, m, s, 2, lambda sd: PolicySearcher(snap, g, s, 2, seed=sd), episodes=1000, seed=5)
    rand = evaluate(g, m, s, 2, lambda sd: RandomSearcher(g, seed=sd), episodes=1000, seed=5)
    a, b = learned.summary(), rand.summary()
    assert a["ci95"][1] < b["ci95"][0], (a["mean_capture_time"], b["mean_capture_time"])


def test_snapshot_round_trip_and_checks(trained_run, tmp_path):
    g, _m, s, res = trained_run
    d = save_snapshot(tmp_path / "snap", res.policy, g, res.model, s, "cepg", [0.5, 0.5], {"seed": 3}, res.summary)
    snap = load_snapshot(d, g)
    for (k, p), (_, q) in zip(res.policy.named_parameters(), snap.policy.named_parameters(), strict=True):
        assert torch.equal(p, q), k
    assert np.allclose(snap.model.dense(), res.model.dense())
    summary = json.loads((d / "training_summary.json").read_text())
    assert summary["episodes"] == res.summary["episodes"]
    # where it was trained: the versions that make the same seeds give the same weights
    assert summary["trained_with"]["torch"] == torch.__version__ and summary["trained_with"]["numpy"] == np.__version__
    # and on which processor kernels (torch's vector instructions differ in their rounding)
    assert summary["trained_with"]["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    assert summary["trained_with"]["processor"]
    assert json.loads((d / "policy.json").read_text())["summary"]["trained_with"] == summary["trained_with"]
    kept = save_snapshot(
        tmp_path / "again",
        res.policy,
        g,
        res.model,
        s,
        "cepg",
        [0.5, 0.5],
        {},
        summary | {"trained_with": {"torch": "0.0"}},
    )
    assert json.loads((kept / "training_summary.json").read_text())["trained_with"] == {"torch": "0.0"}
    # the weights file is numpy-readable: the agent's reader gets the same float32 values, no torch
    from safetensors.numpy import load_file

    stored = load_file(d / "weights.safetensors")
    assert set(stored) == {"w_pos", "w_bel", "b1", "w2", "b2"}
    for k, p in res.policy.named_parameters():
        assert np.array_equal(stored[k], p.detach().numpy()), k
    data = read_snapshot(d, g)
    assert data.robots == 2 and data.variant == "cepg" and np.array_equal(data.weights["w2"], stored["w2"])
    with pytest.raises(SnapshotError, match="not on 'MUSEUM'"):  # trained on the warehouse map
        load_snapshot(d, builtin_graph("museum"))
    w = bytearray((d / "weights.safetensors").read_bytes())
    w[-10] ^= 0xFF
    (d / "weights.safetensors").write_bytes(bytes(w))
    with pytest.raises(SnapshotError, match="sha256"):
        load_snapshot(d, g)
    (d / "policy.json").write_text("{not json")
    with pytest.raises(SnapshotError, match="not valid JSON"):
        load_snapshot(d, g)
    with pytest.raises(SnapshotError, match="not a snapshot directory"):
        load_snapshot(tmp_path / "nothing", g)


def test_numpy_agent_matches_the_batched_policy(trained_run):
    """The robot agent's numpy decision step computes the same distribution as the trainer's."""
    g, m, s, res = trained_run
    from shared.learning.team_snapshot import Snapshot

    snap = Snapshot(meta={"variant": "cepg", "robots": 2}, policy=res.policy, model=res.model, sensor=s)
    agent = PolicyAgent(snap.to_data(), g, robot=1, greedy_actions=True)
    batched = PolicySearcher(snap, g, s, 2, greedy_actions=True)
    ev = evaluate(g, m, s, 2, lambda sd: PolicySearcher(snap, g, s, 2, seed=sd), episodes=20, seed=9, record=True)
    tr = ev.trajectories[0]
    from shared.engine.sim import Obs

    for b in range(20):
        L = int(tr.length[b])
        for t in range(L - 1):
            pos = torch.as_tensor(tr.pos[t, b : b + 1])
            z = torch.as_tensor(tr.z[t, b : b + 1]).bool()
            obs = Obs(
                pos,
                z,
                torch.tensor([t]),
                torch.tensor([t == 0]),
                torch.ones(1, 2, dtype=torch.bool),
                torch.ones(1, dtype=torch.bool),
            )
            want = int(batched.act(obs)[0, 1])
            p, zz = int(tr.pos[t, b, 1]), int(tr.z[t, b, 1])
            agent.reset(p, zz) if t == 0 else agent.observe(p, zz)
            assert agent.act(p) == want


def mures(*args, **kw):
    return subprocess.run(
        [sys.executable, "-m", "shared.tools.cli", *args], capture_output=True, text=True, cwd=ROOT, **kw
    )


@pytest.mark.slow
def test_cli_train_then_evaluate_policy(tmp_path):
    out = tmp_path / "team"
    r = mures(
        "train",
        "--env",
        "office",
        "--robots",
        "3",
        "--episodes",
        "1024",
        "--em-first",
        "512",
        "--em-missions",
        "64",
        "--seed",
        "1",
        "--out",
        str(out),
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "training_summary.json").read_text())
    for key in ("episodes", "env_steps", "wall_seconds", "learning_curve", "em_updates"):
        assert key in summary
    meta = json.loads((out / "policy.json").read_text())
    assert meta["robots"] == 3 and meta["variant"] == "cepg" and meta["beta"] == [0.5] * 3
    assert meta["graph_id"] == builtin_graph("office").graph_id and len(meta["model"]["gamma"]) == 60
    r = mures(
        "evaluate", "--env", "office", "--robots", "2", "--searcher", f"policy:{out}", "--episodes", "300", "--json"
    )
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["episodes"] == 300
    r = mures("evaluate", "--env", "office", "--robots", "5", "--searcher", f"policy:{out}", "--episodes", "50")
    assert r.returncode == 0 and "network i mod 3" in r.stderr
    r = mures("evaluate", "--env", "museum", "--robots", "2", "--searcher", f"policy:{out}")
    assert r.returncode == 2 and "trained on map 'OFFICE'" in r.stderr


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--beta", "0.5,0.1"], "one per robot (3)"),
        (["--beta", "1.5"], "beta must be in [0, 1]"),
        (["--lr", "x"], "comma-separated numbers"),
        (["--variant", "cepg+", "--detection", "node"], "sensing range"),
    ],
)
def test_cli_train_bad_arguments(tmp_path, args, fragment):
    r = mures("train", "--env", "office", "--robots", "3", "--out", str(tmp_path / "x"), *args)
    assert r.returncode == 2 and fragment in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_ctrl_c_leaves_a_valid_snapshot(tmp_path):
    out = tmp_path / "team"
    p = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "shared.tools.cli",
            "train",
            "--env",
            "office",
            "--robots",
            "2",
            "--episodes",
            "10000000",
            "--true-model",
            "--out",
            str(out),
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(6)
    p.send_signal(signal.SIGINT)
    stdout, stderr = p.communicate(timeout=60)
    assert p.returncode == 130, stderr
    assert "interrupted" in stdout
    snap = load_snapshot(out, builtin_graph("office"))
    assert snap.meta["summary"]["interrupted"] and 0 < snap.meta["summary"]["episodes"] < 10000000


@pytest.mark.slow
def test_two_process_data_parallel_training_ends_with_identical_weights(tmp_path):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--standalone",
            "--nproc-per-node",
            "2",
            str(ROOT / "tests" / "dist_worker.py"),
            str(tmp_path),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    # on failure: how far each rank got (the worker says when it wrote; leaving the group ends it) and the end
    # and, after an abort, where Python was (the worker's faulthandler)
    said = [line for line in r.stderr.splitlines() if line.startswith(("rank ", "Fatal Python", "Current thread"))]
    fault = [line for line in r.stderr.splitlines() if line.startswith('  File "')][:30]
    assert r.returncode == 0, (said, fault, sorted(p.name for p in tmp_path.iterdir()), r.stderr[-3000:])
    w0 = torch.load(tmp_path / "rank0.pt", weights_only=True)
    w1 = torch.load(tmp_path / "rank1.pt", weights_only=True)
    assert set(w0) == set(w1)
    for k in w0:
        assert torch.equal(w0[k], w1[k]), k
    info = json.loads((tmp_path / "rank0.json").read_text())
    assert info["processes"] == 2 and info["episodes"] >= 2048
    init = torch.load(tmp_path / "init.pt", weights_only=True)
    assert not torch.equal(init["w2"], w0["w2"])  # it trained


@pytest.mark.slow
def test_mures_train_under_torchrun_writes_one_snapshot_from_two_processes(tmp_path):
    """The scale-out command of docs/cli.md: two gloo processes train one team, rank 0 writes it, and
    both leave the process group cleanly (exit 0)."""
    out = tmp_path / "team"
    launch = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]
    job = ["train", "--env", "office", "--robots", "2", "--episodes", "1024", "--batch", "256", "--seed", "3"]
    r = subprocess.run(
        [*launch, "-m", "shared.tools.cli", *job, "--quiet", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((out / "training_summary.json").read_text())
    assert summary["processes"] == 2 and summary["episodes"] >= 1024 and not summary["interrupted"]
    assert load_snapshot(out, builtin_graph("office")).policy.N == 2


def test_the_trainers_em_takes_a_dirichlet_prior_that_keeps_a_model_from_few_missions_near_the_walk():
    """`mures train --em-pseudo-count 5 --em-b0-pseudo-count 5`: the same missions (the same seeds up
    to the first EM update), the estimate pulled toward the uniform walk, here the truth."""
    graph = builtin_graph("office")
    tv = []
    for prior in (0.0, 5.0):
        cfg = TrainConfig(robots=2, episodes=512, em_first=256, em_missions=32, seed=3,
                          em_pseudo_count=prior, em_b0_pseudo_count=prior)  # fmt: skip
        res = train(graph, uniform_walk(graph), Sensor(), cfg)
        tv.append(res.summary["em_updates"][0]["mean_row_tv_to_true"])
    assert tv[1] < 0.5 * tv[0], tv
    with pytest.raises(ValueError, match="pseudo-counts"):
        TrainConfig(robots=2, em_pseudo_count=-1.0).check()

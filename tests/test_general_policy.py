"""The general policy: one network for any building and team size (shared/core/graph_policy.py,
shared/learning/general.py, `mures train-general`, `--searcher general`)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import deque

import numpy as np
import pytest
import torch

from shared.core.graph import builtin_graph, office_graph
from shared.core.graph_policy import FEATURE_COUNTS, FEATURES, Distances, GeneralAgent, hop_distances
from shared.core.models import Sensor, uniform_walk
from shared.core.snapshot_format import GENERAL_META as META
from shared.core.snapshot_format import GENERAL_WEIGHTS as WEIGHTS
from shared.core.snapshot_format import SnapshotError, load_general, read_snapshot, save_general, shipped_general_path
from shared.engine.evaluate import evaluate, means_differ
from shared.learning.config import FINE_TUNE, fine_tune_defaults
from shared.learning.general import CHECKPOINT, GeneralConfig, GeneralNet, GraphTeam, train_general
from shared.registry import searcher_factory


def _bfs(graph, s: int) -> np.ndarray:
    dist = np.full(graph.n, -1)
    dist[s] = 0
    todo = deque([s])
    while todo:
        u = todo.popleft()
        for v in graph.closed(u):
            if dist[v] < 0:
                dist[v] = dist[u] + 1
                todo.append(v)
    return dist


def test_hop_distances_are_breadth_first_search_and_rows_match_the_table():
    graph = builtin_graph("museum")
    got = hop_distances(graph, np.arange(graph.n))
    want = np.stack([_bfs(graph, s) for s in range(graph.n)])
    assert np.array_equal(got, want)
    table = Distances(graph)
    rows = Distances(graph, all_pairs=False)  # the row-by-row path large buildings take
    nodes = np.array([[3, 0], [graph.n - 1, 3]])
    assert np.array_equal(rows.rows(nodes), table.rows(nodes))
    assert rows.rows(nodes).shape == (2, 2, graph.n)


def test_the_robots_numpy_decision_is_the_trainers_network(tmp_path):
    """GeneralAgent (numpy, what a robot runs) and GraphTeam (torch, what trains) give the same
    logits on the same states, for every robot of the team."""
    graph = office_graph(80, seed=3)
    torch.manual_seed(0)
    net = GeneralNet(16)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.3 * torch.randn_like(p))
    team = GraphTeam(net, graph, 3)
    policy = load_general(save_general(tmp_path / "g", net.numpy_weights(), {}))
    rng = np.random.default_rng(0)
    pos = torch.as_tensor(rng.integers(0, graph.n, size=(5, 3)))
    belief = torch.as_tensor(rng.dirichlet(np.ones(graph.n) * 0.2, size=(5, 3)), dtype=torch.float32)
    with torch.no_grad():
        logits = team.logits(pos, belief)  # (5, 3, n)
    for s in range(5):
        for i in range(3):
            agent = GeneralAgent(policy.weights, graph, i, 3)
            p, mates = int(pos[s, i]), np.delete(pos[s].numpy(), i)  # the teammates where they are
            want = logits[s, i, graph.closed(p)].double().numpy()
            assert np.allclose(agent.logits(p, belief[s, i].double().numpy(), mates), want, atol=1e-4)
            assert (logits[s, i] > -1e8).sum() == len(graph.closed(p))  # only N[p] is allowed
    # a teammate not known (-1, or left out) is no teammate: robot 0 with robot 2 withdrawn
    active = torch.tensor([[True, True, False]] * 5)
    with torch.no_grad():
        partial = team.scatter_logits(pos, net(team.features(pos, belief, active=active)))
    agent = GeneralAgent(policy.weights, graph, 0, 3)
    p = int(pos[0, 0])
    b = belief[0, 0].double().numpy()
    want = partial[0, 0, graph.closed(p)].double().numpy()
    for mates in ([int(pos[0, 1]), -1], [int(pos[0, 1])]):
        assert np.allclose(agent.logits(p, b, np.array(mates)), want, atol=1e-4)
    alone = agent.logits(p, b, np.array([], dtype=np.int64))
    assert np.allclose(alone, agent.logits(p, b), atol=1e-9) and not np.allclose(alone, want, atol=1e-4)


def test_a_general_policy_without_the_teammates_features_still_flies(tmp_path):
    """The first shipped policy read every feature but the teammates' (FEATURE_COUNTS[0]): it loads,
    flies (its scores ignore where the teammates are) and saves as it was."""
    graph = office_graph(60, seed=3)
    torch.manual_seed(0)
    old = GeneralNet(8, FEATURE_COUNTS[0])
    path = save_general(tmp_path / "old", old.numpy_weights(), {})
    policy = load_general(path)
    assert policy.meta["features"] == list(FEATURES[: FEATURE_COUNTS[0]])
    agent = GeneralAgent(policy.weights, graph, 0, 2)
    b = np.full(graph.n, 1.0 / graph.n)
    assert np.array_equal(agent.logits(5, b, np.array([7])), agent.logits(5, b, np.array([40])))
    net = GeneralNet.from_weights(policy.weights)
    assert net.w1.shape[0] == FEATURE_COUNTS[0]
    with torch.no_grad():
        team = GraphTeam(net, graph, 2)
        logits = team.logits(torch.tensor([[5, 7]]), torch.as_tensor(b, dtype=torch.float32).expand(1, 2, -1))
    assert np.allclose(logits[0, 0, graph.closed(5)].double().numpy(), agent.logits(5, b), atol=1e-4)
    meta = json.loads((path / META).read_text())
    meta["features"] = list(FEATURES[:10])
    (path / META).write_text(json.dumps(meta))
    with pytest.raises(SnapshotError, match="features are not this version's"):
        load_general(path)


def test_a_bad_general_policy_directory_is_named(tmp_path):
    with pytest.raises(SnapshotError, match="no general policy here"):
        load_general(tmp_path)
    good = save_general(tmp_path / "g", GeneralNet(8).numpy_weights(), {})
    meta = json.loads((good / META).read_text())
    (good / META).write_text(json.dumps({**meta, "format": "mures.policy/1"}))
    with pytest.raises(SnapshotError, match="expected format"):
        load_general(good)
    (good / META).write_text(json.dumps(meta))
    blob = bytearray((good / WEIGHTS).read_bytes())
    blob[-1] ^= 1
    (good / WEIGHTS).write_bytes(bytes(blob))
    with pytest.raises(SnapshotError, match="sha256"):
        load_general(good)
    (good / META).write_text("{")
    with pytest.raises(SnapshotError, match="not valid JSON"):
        load_general(good)


def _tiny(**kw) -> GeneralConfig:
    base = dict(episodes=800, min_nodes=12, max_nodes=20, max_robots=3, pool=3, batch_elements=200, hidden=8,
                imitation_episodes=2, imitation_epochs=2)  # fmt: skip
    return GeneralConfig(**{**base, **kw})


def test_a_killed_training_run_goes_on_from_its_checkpoint_to_the_same_weights(tmp_path):
    whole = train_general(_tiny(), tmp_path / "whole")
    assert whole["imitation"]["decisions"] > 0 and 0.0 <= whole["imitation"]["agreement"] <= 1.0

    class Killed(Exception):
        pass

    def kill(point):
        if point["updates"] >= 20:
            raise Killed

    with pytest.raises(Killed):
        train_general(_tiny(checkpoint_every=0.0), tmp_path / "again", progress=kill)
    assert (tmp_path / "again" / CHECKPOINT).is_file()
    with pytest.raises(ValueError, match="other settings"):
        train_general(_tiny(checkpoint_every=0.0, seed=5), tmp_path / "again")
    # random states are per device: a checkpoint goes on only on the device its run began on
    saved = torch.load(tmp_path / "again" / CHECKPOINT, weights_only=False)
    assert saved["device"] == "cpu"
    torch.save({**saved, "device": "cuda"}, tmp_path / "elsewhere.pt")
    (tmp_path / "moved").mkdir()
    (tmp_path / "elsewhere.pt").replace(tmp_path / "moved" / CHECKPOINT)
    with pytest.raises(ValueError, match="written by a run on cuda"):
        train_general(_tiny(checkpoint_every=0.0), tmp_path / "moved")
    again = train_general(_tiny(checkpoint_every=0.0), tmp_path / "again")
    assert again["episodes"] == whole["episodes"]
    assert not (tmp_path / "again" / CHECKPOINT).exists()
    a, b = load_general(tmp_path / "whole").weights, load_general(tmp_path / "again").weights
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_rollouts_on_a_local_dask_cluster_give_the_weights_of_one_process(tmp_path):
    """`mures train-general --workers 2 --floors-per-update 2` flies each update's two floors (and the
    imitation phase's planner) on two Dask workers; the weights are those of the same run in one
    process with one torch thread, as the command runs it. One floor per update is today's loop."""
    cmd = [sys.executable, "-m", "shared.tools.cli", "train-general", "--out", str(tmp_path / "dask")]
    cmd += ["--episodes", "800", "--min-nodes", "12", "--max-nodes", "20", "--max-robots", "3", "--pool", "3"]
    cmd += ["--batch-elements", "200", "--hidden", "8", "--imitation-episodes", "2", "--imitation-epochs", "2"]
    dask = [*cmd, "--floors-per-update", "2", "--workers", "2"]
    r = subprocess.run(dask, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "rollouts on 2 Dask workers" in r.stderr
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        here = train_general(_tiny(floors_per_update=2), tmp_path / "here")
        one = train_general(_tiny(), tmp_path / "one")
    finally:
        torch.set_num_threads(threads)
    meta = json.loads((tmp_path / "dask" / META).read_text())["training"]
    assert meta["updates"] == here["updates"] and meta["ran_on"].startswith("2 Dask workers")
    assert here["ran_on"] == "this process" and one["updates"] > here["updates"]  # two floors an update: fewer
    a, b = load_general(tmp_path / "dask").weights, load_general(tmp_path / "here").weights
    assert all(np.array_equal(a[k], b[k]) for k in a)
    c = load_general(tmp_path / "one").weights
    assert not all(np.array_equal(a[k], c[k]) for k in a)
    r = subprocess.run([*cmd, "--floors-per-update", "4"], capture_output=True, text=True)
    assert r.returncode == 2 and "floors_per_update must be 1 to the pool's 3" in r.stderr
    # going on from a policy of the first 24 features: the workers' networks take its shape
    torch.manual_seed(0)
    old = save_general(tmp_path / "old", GeneralNet(8, FEATURE_COUNTS[0]).numpy_weights(), {})
    init = ["--init", str(old), "--episodes", "400"]
    r = subprocess.run([*dask[:5], str(tmp_path / "old-dask"), *dask[6:], *init], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    torch.set_num_threads(1)
    try:
        train_general(_tiny(floors_per_update=2, init=str(old), episodes=400), tmp_path / "old-here")
    finally:
        torch.set_num_threads(threads)
    a, b = load_general(tmp_path / "old-dask").weights, load_general(tmp_path / "old-here").weights
    assert a["w1"].shape[0] == FEATURE_COUNTS[0] and all(np.array_equal(a[k], b[k]) for k in a)


def test_the_shipped_general_policy_beats_greedy_on_a_floor_it_never_saw():
    """Zero shot, paired on the same 200 episodes: a generated floor of 150 nodes (the training pool's
    seeds start at 10,000), a team of 3."""
    graph = office_graph(150, seed=2)
    target, sensor = uniform_walk(graph), Sensor()
    runs = {
        name: evaluate(graph, target, sensor, 3, searcher_factory(name, graph, target, sensor, 3), 200, seed=4)
        for name in ("general", "greedy")
    }
    general, greedy = runs["general"].capture_time, runs["greedy"].capture_time
    differ, _z = means_differ(general, greedy)
    assert differ and general.mean() < 0.8 * greedy.mean()


def test_train_general_and_evaluate_general_from_the_command_line(tmp_path):
    out = tmp_path / "gen"
    cmd = [sys.executable, "-m", "shared.tools.cli", "train-general", "--out", str(out), "--episodes", "300"]
    cmd += ["--min-nodes", "12", "--max-nodes", "16", "--pool", "2", "--max-robots", "2", "--hidden", "8"]
    cmd += ["--imitation-episodes", "2", "--imitation-epochs", "1"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "episodes" in r.stderr and "ETA" in r.stderr and "imitation: FHPE-SA on building 2/2" in r.stderr
    assert json.loads((out / META).read_text())["training"]["command"].startswith("mures train-general")
    ev = [sys.executable, "-m", "shared.tools.cli", "evaluate", "--env", "museum", "--robots", "5"]
    r = subprocess.run(
        [*ev, "--searcher", f"general:{out}", "--episodes", "50", "--json"], capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["episodes"] == 50 and res["robots"] == 5 and res["searcher"] == f"general:{out}"
    r = subprocess.run([*ev, "--searcher", f"general:{tmp_path}", "--episodes", "5"], capture_output=True, text=True)
    assert r.returncode != 0 and "no general policy here" in r.stderr and "Traceback" not in r.stderr
    bad = [sys.executable, "-m", "shared.tools.cli", "train-general", "--out", str(tmp_path / "x")]
    r = subprocess.run([*bad, "--min-nodes", "50", "--max-nodes", "10"], capture_output=True, text=True)
    assert r.returncode == 2 and "min_nodes <= max_nodes" in r.stderr and not (tmp_path / "x").exists()
    # --device: one that does not exist here, or a GPU beside Dask workers, is refused before anything is written
    r = subprocess.run([*bad, "--device", "tpu9"], capture_output=True, text=True)
    assert r.returncode == 2 and "unknown device 'tpu9'" in r.stderr and not (tmp_path / "x").exists()
    if not torch.cuda.is_available():
        r = subprocess.run([*bad, "--device", "cuda"], capture_output=True, text=True)
        assert r.returncode == 2 and "no CUDA device is available" in r.stderr and not (tmp_path / "x").exists()
    else:
        r = subprocess.run([*bad, "--device", "cuda", "--workers", "2"], capture_output=True, text=True)
        assert r.returncode == 2 and "goes without --workers" in r.stderr and not (tmp_path / "x").exists()


def test_a_fine_tune_of_the_general_policy_takes_its_own_defaults_unless_told(tmp_path):
    """`mures train --init general` fine-tunes with FINE_TUNE (J in units of the run's capture time,
    beta 0.9, lr 0.001, EM's prior, a batch of 24,000 / n episodes) and beliefs that start on the
    uniform walk; a flag given wins."""
    cmd = [sys.executable, "-m", "shared.tools.cli", "train", "--env", "office", "--robots", "2", "--init", "general"]
    cmd += ["--episodes", "64", "--em-first", "32", "--em-missions", "16", "--quiet"]
    r = subprocess.run([*cmd, "--out", str(tmp_path / "a")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    cfg = json.loads((tmp_path / "a" / "policy.json").read_text())["training"]
    got = {k: cfg[k] for k in ("lr", "beta", "j_unit", "em_pseudo_count", "em_b0_pseudo_count", "batch")}
    assert got == {**FINE_TUNE, "em_pseudo_count": 1.0, "em_b0_pseudo_count": 1.0, "batch": 256}  # OFFICE, n = 60
    assert cfg["em_missions"] == 16  # given
    assert "warning" not in r.stderr  # the per-map team's large-graph warning is not about this
    data = read_snapshot(tmp_path / "a", builtin_graph("office"))
    assert cfg["node_bias"] == 10.0 and data.weights["node_bias"].shape == (2, 60)  # learned for this map and team
    assert np.abs(data.weights["node_bias"]).max() > 0
    given = ["--lr", "0.005", "--beta", "0.5", "--j-unit", "1", "--batch", "32", "--em-pseudo-count", "0"]
    r = subprocess.run([*cmd, *given, "--out", str(tmp_path / "b")], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    cfg = json.loads((tmp_path / "b" / "policy.json").read_text())["training"]
    assert (cfg["lr"], cfg["beta"], cfg["j_unit"], cfg["batch"], cfg["em_pseudo_count"]) == (
        [0.005],
        [0.5],
        1.0,
        32,
        0.0,
    )
    r = subprocess.run([*cmd, "--node-bias", "0", "--out", str(tmp_path / "c")], capture_output=True, text=True,
                       timeout=300)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "node_bias" not in read_snapshot(tmp_path / "c", builtin_graph("office")).weights  # the network alone
    per_map = [*cmd[: cmd.index("--init")], "--episodes", "8", "--node-bias", "5", "--out", str(tmp_path / "d")]
    r = subprocess.run(per_map, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "--node-bias is for a fine-tune of the general policy" in r.stderr
    assert not (tmp_path / "d").exists()
    assert fine_tune_defaults(1_000)["batch"] == 24 and fine_tune_defaults(20)["batch"] == 256
    assert fine_tune_defaults(1_000)["em_missions"] == 128 and fine_tune_defaults(60)["em_missions"] == 512
    # EM's prior: 1 on the paper's maps, stronger on larger floors, at most 20
    assert [fine_tune_defaults(n)["em_pseudo_count"] for n in (60, 99, 100, 300, 1_000)] == [1.0, 1.0, 6.0, 20.0, 20.0]
    assert fine_tune_defaults(1_000)["em_b0_pseudo_count"] == 20.0


def test_the_shipped_policy_is_there():
    policy = load_general(shipped_general_path())
    assert policy.meta["training"]["command"].startswith("mures train-general")


def test_a_server_without_init_policy_flies_the_general_policy_and_fine_tunes_it(tmp_path):
    """fleet-sim's server starts with no --init-policy: version 1 is the general policy bound to the
    map with FHPE-SA as its team searcher, the robot agents fly it from the first mission (their
    capture times agree with `mures evaluate` of the same snapshot flown as a team), and the
    retraining fine-tunes it (the gate then decides, as for any run)."""
    work = tmp_path / "work"
    cmd = [sys.executable, "-m", "shared.tools.cli", "fleet-sim", "--env", "museum", "--robots", "3"]
    cmd += ["--missions", "48", "--retrain-every", "40", "--retrain-episodes", "256", "--seed", "0"]
    r = subprocess.run([*cmd, "--workdir", str(work), "--json"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout)
    assert out["policy_versions_used"][0] == 1
    flown = out["by_policy_version"]["1"]
    assert flown["missions"] >= 40
    v1 = work / "server" / "policies" / "v1" / "snapshot"
    meta = json.loads((v1 / "policy.json").read_text())
    assert meta["architecture"] == "general" and meta["robots"] == 3 and meta["team_searcher"] == "fhpe-sa"
    assert out["coordinated_share"] > 0.9  # links up: the team's plan on every observation
    ev = [sys.executable, "-m", "shared.tools.cli", "evaluate", "--env", "museum", "--robots", "3"]
    r = subprocess.run([*ev, "--searcher", f"policy:{v1}", "--team-searcher", "fhpe-sa", "--episodes", "200",
                        "--seed", "5", "--json"], capture_output=True, text=True, timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr
    batched = json.loads(r.stdout)
    se = ((flown["ci95_halfwidth"] / 1.96) ** 2 + (batched["ci95_halfwidth"] / 1.96) ** 2) ** 0.5
    assert abs(flown["mean_capture_time"] - batched["mean_capture_time"]) < 3.29 * se, (flown, batched)
    run = out["training_runs"][0]
    assert run["metrics"]["train"]["episodes"] >= 256  # the general network trained on this map's EM model
    assert run["status"] == "succeeded" or run["error"].startswith("evaluation gate")
    for p in (work / "server" / "policies").glob("v*/snapshot/policy.json"):  # every version is the one network
        assert json.loads(p.read_text())["architecture"] == "general"


def test_a_snapshot_of_the_general_policy_flies_any_team_size(tmp_path):
    """The general policy bound to a map is a snapshot like any other (docs/SPEC.md section 8) with
    architecture "general": read back with its checks, flown by PolicyAgent for every team size,
    robots left after a drop-out keep the same network, and it holds no teams."""
    from shared.core.snapshot_format import PolicyAgent, read_snapshot, write_snapshot
    from shared.learning.team_snapshot import general_snapshot, load_snapshot, save_snapshot

    graph = builtin_graph("office")
    snap = general_snapshot(load_general(shipped_general_path()), graph, 3, uniform_walk(graph), Sensor())
    where = save_snapshot(tmp_path / "v1", snap.policy, graph, snap.model, Sensor(), "cepg", [1.0] * 3, {}, {})
    data = read_snapshot(where, graph)
    assert data.general and data.robots == 3 and set(data.weights) == {"w1", "b1", "w2", "b2", "w3", "skip"}
    assert data.team_for(5).robots == 5 and data.switches_to(2) and data.team_note(7) is None
    rng = np.random.default_rng(0)
    for k in (1, 3, 5):
        flown = data.team_for(k)
        for i in range(k):
            agent = PolicyAgent(flown, graph, i, seed=i)
            agent.reset(graph.start, 0)
            b = rng.dirichlet(np.ones(graph.n))
            assert agent.act(graph.start, b) in graph.closed(graph.start)
    again = load_snapshot(where, graph)
    assert again.general and np.array_equal(again.to_data().weights["w1"], data.weights["w1"])
    with pytest.raises(ValueError, match="holds no teams"):
        write_snapshot(tmp_path / "x", graph, data.weights, data.model, Sensor(), "cepg", [1.0], {}, {},
                       teams={2: data.weights}, robots=3)  # fmt: skip
    meta = json.loads((where / "policy.json").read_text())
    (where / "policy.json").write_text(json.dumps({**meta, "architecture": "transformer"}))
    with pytest.raises(SnapshotError, match="unknown architecture 'transformer'"):
        read_snapshot(where, graph)


def test_a_fine_tunes_node_bias_is_flown_by_the_robots_as_trained(tmp_path):
    """A fine-tune's node_bias (N, n): robot i's scores gain its row at the candidates, in torch (the
    rollout, and network j on robot i's state in the cross-entropy term with row j) and in numpy (what
    a robot runs); a snapshot keeps it, a team of another size flies the network without it, and a
    node_bias of the wrong shape is refused by name."""
    from shared.core.snapshot_format import PolicyAgent, write_snapshot
    from shared.learning.team_snapshot import load_snapshot, save_snapshot

    graph = builtin_graph("office")
    torch.manual_seed(0)
    net = GeneralNet.from_weights(load_general(shipped_general_path()).weights)
    rng = np.random.default_rng(1)
    bias = rng.normal(0.0, 2.0, size=(3, graph.n)).astype(np.float32)
    team = GraphTeam(net, graph, 3, node_bias=bias, bias_rate=10.0)
    assert any(p is team.bias for p in team.parameters())  # learned
    learned = team.bias
    assert team.to("cpu").bias is learned  # the optimiser's tensor still (an EM update's searcher moves the team)
    pos = torch.as_tensor(rng.integers(0, graph.n, size=(4, 3)))
    belief = torch.as_tensor(rng.dirichlet(np.ones(graph.n) * 0.2, size=(4, 3)), dtype=torch.float32)
    with torch.no_grad():
        logits = team.logits(pos, belief)
        plain = GraphTeam(net, graph, 3).logits(pos, belief)
        cross = team.cross_probs(pos, belief)  # (4, N_i, N_j, d)
        own = torch.softmax(team.slot_logits(pos, belief), -1)
    assert torch.allclose(cross.diagonal(dim1=1, dim2=2).permute(0, 2, 1), own, atol=1e-6)
    where = save_snapshot(tmp_path / "v", team, graph, uniform_walk(graph), Sensor(), "cepg", [0.9] * 3, {}, {})
    data = read_snapshot(where, graph)
    assert np.allclose(data.weights["node_bias"], bias, atol=1e-5)
    assert torch.allclose(load_snapshot(where, graph).policy.logits(pos, belief), logits, atol=1e-5)
    for s in range(4):
        for i in range(3):
            p, mates = int(pos[s, i]), np.delete(pos[s].numpy(), i)
            b = belief[s, i].double().numpy()
            agent = PolicyAgent(data, graph, i)
            got = agent.general.logits(p, b, mates)
            assert np.allclose(got, logits[s, i, graph.closed(p)].double().numpy(), atol=1e-4)
            assert np.allclose(got - plain[s, i, graph.closed(p)].double().numpy(), bias[i, graph.closed(p)], atol=1e-4)
    two = data.team_for(2)  # robots left after a drop-out: the network as a team of 2, without the bias
    assert "node_bias" not in two.weights and PolicyAgent(two, graph, 1).general.node_bias is None
    with pytest.raises(SnapshotError, match=r"node_bias has shape \(2, 60\), expected \(3, 60\)"):
        write_snapshot(tmp_path / "x", graph, {**data.weights, "node_bias": bias[:2]}, data.model, Sensor(), "cepg",
                       [0.9] * 3, {}, {}, robots=3)  # fmt: skip
    assert not (tmp_path / "x").exists()

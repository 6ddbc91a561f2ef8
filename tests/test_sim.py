"""The batched simulator against the paper setup (docs/SPEC.md section 1) and an independent plain-Python one."""

import math

import numpy as np
import pytest
import torch

from shared.core.graph import builtin_graph, graph_from_dict
from shared.core.models import Sensor, from_matrix, uniform_walk
from shared.engine.evaluate import evaluate, means_differ
from shared.engine.searchers import RandomSearcher
from shared.engine.sim import SearchSim


def reference_random_search(graph, model, sensor, N, episodes, seed):
    """A direct, one-episode-at-a-time transcription of docs/SPEC.md section 1 with the random searcher."""
    rng = np.random.default_rng(seed)
    G = model.dense()
    ptr, idx = graph.detection_sets(sensor.detection)
    t_max = 3 * graph.n
    cts, fas = [], []
    for _ in range(episodes):
        pos = [graph.start] * N
        e = rng.choice(graph.n, p=model.b0)
        t, fa = 0, 0
        while True:
            captured = False
            for p in pos:
                inside = e in idx[ptr[p] : ptr[p + 1]]
                zz = rng.random() < (1 - sensor.eta_fn if inside else sensor.eta_fp)
                fa += zz and not inside
                captured |= zz and inside
            if captured or t == t_max:
                break
            pos = [int(rng.choice(graph.closed(p))) for p in pos]  # robots move
            e = rng.choice(graph.n, p=G[e])  # then the target
            t += 1
        cts.append(t)
        fas.append(fa)
    return np.array(cts, float), np.array(fas, float)


def test_matches_an_independent_reference_implementation():
    g = builtin_graph("office")
    model, sensor = uniform_walk(g), Sensor(eta_fn=0.2, eta_fp=0.02)
    ref_ct, ref_fa = reference_random_search(g, model, sensor, N=2, episodes=3000, seed=5)
    res = evaluate(g, model, sensor, 2, lambda s: RandomSearcher(g, seed=s), episodes=3000, seed=5)
    ct, fa = res.capture_time.astype(float), res.false_alarms.astype(float)
    for a, b in ((ct, ref_ct), (fa, ref_fa)):
        differ, z = means_differ(a, b, z=4.0)
        assert not differ, (a.mean(), b.mean(), z)


def test_means_differ_is_welchs_two_sample_test():
    rng = np.random.default_rng(3)
    a, b = rng.exponential(10.0, 60), rng.exponential(10.0, 1500)
    differ, z = means_differ(a, b)
    se = math.sqrt(a.var(ddof=1) / 60 + b.var(ddof=1) / 1500)
    assert not differ and np.isclose(z, (a.mean() - b.mean()) / se)
    assert means_differ(a + 8.0, b)[0] and means_differ(a, b, z=abs(z) / 2)[0]
    assert means_differ([3, 3], [3, 3]) == (False, 0.0) and means_differ([4, 4], [3, 3])[0]
    with pytest.raises(ValueError, match="at least 2"):
        means_differ([1.0], b)


class Scripted:
    """Every robot moves toward a fixed node along a given next-hop table."""

    def __init__(self, hop):
        self.hop = torch.as_tensor(hop)

    def act(self, obs):
        return self.hop[obs.pos]


def two_rooms(stay_target_at=1):
    g = graph_from_dict({"nodes": [0, 1], "edges": [[0, 1]], "start_node": 0})
    model = from_matrix(g, np.eye(2), np.eye(2)[stay_target_at])  # a target that never moves
    return g, model


def test_capture_censoring_and_move_order():
    g, model = two_rooms()
    go = SearchSim(g, model, Sensor(), n_robots=1, batch=4, auto_reset=False)
    obs = go.reset()
    obs, res = go.step(Scripted([1, 1]).act(obs))
    assert res.done.all() and (res.capture_time == 1).all() and not res.censored.any()
    assert (res.captured_by == 0).all()
    stay = SearchSim(g, model, Sensor(), n_robots=1, batch=4, auto_reset=False)
    obs = stay.reset()
    steps = 0
    while stay.any_alive:
        obs, res = stay.step(Scripted([0, 0]).act(obs))
        steps += 1
    assert steps == 6 and res.censored.all() and (res.capture_time == 6).all()  # T_max = 3n
    assert (res.captured_by == -1).all()


def test_capture_at_t0_and_false_alarms():
    g, model = two_rooms(stay_target_at=0)  # target on the start node: captured at t = 0
    sim = SearchSim(g, model, Sensor(), n_robots=3, batch=5, auto_reset=False)
    obs = sim.reset()
    obs, res = sim.step(Scripted([1, 1]).act(obs))
    assert res.done.all() and (res.capture_time == 0).all()
    g, model = two_rooms(stay_target_at=1)
    sim = SearchSim(g, model, Sensor(eta_fp=0.4), n_robots=1, batch=2000, auto_reset=False, seed=3)
    obs = sim.reset()
    while sim.any_alive:
        obs, res_last = sim.step(Scripted([0, 0]).act(obs))
    # 7 observations (t = 0..6) at node 0, each a false alarm with probability 0.4
    assert abs(res_last.false_alarms.float().mean().item() - 7 * 0.4) < 0.1


def test_withdrawn_robot_neither_moves_nor_captures():
    g, model = two_rooms()
    sim = SearchSim(g, model, Sensor(), n_robots=2, batch=3, auto_reset=False, withdraw_at=[0, 3])
    obs = sim.reset()
    hist = []
    while sim.any_alive:
        obs, res = sim.step(torch.tensor([[1, 0]] * 3))
        hist.append(obs.pos.clone())
    assert all((p[:, 0] == 0).all() for p in hist)  # robot 0 withdrawn at t = 0 never left
    assert res.censored.all()


def test_deterministic_for_a_seed_and_auto_reset():
    g = builtin_graph("museum")
    model, sensor = uniform_walk(g), Sensor(0.1, 0.01)

    def run(seed):
        sim = SearchSim(g, model, sensor, n_robots=3, batch=64, seed=seed)
        searcher = RandomSearcher(g, seed=seed)
        obs = sim.reset()
        done_ct = []
        for _ in range(300):
            obs, res = sim.step(searcher.act(obs))
            done_ct.append(res.capture_time[res.done])
            assert (obs.t[res.done] == 0).all() and obs.new[res.done].all()
            assert (obs.pos[res.done] == g.start).all()
        return torch.cat(done_ct)

    a, b, c = run(1), run(1), run(2)
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert len(a) > 64  # slots were reused for fresh episodes


def test_the_trainers_lean_mode_plays_the_same_episodes():
    """check_actions=False, details=False (what the trainer runs): the same draws, positions,
    observations and ends as the full simulator for the same seed and actions; only the false-alarm
    and captured-by bookkeeping is left out, and a move outside N[p] is no longer refused."""
    g = builtin_graph("office")
    full = SearchSim(g, uniform_walk(g), Sensor(), 3, 64, seed=5, auto_reset=False)
    lean = SearchSim(g, uniform_walk(g), Sensor(), 3, 64, seed=5, auto_reset=False, check_actions=False, details=False)
    obs_f, obs_l = full.reset(), lean.reset()
    searcher = RandomSearcher(g, seed=2)
    while full.any_alive:
        act = searcher.act(obs_f)
        (obs_f, res_f), (obs_l, res_l) = full.step(act), lean.step(act)
        for a, b in ((obs_f.pos, obs_l.pos), (obs_f.z, obs_l.z), (obs_f.t, obs_l.t), (full.target, lean.target)):
            assert torch.equal(a, b)
        for a, b in (
            (res_f.done, res_l.done),
            (res_f.capture_time, res_l.capture_time),
            (res_f.censored, res_l.censored),
        ):
            assert torch.equal(a, b)
    assert not lean.any_alive
    # and episodes restarted in the slots of finished ones, with a noisy sensor (false alarms,
    # captures at t = 0 pending): the same episodes again
    sensor = Sensor(eta_fn=0.2, eta_fp=0.1)
    full_r = SearchSim(g, uniform_walk(g), sensor, 3, 64, seed=6)
    lean_r = SearchSim(g, uniform_walk(g), sensor, 3, 64, seed=6, check_actions=False, details=False)
    obs_f, obs_l = full_r.reset(), lean_r.reset()
    ended = 0
    for _ in range(200):
        act = searcher.act(obs_f)
        (obs_f, res_f), (obs_l, res_l) = full_r.step(act), lean_r.step(act)
        for a, b in ((obs_f.pos, obs_l.pos), (obs_f.z, obs_l.z), (obs_f.t, obs_l.t), (obs_f.new, obs_l.new)):
            assert torch.equal(a, b)
        assert torch.equal(res_f.done, res_l.done) and torch.equal(res_f.censored, res_l.censored)
        assert torch.equal(res_f.capture_time, res_l.capture_time)
        ended += int(res_f.done.sum())
    assert ended > 64  # slots were restarted
    far = next(v for v in range(g.n) if v not in set(g.closed(g.start).tolist()))  # not one move from s
    full.reset()
    with pytest.raises(ValueError, match="is not in N"):
        full.step(torch.full((64, 3), far))

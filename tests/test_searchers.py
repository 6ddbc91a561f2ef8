import numpy as np
import torch

from shared.core.belief_filter import BeliefFilter
from shared.core.graph import builtin_graph, graph_from_dict
from shared.core.models import Sensor, uniform_walk
from shared.engine.searchers import GreedySearcher, RandomSearcher
from shared.engine.sim import SearchSim


def test_random_picks_uniformly_from_the_closed_neighbourhood():
    g = builtin_graph("office")
    sim = SearchSim(g, uniform_walk(g), Sensor(), n_robots=1, batch=20000, seed=0)
    obs = sim.reset()
    a = RandomSearcher(g, seed=1).act(obs)[:, 0].numpy()
    nbrs = g.closed(g.start)
    counts = np.array([(a == v).sum() for v in nbrs])
    assert counts.sum() == 20000
    assert np.all(np.abs(counts / 20000 - 1 / len(nbrs)) < 0.02)


def test_greedy_moves_to_the_largest_predicted_mass():
    g = builtin_graph("office")
    model, sensor = uniform_walk(g), Sensor(0.1, 0.05)
    B, N = 64, 2
    sim = SearchSim(g, model, sensor, n_robots=N, batch=B, seed=3, auto_reset=False)
    greedy = GreedySearcher(g, model, sensor, seed=4)
    filters = [[BeliefFilter(g, model, sensor) for _ in range(N)] for _ in range(B)]
    obs = sim.reset()
    G = model.dense()
    for t in range(8):
        act = greedy.act(obs).numpy()
        for b in range(B):
            if not obs.alive[b]:
                continue
            for i in range(N):
                p, z = int(obs.pos[b, i]), int(obs.z[b, i])
                bel = filters[b][i].reset(p, z) if t == 0 else filters[b][i].update(p, z)
                pred = G.T @ bel
                cand = g.closed(p)
                assert act[b, i] in cand
                assert pred[act[b, i]] >= pred[cand].max() * (1 - 1e-4)
        obs, _ = sim.step(torch.as_tensor(act))


def test_greedy_breaks_ties_uniformly():
    ring = graph_from_dict({"nodes": list(range(6)), "edges": [[i, (i + 1) % 6] for i in range(6)], "start_node": 0})
    model = uniform_walk(ring)
    sim = SearchSim(ring, model, Sensor(), n_robots=1, batch=6000, seed=0)
    obs = sim.reset()
    a = GreedySearcher(ring, model, Sensor(), seed=1).act(obs)[:, 0].numpy()
    keep = ~obs.z[:, 0].numpy()  # where z0 = 0 the belief is uniform on 1..5: nodes 5, 0, 1 tie
    freq = np.array([(a[keep] == v).mean() for v in (5, 0, 1)])
    assert np.all(np.abs(freq - 1 / 3) < 0.03), freq

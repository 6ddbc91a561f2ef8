"""Beliefs: the O(n + m) filter, the batched torch filter and brute-force Bayes must agree."""

import itertools

import numpy as np
import pytest
import torch

from shared.core.belief_filter import BeliefFilter
from shared.core.graph import grid_graph
from shared.core.models import Sensor, from_matrix, lazy_walk
from shared.engine.batched_belief import BatchedBelief


def random_model(graph, rng):
    """A random row-stochastic Gamma on N[u] (clearly non-symmetric) and a random b0."""
    A = graph.adjacency(closed=True) * rng.uniform(0.1, 1.0, (graph.n, graph.n))
    return from_matrix(graph, A / A.sum(1, keepdims=True), rng.dirichlet(np.ones(graph.n)))


def brute_force_posterior(graph, model, sensor, pos, z):
    """P(e_T | all robots' observations) by enumerating every target path. pos, z: (T+1, N)."""
    G, n = model.dense(), graph.n
    ptr, idx = graph.detection_sets(sensor.detection)
    D = [set(idx[ptr[p] : ptr[p + 1]]) for p in range(n)]
    T1 = len(pos)
    post = np.zeros(n)
    for path in itertools.product(range(n), repeat=T1):
        w = model.b0[path[0]]
        for t in range(1, T1):
            w *= G[path[t - 1], path[t]]
        for t in range(T1):
            for p, zz in zip(pos[t], z[t], strict=True):
                inside = path[t] in D[p]
                pz1 = 1 - sensor.eta_fn if inside else sensor.eta_fp
                w *= pz1 if zz else 1 - pz1
        post[path[-1]] += w
    return post / post.sum()


def random_walk(graph, rng, T, N):
    pos = np.zeros((T + 1, N), dtype=int)
    pos[0] = rng.integers(graph.n)
    for t in range(1, T + 1):
        for i in range(N):
            pos[t, i] = rng.choice(graph.closed(pos[t - 1, i]))
    return pos


@pytest.mark.parametrize("detection", ["node", "neighbourhood"])
def test_own_belief_three_ways(small_graph, rng, detection):
    sensor = Sensor(eta_fn=0.2, eta_fp=0.1, detection=detection)
    for _ in range(5):
        model = random_model(small_graph, rng)
        T = 4
        pos = random_walk(small_graph, rng, T, 1)
        z = rng.integers(0, 2, (T + 1, 1))
        f = BeliefFilter(small_graph, model, sensor)
        b = f.reset(int(pos[0, 0]), int(z[0, 0]))
        bb = BatchedBelief(small_graph, model, sensor, dtype=torch.float64)
        lik = bb.likelihood(torch.tensor(pos[0, 0]), torch.tensor(z[0, 0]))
        tb = bb.initial(lik)
        for t in range(1, T + 1):
            b = f.update(int(pos[t, 0]), int(z[t, 0]))
            tb = bb.update(tb, bb.likelihood(torch.tensor(pos[t, 0]), torch.tensor(z[t, 0])))
        want = brute_force_posterior(small_graph, model, sensor, pos, z)
        assert np.allclose(b, want, atol=1e-10)
        assert np.allclose(tb.numpy(), want, atol=1e-10)


def test_collective_belief_and_posterior_b0(small_graph, rng):
    sensor = Sensor(eta_fn=0.15, eta_fp=0.05)
    model = random_model(small_graph, rng)
    N, T = 3, 3
    pos = random_walk(small_graph, rng, T, N)
    z = rng.integers(0, 2, (T + 1, N))
    bb = BatchedBelief(small_graph, model, sensor, dtype=torch.float64)
    P, Z = torch.tensor(pos), torch.tensor(z)
    b = bb.initial(bb.collective_likelihood(P[0:1], Z[0:1]))  # Theorem 2 (Eq. 4-5)
    assert np.allclose(b[0].numpy(), brute_force_posterior(small_graph, model, sensor, pos[:1], z[:1]))
    for t in range(1, T + 1):
        b = bb.update(b, bb.collective_likelihood(P[t : t + 1], Z[t : t + 1]))  # Theorem 3 (Eq. 6-7)
    assert np.allclose(b[0].numpy(), brute_force_posterior(small_graph, model, sensor, pos, z))


def test_orientation_is_gamma_transpose(small_graph):
    """All mass on a pendant node u moves to N[u] along row u of Gamma (Gamma^T b, not Gamma b)."""
    g = small_graph
    model = lazy_walk(g, 0.25, b0=np.eye(g.n)[g.row(14)])
    f = BeliefFilter(g, model, Sensor())
    f.reset(g.row(10), 0)
    b = f.update(g.row(10), 0)
    assert b[g.row(14)] == pytest.approx(0.25) and b[g.row(13)] == pytest.approx(0.75)


def test_vanishing_mass_restarts_from_the_observation(small_graph):
    """A wrong Gamma_hat (target believed frozen at 14) and a detection at 10: mass vanishes."""
    g = small_graph
    frozen = from_matrix(g, np.eye(g.n), np.eye(g.n)[g.row(14)])
    f = BeliefFilter(g, frozen, Sensor())
    f.reset(g.row(10), 0)
    b = f.update(g.row(10), 1)  # eta_fp = 0: the target must be at 10
    assert f.restarts == 1
    assert np.allclose(b, np.eye(g.n)[g.row(10)])
    bb = BatchedBelief(g, frozen, Sensor(), dtype=torch.float64)
    tb = bb.update(bb.b0.unsqueeze(0), bb.likelihood(torch.tensor([g.row(10)]), torch.tensor([1])))
    assert np.allclose(tb[0].numpy(), b)


def test_filter_on_a_large_grid_stays_normalised():
    g = grid_graph(100, 100)
    model = lazy_walk(g, 0.5)
    f = BeliefFilter(g, model, Sensor(0.1, 0.01))
    f.reset(0, 0)
    for p in range(1, 50):
        b = f.update(p, 0)
    assert b.sum() == pytest.approx(1.0) and b.min() >= 0


@pytest.mark.parametrize("detection", ["node", "neighbourhood"])
def test_sparse_beliefs_agree_with_dense_ones(detection):
    """Above SPARSE_FROM_NODES the engine keeps Gamma_hat on its support and Lambda as D(p): the
    same algebra as the dense matrices, to float32 rounding."""
    from shared.core.graph import builtin_graph

    graph = builtin_graph("museum")
    model = lazy_walk(graph, 0.3)
    gen = torch.Generator().manual_seed(0)
    for sensor in (Sensor(detection=detection), Sensor(eta_fn=0.1, eta_fp=0.05, detection=detection)):
        dense, sparse = (BatchedBelief(graph, model, sensor, sparse=s) for s in (False, True))
        assert dense.gamma is not None and sparse.gamma is None
        pos = torch.randint(0, graph.n, (7, 3), generator=gen)
        z = torch.rand(7, 3, generator=gen) < 0.3
        b = torch.softmax(torch.rand(7, 3, graph.n, generator=gen), -1)
        torch.testing.assert_close(sparse.likelihood(pos, z), dense.likelihood(pos, z), rtol=0, atol=0)
        torch.testing.assert_close(sparse.predict(b), dense.predict(b))
        lik = dense.likelihood(pos, z)
        torch.testing.assert_close(sparse.update(b, lik), dense.update(b, lik))
        np.testing.assert_allclose(sparse.model(graph, "m").dense(), dense.model(graph, "m").dense(), atol=1e-7)


def test_a_ten_thousand_node_floor_runs_in_the_engine_without_an_n_by_n_array():
    from shared.core.graph import office_graph
    from shared.engine.searchers import GreedySearcher
    from shared.engine.sim import SearchSim

    graph = office_graph(10_000, seed=0)
    model, sensor = lazy_walk(graph, 0.5), Sensor()
    sim = SearchSim(graph, model, sensor, 2, 4, seed=0, auto_reset=False)
    greedy = GreedySearcher(graph, model, sensor, seed=0)
    assert greedy.beliefs.belief.sparse
    obs = sim.reset()
    for _ in range(30):
        obs, _res = sim.step(greedy.act(obs))
    b = greedy.beliefs._pred
    assert b is not None and b.shape == (4, 2, graph.n)
    torch.testing.assert_close(b.sum(-1), torch.ones(4, 2))
    for holder in (sim, greedy.beliefs.belief):
        big = [k for k, v in vars(holder).items() if isinstance(v, torch.Tensor) and v.numel() >= graph.n**2 // 100]
        assert not big, big  # nothing of O(n^2) size (the largest table here is O(n + m))

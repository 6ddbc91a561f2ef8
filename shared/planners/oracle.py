"""`oracle`: robots that always know the target's node, acting on the exact dynamic-programming
optimum for N <= 2 (a lower bound for every method that does not see the target)."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import torch

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.engine.sim import Obs


def oracle_values(graph: Graph, model: TargetModel, sensor: Sensor, robots: int) -> tuple[np.ndarray, int]:
    """V[p.., e]: expected remaining capture time (capped at T_max = 3n) when the robots stand on
    p.. and know the target is on e, acting optimally (value iteration over T_max stages).
    Returns (V, T_max); V has shape (n,)*robots + (n,)."""
    if robots not in (1, 2):
        raise ValueError("the oracle is computed exactly for 1 and 2 robots only")
    n, T = graph.n, 3 * graph.n
    G = model.dense()
    det = graph.detection_matrix(sensor.detection).astype(np.float64)
    hit = 1.0 - sensor.eta_fn
    nbr, valid = graph.nbr, np.arange(graph.nbr.shape[1])[None, :] < graph.deg_closed[:, None]
    big = np.inf
    if robots == 1:
        surv = 1.0 - hit * det  # (a, e')
        V = np.zeros((n, n))
        for _ in range(T):
            W = (V * surv) @ G.T  # W[a, e] = sum_e' G(e, e') surv(a, e') V(a, e')
            cand = np.where(valid[:, :, None], W[nbr], big)  # (p, d, e)
            V = 1.0 + cand.min(1)
        return V, T
    surv = (1.0 - hit * det)[:, None, :] * (1.0 - hit * det)[None, :, :]  # (a1, a2, e')
    V = np.zeros((n, n, n))
    for _ in range(T):
        W = (V * surv) @ G.T  # (a1, a2, e)
        M2 = np.where(valid[None, :, :, None], W[:, nbr], big).min(2)  # (a1, p2, e)
        M1 = np.where(valid[:, :, None, None], M2[nbr], big).min(1)  # (p1, p2, e)
        V = 1.0 + M1
    return V, T


def oracle_expected_time(graph: Graph, model: TargetModel, sensor: Sensor, robots: int) -> float:
    """E[t_cap] of the oracle team from the start node (exact, with the T_max cut)."""
    V, _T = oracle_values(graph, model, sensor, robots)
    s = graph.start
    d0 = graph.detection_matrix(sensor.detection)[s]
    miss0 = (1.0 - (1.0 - sensor.eta_fn) * d0) ** robots  # no capture at t = 0
    v0 = V[s] if robots == 1 else V[s, s]
    return float((model.b0 * miss0 * v0).sum())


class OracleSearcher:
    """`oracle`: robots that always know the target's node, acting on the DP values (N <= 2)."""

    name = "oracle"

    _cache: ClassVar[dict[tuple[str, bytes, tuple[float, float, str], int], np.ndarray]] = {}

    def __init__(self, graph: Graph, model: TargetModel, sensor: Sensor, n_robots: int, seed: int = 0) -> None:
        self.graph = graph
        key = (graph.graph_id, model.dense().tobytes(), (sensor.eta_fn, sensor.eta_fp, sensor.detection), n_robots)
        if key not in self._cache:  # the DP is the same for every chunk of an evaluation
            self._cache.clear()
            self._cache[key] = oracle_values(graph, model, sensor, n_robots)[0]
        self.V = self._cache[key]
        self.G = model.dense()
        self.surv = 1.0 - (1.0 - sensor.eta_fn) * graph.detection_matrix(sensor.detection)
        self.N = n_robots

    def act(self, obs: Obs) -> torch.Tensor:
        if obs.target is None:
            raise ValueError("the oracle needs the simulator's target positions")
        pos, tgt = obs.pos.numpy(), obs.target.numpy()
        out = pos.copy()
        g = self.graph
        for e in np.nonzero(obs.alive.numpy())[0]:
            row = self.G[tgt[e]]  # P(e' | e)
            if self.N == 1:
                cand = g.closed(int(pos[e, 0]))
                q = [(row * self.surv[a] * self.V[a]).sum() for a in cand]
                out[e, 0] = cand[int(np.argmin(q))]
            else:
                c1, c2 = g.closed(int(pos[e, 0])), g.closed(int(pos[e, 1]))
                best, arg = np.inf, (pos[e, 0], pos[e, 1])
                for a1 in c1:
                    for a2 in c2:
                        q = (row * self.surv[a1] * self.surv[a2] * self.V[a1, a2]).sum()
                        if q < best:
                            best, arg = q, (a1, a2)
                out[e] = arg
        return torch.as_tensor(out)

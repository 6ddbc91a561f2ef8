"""The methods the paper compares CE-PG with (section V), as batched searchers for the evaluator.

All planners here are *centralised and fully informed*, as in the paper: they get the true target
model and b0 and plan on the collective belief (Theorem 3, every robot's observations). CE-PG
robots, by contrast, use only their own observations and an estimated model. Planning is per
episode (a Python loop over the batch); decision times are reported by the experiments.

- ``fhpe``: finite-horizon path enumeration over the team's joint paths, h = 2 (paper Table II),
  maximising the discounted probability of capture sum_k gamma^k P(capture at k), gamma = 0.97;
  receding horizon (the first move is taken, then it plans again). Node detection only.
- ``fhpe-sa``: the same objective with sequential allocation: robot 1 picks its best h-step path
  (h = 5), robot 2 its best given robot 1's, and so on.
- ``milp``: the MESPP mixed-integer model of Asfora et al. (robots' paths as flows on the
  time-expanded graph, belief mass propagated through Gamma, capture linearised: captured mass
  c_t(v) <= (1 - eta_fn) m_t(v) and c_t(v) <= y_t(v), where y_t(v) = 1 iff some robot detects v),
  objective the discounted captured mass, horizon h = 5, solved by HiGHS (scipy.optimize.milp)
  with a per-solve time limit; the incumbent is used when the limit is hit, and a one-step
  sequential greedy move when there is none yet (counted in ``fallbacks``).
- ``d-milp``: the distributed variant: robots solve one after another, each with the plans of
  the robots before it fixed.
- ``oracle``: robots that always know where the target is, acting on the dynamic-programming
  optimum for N = 1 and N = 2 (``oracle_expected_time`` gives the exact expectation with the
  T_max cut). Its capture time is a lower bound for every method that does not see the target.
  Not computed for N > 2 (the state space is n^(N+1)).
"""

from __future__ import annotations

import itertools
import math
from typing import ClassVar

import numpy as np
import scipy.sparse as sp
import torch

from shared.belief import BatchedBelief
from shared.graph import Graph
from shared.models import Sensor, TargetModel
from shared.searchers import BeliefTracker
from shared.sim import Obs

GAMMA = 0.97  # discount of the planners' objective (paper Table II)
BASELINES = ("fhpe", "fhpe-sa", "milp", "d-milp", "oracle")


class _Planner:
    """Collective belief with the true model; ``plan(b, pos, active)`` -> next rows, per episode."""

    name = "planner"

    def __init__(self, graph: Graph, model: TargetModel, sensor: Sensor, seed: int = 0) -> None:
        self.graph, self.sensor = graph, sensor
        self.n = graph.n
        self.gamma_dense = model.dense()
        self.G = sp.csr_matrix(self.gamma_dense)  # Gamma, row-stochastic
        self.belief = BatchedBelief(graph, model, sensor, "cpu", dtype=torch.float64)
        self.tracker = BeliefTracker(self.belief)
        self.det = graph.detection_matrix(sensor.detection).astype(np.float64)  # det[p, v] = 1 if v in D(p)
        self.hit = 1.0 - sensor.eta_fn  # P(z = 1 | target in D(p))
        self.rng = np.random.default_rng(seed)
        self.decisions = 0

    def act(self, obs: Obs) -> torch.Tensor:
        lik = self.belief.collective_likelihood(obs.pos, obs.z, obs.active).unsqueeze(1)  # (B, 1, n)
        b, _ = self.tracker.update(lik, obs.new)  # Eq. 6 with the true Gamma, (B, 1, n)
        b = b[:, 0].numpy()
        pos = obs.pos.numpy()
        act = pos.copy()
        for e in np.nonzero(obs.alive.numpy())[0]:
            active = obs.active[e].numpy()
            act[e] = self.plan(b[e], pos[e], active)
            self.decisions += 1
        return torch.as_tensor(act)

    def plan(self, b: np.ndarray, pos: np.ndarray, active: np.ndarray) -> np.ndarray:
        raise NotImplementedError


def walks(graph: Graph, start: int, h: int) -> np.ndarray:
    """All walks of h moves from ``start`` (stays allowed): (K, h) rows after each move."""
    paths = np.array([[start]], dtype=np.int64)
    for _ in range(h):
        last = paths[:, -1]
        deg = graph.deg_closed[last]
        rep = np.repeat(np.arange(len(paths)), deg)
        nxt = np.concatenate([graph.closed(int(p)) for p in last])
        paths = np.concatenate([paths[rep], nxt[:, None]], axis=1)
    return paths[:, 1:]


class FhpeSA(_Planner):
    """`fhpe-sa`: sequential allocation of h-step paths (module docstring)."""

    name = "fhpe-sa"

    def __init__(self, graph: Graph, model: TargetModel, sensor: Sensor, seed: int = 0, horizon: int = 5) -> None:
        super().__init__(graph, model, sensor, seed)
        self.h = horizon
        self._walks: dict[int, np.ndarray] = {}
        self.disc = GAMMA ** np.arange(1, horizon + 1)

    def _paths(self, p: int) -> np.ndarray:
        if p not in self._walks:
            self._walks[p] = walks(self.graph, p, self.h)
        return self._walks[p]

    def plan(self, b: np.ndarray, pos: np.ndarray, active: np.ndarray) -> np.ndarray:
        h, hit = self.h, self.hit
        survive_fixed = np.ones((h, self.n))  # 1 - hit * [v detected by the robots already planned]
        out = pos.copy()
        g1 = b @ self.gamma_dense  # Gamma^T b
        for i in np.nonzero(active)[0]:
            P = self._paths(int(pos[i]))  # (K, h)
            U = np.broadcast_to(g1, (len(P), self.n)).copy()
            val = np.zeros(len(P))
            for k in range(h):
                if k:
                    U = np.asarray(U @ self.G)  # propagate the uncaptured mass: U Gamma
                cap = U @ (1.0 - survive_fixed[k])
                U *= survive_fixed[k]
                D = self.det[P[:, k]]
                cap += hit * (U * D).sum(1)
                U *= 1.0 - hit * D
                val += self.disc[k] * cap
            best = np.flatnonzero(val >= val.max() - 1e-12)
            j = int(self.rng.choice(best))
            for k in range(h):
                survive_fixed[k] *= 1.0 - hit * self.det[P[j, k]]
            out[i] = P[j, 0]
        return out


class Fhpe(_Planner):
    """`fhpe`: joint path enumeration, horizon 2 (module docstring). Node detection only."""

    name = "fhpe"
    MAX_JOINT = 3_000_000

    def __init__(self, graph: Graph, model: TargetModel, sensor: Sensor, seed: int = 0) -> None:
        if sensor.detection != "node":
            raise ValueError("fhpe enumerates joint paths for node detection only; use fhpe-sa")
        super().__init__(graph, model, sensor, seed)
        self._walks: dict[int, np.ndarray] = {}

    def plan(self, b: np.ndarray, pos: np.ndarray, active: np.ndarray) -> np.ndarray:
        robots = np.nonzero(active)[0]
        per = [self._walks.setdefault(int(pos[i]), walks(self.graph, int(pos[i]), 2)) for i in robots]
        M = math.prod(len(p) for p in per)
        if M > self.MAX_JOINT:
            raise ValueError(f"fhpe: {M:,} joint paths for {len(robots)} robots; use fhpe-sa (sequential)")
        idx = np.array(list(itertools.product(*[range(len(p)) for p in per])), dtype=np.int64)  # (M, N)
        A1 = np.stack([per[r][idx[:, r], 0] for r in range(len(robots))], 1)  # (M, N) rows after move 1
        A2 = np.stack([per[r][idx[:, r], 1] for r in range(len(robots))], 1)
        hit = self.hit
        g1 = b @ self.gamma_dense  # mass at step 1
        g2 = g1 @ self.gamma_dense  # mass at step 2 without any capture at step 1

        def first(A: np.ndarray) -> np.ndarray:  # a node counts once in a union
            keep = np.ones(A.shape, dtype=bool)
            for j in range(1, A.shape[1]):
                keep[:, j] = (A[:, :j] != A[:, j : j + 1]).all(1)
            return keep

        k1, k2 = first(A1), first(A2)
        c1 = hit * (g1[A1] * k1).sum(1)
        # (U1 Gamma)(w) = g2(w) - hit * sum_{v in S1} g1(v) Gamma(v, w)   (linearity, S1 a union)
        cross = (k1[:, :, None] * g1[A1][:, :, None] * self.gamma_dense[A1[:, :, None], A2[:, None, :]]).sum(1)
        c2 = hit * ((g2[A2] - hit * cross) * k2).sum(1)
        val = GAMMA * c1 + GAMMA**2 * c2
        best = np.flatnonzero(val >= val.max() - 1e-12)
        m = int(self.rng.choice(best))
        out = pos.copy()
        out[robots] = A1[m]
        return out


class Milp(_Planner):
    """`milp` (and `d-milp` with ``distributed``): the MESPP model solved by HiGHS (module docstring)."""

    name = "milp"

    def __init__(self, graph: Graph, model: TargetModel, sensor: Sensor, seed: int = 0, horizon: int = 5,
                 time_limit: float = 2.0, distributed: bool = False) -> None:  # fmt: skip
        super().__init__(graph, model, sensor, seed)
        self.h, self.time_limit, self.distributed = horizon, time_limit, distributed
        self.name = "d-milp" if distributed else "milp"
        self.adj = graph.closed_adjacency.astype(np.float64)
        self.timeouts = 0
        self.fallbacks = 0

    def plan(self, b: np.ndarray, pos: np.ndarray, active: np.ndarray) -> np.ndarray:
        robots = [int(i) for i in np.nonzero(active)[0]]
        out = pos.copy()
        if not self.distributed:
            paths = self._solve(b, [int(pos[i]) for i in robots], {})
            for r, i in enumerate(robots):
                out[i] = paths[r][0]
            return out
        fixed: dict[int, list[int]] = {}
        for r, i in enumerate(robots):
            paths = self._solve(b, [int(pos[j]) for j in robots[: r + 1]], fixed)
            fixed[r] = paths[r]
            out[i] = paths[r][0]
        return out

    def _one_step_paths(self, b: np.ndarray, starts: list[int], fixed: dict[int, list[int]]) -> list[list[int]]:
        """The fallback when HiGHS has no incumbent within the time limit: robot by robot (the fixed
        plans first), the move or stay whose detection set holds the most predicted mass b Gamma not
        yet covered by the robots before it; then it stays for the rest of the horizon."""
        mass = b @ self.gamma_dense
        free = np.ones(self.n, dtype=bool)
        paths: list[list[int]] = []
        for r, s in enumerate(starts):
            if r in fixed:
                v = fixed[r][0]
            else:
                nbrs = self.graph.closed(s)
                v = int(nbrs[int(np.argmax([(mass * free * self.det[u]).sum() for u in nbrs]))])
            free &= self.det[v] == 0
            paths.append(fixed.get(r, [v] * self.h))
        return paths

    def _solve(self, b: np.ndarray, starts: list[int], fixed: dict[int, list[int]]) -> list[list[int]]:
        """Team paths (h nodes each) maximising sum_t gamma^t sum_v c_t(v)."""
        from scipy.optimize import Bounds, LinearConstraint, milp

        n, h, R = self.n, self.h, len(starts)
        nx = R * n * h  # x[r, v, t], t = 1..h
        ny = n * h  # y[v, t]
        nc = n * h  # c[v, t]   captured mass
        nu = n * h  # u[v, t]   uncaptured mass after step t
        X = lambda r, t: r * n * h + t * n + np.arange(n)  # noqa: E731
        Y = lambda t: nx + t * n + np.arange(n)  # noqa: E731
        C = lambda t: nx + ny + t * n + np.arange(n)  # noqa: E731
        U = lambda t: nx + ny + nc + t * n + np.arange(n)  # noqa: E731
        nvar = nx + ny + nc + nu
        rows, cols, vals, lo, hi = [], [], [], [], []
        row = 0

        def add(block_cols: list[np.ndarray], blocks: list[np.ndarray], lb: np.ndarray, ub: np.ndarray) -> None:
            """Rows lb <= sum_j blocks[j] @ x[block_cols[j]] <= ub (each block k x n, dense)."""
            nonlocal row
            for c_, m_ in zip(block_cols, blocks, strict=True):
                r_, cc = np.nonzero(m_)
                rows.append(row + r_)
                cols.append(c_[cc])
                vals.append(m_[r_, cc])
            lo.append(lb)
            hi.append(ub)
            row += len(lb)

        one, zero = np.ones(n), np.zeros(n)
        eye = np.eye(n)
        g1 = b @ self.gamma_dense
        for r in range(R):
            for t in range(h):
                add([X(r, t)], [np.ones((1, n))], np.ones(1), np.ones(1))  # one node per time
                prev = self.adj[starts[r]] if t == 0 else None
                if t == 0:  # x[r, v, 1] <= [v in N[p_r]]
                    add([X(r, 0)], [eye], -np.inf * one, prev)
                else:  # x[r, v, t] <= sum_{u in N[v]} x[r, u, t-1]
                    add([X(r, t), X(r, t - 1)], [eye, -self.adj], -np.inf * one, zero)
        for t in range(h):
            # y[v, t] <= sum_r sum_{p: v in D(p)} x[r, p, t]
            add([Y(t)] + [X(r, t) for r in range(R)], [eye] + [-self.det.T] * R, -np.inf * one, zero)
            # c[v, t] <= y[v, t]  (mass <= 1)
            add([C(t), Y(t)], [eye, -eye], -np.inf * one, zero)
            # m_t = Gamma^T u_{t-1} (m_1 = Gamma^T b); c <= hit * m; u = m - c
            if t == 0:
                add([C(0)], [eye], -np.inf * one, self.hit * g1)
                add([U(0), C(0)], [eye, eye], g1, g1)
            else:
                GT = self.gamma_dense.T
                add([C(t), U(t - 1)], [eye, -self.hit * GT], -np.inf * one, zero)
                add([U(t), C(t), U(t - 1)], [eye, eye, -GT], zero, zero)
        A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(row, nvar))
        cost = np.zeros(nvar)
        for t in range(h):
            cost[C(t)] = -(GAMMA ** (t + 1))
        lb, ub = np.zeros(nvar), np.ones(nvar)
        ub[nx + ny :] = np.inf
        for r, path in fixed.items():
            for t, v in enumerate(path):
                lb[X(r, t)[v]] = 1.0
        integrality = np.zeros(nvar)
        integrality[: nx + ny] = 1
        res = milp(cost, constraints=LinearConstraint(A, np.concatenate(lo), np.concatenate(hi)),
                   integrality=integrality, bounds=Bounds(lb, ub),
                   options={"time_limit": self.time_limit, "disp": False})  # fmt: skip
        if res.status == 1:
            self.timeouts += 1
        if res.x is None:  # no incumbent within the limit
            self.fallbacks += 1
            return self._one_step_paths(b, starts, fixed)
        x = res.x[:nx].reshape(R, h, n)
        return [[int(np.argmax(x[r, t])) for t in range(h)] for r in range(R)]


# ---------------------------------------------------------------------- oracle
def _capture_factor(det: np.ndarray, hit: float, acts: list[np.ndarray]) -> np.ndarray:
    """P(no capture | target at e') for robots at ``acts`` (broadcast shapes), per e'."""
    f = 1.0
    for a in acts:
        f = f * (1.0 - hit * det[a])
    return f


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


def make_baseline(name: str, graph: Graph, model: TargetModel, sensor: Sensor, n_robots: int, seed: int = 0,
                  **kw: float) -> object:  # fmt: skip
    if name == "fhpe":
        return Fhpe(graph, model, sensor, seed)
    if name == "fhpe-sa":
        return FhpeSA(graph, model, sensor, seed, horizon=int(kw.get("horizon", 5)))
    if name in ("milp", "d-milp"):
        return Milp(graph, model, sensor, seed, horizon=int(kw.get("horizon", 5)),
                    time_limit=float(kw.get("time_limit", 2.0)), distributed=name == "d-milp")  # fmt: skip
    if name == "oracle":
        return OracleSearcher(graph, model, sensor, n_robots, seed)
    raise ValueError(f"unknown baseline {name!r}")

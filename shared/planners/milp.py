"""`milp` and `d-milp`: the MESPP mixed-integer model solved by HiGHS (shared/planners/base.py
describes the model)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator

import numpy as np
import scipy.sparse as sp

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.planners.base import GAMMA, Planner

_LIBC = ctypes.CDLL(None)


@contextlib.contextmanager
def native_stdout_to_stderr() -> Iterator[None]:
    """While the block runs, what native code writes to stdout (file descriptor 1) goes to stderr.

    HiGHS prints some diagnostics with printf whatever its output options say (for example
    ``HighsMipSolverData::transformNewIntegerFeasibleSolution tmpSolver.run();`` in the middle of a
    d-milp run), which broke `mures evaluate --json`'s promise of pure JSON on stdout. C's stdio
    buffers are flushed before fd 1 is restored, so nothing written inside leaks out later.
    Process-wide: another thread printing during a solve also goes to stderr."""
    sys.stdout.flush()
    _LIBC.fflush(None)
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        _LIBC.fflush(None)
        os.dup2(saved, 1)
        os.close(saved)


class Milp(Planner):
    """`milp` (and `d-milp` with ``distributed``): the MESPP model solved by HiGHS (module docstring)."""

    name = "milp"

    def __init__(
        self,
        graph: Graph,
        model: TargetModel,
        sensor: Sensor,
        seed: int = 0,
        horizon: int = 5,
        time_limit: float = 2.0,
        distributed: bool = False,
    ) -> None:
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
                if t == 0:  # x[r, v, 1] <= [v in N[p_r]]
                    add([X(r, 0)], [eye], -np.inf * one, self.adj[starts[r]])
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
        with native_stdout_to_stderr():
            res = milp(
                cost,
                constraints=LinearConstraint(A, np.concatenate(lo), np.concatenate(hi)),
                integrality=integrality,
                bounds=Bounds(lb, ub),
                options={"time_limit": self.time_limit, "disp": False},
            )
        if res.status == 1:
            self.timeouts += 1
        if res.x is None:  # no incumbent within the limit
            self.fallbacks += 1
            return self._one_step_paths(b, starts, fixed)
        x = res.x[:nx].reshape(R, h, n)
        return [[int(np.argmax(x[r, t])) for t in range(h)] for r in range(R)]

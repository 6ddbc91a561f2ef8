"""`milp` and `d-milp`: the MESPP mixed-integer model solved by HiGHS through highspy
(shared/planners/base.py describes the model)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator

import numpy as np
import scipy.sparse as sp

from shared.core.fhpe_sa import GAMMA
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.planners.base import Planner

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
        self._models: dict[int, _TeamModel] = {}  # one HiGHS model per team size solved, for this episode
        self._plans: dict[tuple[int, int], list[int]] = {}  # (team size, robot) -> its last plan

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
        """The first incumbent of a robot with no plan to continue, and the fallback if HiGHS were
        left with none: robot by robot (the fixed plans first), the move or stay whose detection
        set holds the most predicted mass b Gamma not yet covered by the robots before it; then it
        stays for the rest of the horizon."""
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

    def _model(self, R: int) -> _TeamModel:
        """The MILP of an R-robot team for this episode, built once and then only re-bounded."""
        if R not in self._models:
            self._models[R] = _TeamModel(
                R, self.n, self.h, self.adj, self.det, self.gamma_dense, self.hit, self.time_limit
            )
        return self._models[R]

    def _solve(self, b: np.ndarray, starts: list[int], fixed: dict[int, list[int]]) -> list[list[int]]:
        """Team paths (h nodes each) maximising sum_t gamma^t sum_v c_t(v), warm-started from each
        robot's previous plan shifted by the step it took (or from the greedy uncovered move)."""
        m = self._model(len(starts))
        g1 = b @ self.gamma_dense
        greedy = self._one_step_paths(b, starts, fixed)
        start_paths = []
        for r, s in enumerate(starts):
            prev = self._plans.get((len(starts), r))
            if r in fixed:
                start_paths.append(fixed[r])
            elif prev is not None and prev[0] == s:  # the robot took its plan's first move
                start_paths.append(prev[1:] + prev[-1:])
            else:
                start_paths.append(greedy[r])
        with native_stdout_to_stderr():
            paths, status = m.solve(g1, starts, fixed, start_paths)
        if status == "time_limit":
            self.timeouts += 1
        if paths is None:  # no incumbent within the limit
            self.fallbacks += 1
            return self._one_step_paths(b, starts, fixed)
        for r, path in enumerate(paths):
            self._plans[(len(starts), r)] = path
        return paths


class _TeamModel:
    """The MESPP model (shared/planners/base.py) of R robots over horizon h, held by one HiGHS
    instance (highspy) for an episode. Only bounds change from one decision to the next: the
    robots' first moves (x[r, v, 1] <= [v in N[p_r]]), the predicted mass m_1 = Gamma^T b (c[v, 1]
    <= hit m_1(v) and u[v, 1] + c[v, 1] = m_1(v)) and the plans held fixed (d-milp); so the
    matrix is built once, and each solve starts from a feasible incumbent given to HiGHS.

    Columns: x[r, v, t] (R n h, binary), y[v, t] (n h, binary), c[v, t] captured and u[v, t]
    uncaptured mass (n h each, continuous); t = 1..h is stored as 0..h-1."""

    def __init__(
        self,
        R: int,
        n: int,
        h: int,
        adj: np.ndarray,
        det: np.ndarray,
        gamma: np.ndarray,
        hit: float,
        time_limit: float,
    ) -> None:
        import highspy

        self.R, self.n, self.h, self.adj, self.det, self.gamma, self.hit = R, n, h, adj, det, gamma, hit
        nx = R * n * h
        self.nx = nx
        self.Y0, self.C0, self.U0 = nx, nx + n * h, nx + 2 * n * h
        nvar = nx + 3 * n * h
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        lo: list[np.ndarray] = []
        hi: list[np.ndarray] = []
        row = 0

        def add(block_cols: list[np.ndarray], blocks: list[np.ndarray], lb: np.ndarray, ub: np.ndarray) -> int:
            """Rows lb <= sum_j blocks[j] @ x[block_cols[j]] <= ub (each block k x n, dense); their first row."""
            nonlocal row
            for c_, m_ in zip(block_cols, blocks, strict=True):
                r_, cc = np.nonzero(m_)
                rows.append(row + r_)
                cols.append(c_[cc])
                vals.append(m_[r_, cc])
            lo.append(lb)
            hi.append(ub)
            first, row = row, row + len(lb)
            return first

        one, zero, eye, GT = np.ones(n), np.zeros(n), np.eye(n), gamma.T
        for r in range(R):
            for t in range(h):
                add([self.X(r, t)], [np.ones((1, n))], np.ones(1), np.ones(1))  # one node per time
                if t > 0:  # x[r, v, t] <= sum_{u in N[v]} x[r, u, t-1]
                    add([self.X(r, t), self.X(r, t - 1)], [eye, -adj], -np.inf * one, zero)
        for t in range(h):
            # y[v, t] <= sum_r sum_{p: v in D(p)} x[r, p, t]
            add([self.Y(t)] + [self.X(r, t) for r in range(R)], [eye] + [-det.T] * R, -np.inf * one, zero)
            add([self.C(t), self.Y(t)], [eye, -eye], -np.inf * one, zero)  # c[v, t] <= y[v, t] (mass <= 1)
            if t == 0:  # u_1 + c_1 = m_1 (its bounds set per solve); c_1 <= hit m_1 is a column bound
                self.mass_rows = add([self.U(0), self.C(0)], [eye, eye], zero, zero) + np.arange(n)
            else:  # m_t = Gamma^T u_{t-1}; c_t <= hit m_t; u_t = m_t - c_t
                add([self.C(t), self.U(t - 1)], [eye, -hit * GT], -np.inf * one, zero)
                add([self.U(t), self.C(t), self.U(t - 1)], [eye, eye, -GT], zero, zero)
        A = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(row, nvar))
        lp = highspy.HighsLp()
        lp.num_col_, lp.num_row_ = nvar, row
        cost = np.zeros(nvar)
        for t in range(h):
            cost[self.C(t)] = -(GAMMA ** (t + 1))
        lp.col_cost_ = cost
        self.col_lb, self.col_ub = np.zeros(nvar), np.ones(nvar)
        self.col_ub[self.C0 :] = np.inf
        lp.col_lower_, lp.col_upper_ = self.col_lb, self.col_ub
        lp.row_lower_, lp.row_upper_ = np.concatenate(lo), np.concatenate(hi)
        lp.a_matrix_.format_ = highspy.MatrixFormat.kColwise
        lp.a_matrix_.start_, lp.a_matrix_.index_, lp.a_matrix_.value_ = A.indptr, A.indices, A.data
        lp.integrality_ = [highspy.HighsVarType.kInteger] * (nx + n * h) + [highspy.HighsVarType.kContinuous] * (
            2 * n * h
        )
        self.highs = highspy.Highs()
        self.highs.setOptionValue("output_flag", False)
        self.highs.setOptionValue("time_limit", float(time_limit))
        self.highs.setOptionValue("random_seed", 0)
        self.highs.passModel(lp)
        self._status = highspy.HighsModelStatus
        self._all = np.arange(nvar, dtype=np.int32)

    def X(self, r: int, t: int) -> np.ndarray:
        return r * self.n * self.h + t * self.n + np.arange(self.n)

    def Y(self, t: int) -> np.ndarray:
        return self.Y0 + t * self.n + np.arange(self.n)

    def C(self, t: int) -> np.ndarray:
        return self.C0 + t * self.n + np.arange(self.n)

    def U(self, t: int) -> np.ndarray:
        return self.U0 + t * self.n + np.arange(self.n)

    def incumbent(self, g1: np.ndarray, paths: list[list[int]]) -> np.ndarray:
        """The model's variables for the team walking ``paths`` (a feasible point): x from the
        paths, y what they detect, c and u the mass they capture and leave, step by step."""
        x = np.zeros(self.nvar)
        m = g1
        for t in range(self.h):
            y = np.zeros(self.n)
            for r, path in enumerate(paths):
                x[self.X(r, t)[path[t]]] = 1.0
                y = np.maximum(y, self.det[path[t]])
            c = self.hit * m * y
            u = m - c
            x[self.Y(t)], x[self.C(t)], x[self.U(t)] = y, c, u
            m = u @ self.gamma  # Gamma^T u, as a row vector
        return x

    @property
    def nvar(self) -> int:
        return self.U0 + self.n * self.h

    def solve(
        self, g1: np.ndarray, starts: list[int], fixed: dict[int, list[int]], warm: list[list[int]]
    ) -> tuple[list[list[int]] | None, str]:
        """Re-bound the model for this decision, give HiGHS ``warm`` as its first incumbent, solve
        within the time limit; the paths (None without an incumbent) and "optimal", "time_limit"
        or another HiGHS status."""
        lb, ub = self.col_lb.copy(), self.col_ub.copy()
        for r, s in enumerate(starts):
            ub[self.X(r, 0)] = self.adj[s]  # x[r, v, 1] <= [v in N[p_r]]
        for r, path in fixed.items():
            for t, v in enumerate(path):
                lb[self.X(r, t)[v]] = 1.0
        ub[self.C(0)] = self.hit * g1  # c_1 <= hit m_1
        h = self.highs
        h.changeColsBounds(len(lb), self._all, lb, ub)
        for k, v in zip(self.mass_rows, g1, strict=True):
            h.changeRowBounds(int(k), float(v), float(v))  # u_1 + c_1 = m_1
        sol = h.getSolution()
        sol.col_value = list(self.incumbent(g1, warm))
        sol.value_valid = True
        h.setSolution(sol)
        h.run()
        status = h.getModelStatus()
        label = {self._status.kOptimal: "optimal", self._status.kTimeLimit: "time_limit"}.get(status, str(status))
        if h.getInfo().primal_solution_status == 0:
            return None, label
        x = np.asarray(h.getSolution().col_value[: self.nx]).reshape(self.R, self.h, self.n)
        return [[int(np.argmax(x[r, t])) for t in range(self.h)] for r in range(self.R)], label

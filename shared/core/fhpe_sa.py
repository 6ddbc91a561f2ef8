"""FHPE-SA's planning step in numpy (the paper's finite-horizon path enumeration with sequential
allocation, section V): what both the batched planner (shared/planners/fhpe.py) and a robot agent
flying the team's plan (shared/core/team.py) run. No scipy, no torch.

The objective over a horizon of h moves (paper Table II: h = 5, gamma = 0.97) is the discounted
probability of capture sum_k gamma^k P(capture at step k), with the target's mass propagated by
Gamma_hat (``U Gamma``, row vectors) and each detection catching it with probability 1 - eta_fn.
Robot 1 (in the team's order) picks its best h-step walk, robot 2 its best given robot 1's, and
so on; the first move of each robot's walk is taken, then the team plans again (receding horizon).
Ties between equally good walks are broken by the caller's random generator, so that robots
planning from the same information with generators seeded alike choose the same plan.

On the mission clock (``move_steps``, shared/core/timed_team.py) a move lasts its travel time in
the model's steps, and a detection's discount is gamma to the power of the steps' worth of time
elapsed when it happens: of two walks that look alike, the one through shorter edges is worth more.
With ``travel`` the target's mass is also propagated over each move's steps rather than once a move:
s steps as c = ceil(s) passes of I + (s / c)(Gamma - I), the uniformization of shared/core/clock.py.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel

GAMMA = 0.97  # discount of the planners' objective (paper Table II)
HORIZON = 5  # fhpe-sa's h (paper Table II)


def walks(graph: Graph, start: int, h: int) -> np.ndarray:
    """All walks of h moves from ``start`` (stays allowed): (K, h) rows after each move."""
    return walk_tree(graph, start, h)[0]


def walk_tree(graph: Graph, start: int, h: int) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
    """The walks of ``walks`` and the tree of their prefixes: per move k, each prefix's parent
    among the prefixes of k - 1 moves and its node (the last prefixes are the walks, in order)."""
    paths = np.array([[start]], dtype=np.int64)
    levels = []
    for _ in range(h):
        last = paths[:, -1]
        deg = graph.deg_closed[last]
        rep = np.repeat(np.arange(len(paths)), deg)
        nxt = np.concatenate([graph.closed(int(p)) for p in last])
        levels.append((rep, nxt))
        paths = np.concatenate([paths[rep], nxt[:, None]], axis=1)
    return paths[:, 1:], levels


class FhpeSAPlanner:
    """The team's next moves for a belief ``b`` (n,) and positions ``pos`` (N,) under ``model``:
    ``plan(b, pos, active, rng)`` -> (N,) node rows (a robot not ``active`` stays where it is).

    ``propagate`` is U -> U Gamma for U (K, n); the default sums over Gamma's nonzeros (O(K (n + m))
    rather than a dense product's O(K n^2)), the batched planner passes its scipy product."""

    def __init__(
        self,
        graph: Graph,
        model: TargetModel,
        sensor: Sensor,
        horizon: int = HORIZON,
        propagate: Callable[[np.ndarray], np.ndarray] | None = None,
        move_steps: np.ndarray | None = None,
        travel: bool = False,
    ) -> None:
        if travel and move_steps is None:
            raise ValueError("travel propagates the target over each move's steps: it needs move_steps")
        self.graph, self.n, self.h = graph, graph.n, horizon
        self.move_steps = move_steps  # (n, n): how many of the model's steps the move u -> v lasts (None: 1 each)
        self.travel = travel  # the target propagated over each move's steps, not once a move
        self.gamma_dense = model.dense()
        self.propagate = propagate or _SparsePropagation(model)
        self.det = graph.detection_matrix(sensor.detection).astype(np.float64)  # det[p, v] = 1 if v in D(p)
        self.hit = 1.0 - sensor.eta_fn  # P(z = 1 | target in D(p))
        self.disc = GAMMA ** np.arange(1, horizon + 1)
        self._walks: dict[int, tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]] = {}

    def paths(self, p: int) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray]]]:
        """``walk_tree`` from node row ``p``, computed once per node."""
        if p not in self._walks:
            self._walks[p] = walk_tree(self.graph, p, self.h)
        return self._walks[p]

    def plan(self, b: np.ndarray, pos: np.ndarray, active: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The walks' values are computed down their prefix tree: the target's mass is propagated
        once per prefix (the K_{k-1} prefixes of k - 1 moves, not the K walks), which gives each walk
        the same numbers as propagating it on its own (with ``travel``, once per walk prefix's last
        move, over that move's steps)."""
        h, hit = self.h, self.hit
        survive_fixed = np.ones((h, self.n))  # 1 - hit * [v detected by the robots already planned]
        out = pos.copy()
        first = b if self.travel else b @ self.gamma_dense  # Gamma^T b: the mass at the first arrival
        for i in np.nonzero(active)[0]:
            P, levels = self.paths(int(pos[i]))  # (K, h)
            U = first[None, :]  # the uncaptured mass after each prefix, (prefixes, n)
            val = np.zeros(1)
            here, elapsed = np.array([pos[i]]), np.zeros(1)  # each prefix's last node, and its steps' worth of time
            for k, (rep, nodes) in enumerate(levels):
                if k and not self.travel:
                    U = np.asarray(self.propagate(U))  # propagate the uncaptured mass: U Gamma
                U, val = U[rep], val[rep]  # each prefix's children
                if self.move_steps is not None:  # discounted by when the detection happens, not by the move's index
                    steps = self.move_steps[here[rep], nodes]
                    elapsed = elapsed[rep] + steps
                    here = nodes
                    if self.travel:
                        U = self._over(U, steps)
                disc = self.disc[k] if self.move_steps is None else GAMMA**elapsed
                cap = U @ (1.0 - survive_fixed[k])
                U = U * survive_fixed[k]
                D = self.det[nodes]
                cap += hit * (U * D).sum(1)
                U *= 1.0 - hit * D
                val = val + disc * cap
            best = np.flatnonzero(val >= val.max() - 1e-12)
            j = int(rng.choice(best))
            for k in range(h):
                survive_fixed[k] *= 1.0 - hit * self.det[P[j, k]]
            out[i] = P[j, 0]
        return out

    def _over(self, U: np.ndarray, steps: np.ndarray) -> np.ndarray:
        """Each row of U (K, n) propagated over its move's ``steps`` (K,) of the model: c = ceil(s)
        passes of U + (s / c)(U Gamma - U), at least one."""
        passes = np.maximum(np.ceil(steps - 1e-9), 1).astype(np.int64)
        a = (steps / passes)[:, None]
        U = U.copy()
        for j in range(int(passes.max())):
            rows = np.flatnonzero(passes > j)
            Ur = U[rows]
            U[rows] = Ur + a[rows] * (np.asarray(self.propagate(Ur)) - Ur)
        return U


class _SparsePropagation:
    """U -> U Gamma for U (K, n) in O(K (n + m)), numpy only: (U Gamma)[:, v] = sum over the
    entries (u, v) of Gamma of U[:, u] Gamma(u, v), summed per column by ``np.add.reduceat``."""

    def __init__(self, model: TargetModel) -> None:
        order = np.argsort(model.dst, kind="stable")
        self.src, self.prob = model.src[order], model.prob[order]
        dst = model.dst[order]
        self.cols, self.starts = np.unique(dst, return_index=True)  # columns with an entry, where each begins
        self.n = model.n

    def __call__(self, U: np.ndarray) -> np.ndarray:
        out = np.zeros((U.shape[0], self.n))
        out[:, self.cols] = np.add.reduceat(U[:, self.src] * self.prob, self.starts, axis=1)
        return out

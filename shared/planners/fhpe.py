"""`fhpe` (joint path enumeration, h = 2) and `fhpe-sa` (sequential allocation, h = 5): the paper's
finite-horizon path-enumeration planners (shared/planners/base.py has the common setup)."""

from __future__ import annotations

import itertools
import math

import numpy as np

from shared.core.fhpe_sa import GAMMA, FhpeSAPlanner, walks
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.planners.base import Planner


class FhpeSA(Planner):
    """`fhpe-sa`: sequential allocation of h-step paths (shared/core/fhpe_sa.py, which a robot
    agent runs too), on the collective belief with the true model."""

    name = "fhpe-sa"

    def __init__(self, graph: Graph, model: TargetModel, sensor: Sensor, seed: int = 0, horizon: int = 5) -> None:
        super().__init__(graph, model, sensor, seed)
        self.core = FhpeSAPlanner(graph, model, sensor, horizon, propagate=lambda U: U @ self.G)

    def plan(self, b: np.ndarray, pos: np.ndarray, active: np.ndarray) -> np.ndarray:
        return self.core.plan(b, pos, active, self.rng)


class Fhpe(Planner):
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

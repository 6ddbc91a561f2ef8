"""`fhpe` (joint path enumeration, h = 2) and `fhpe-sa` (sequential allocation, h = 5): the paper's
finite-horizon path-enumeration planners (shared/planners/base.py has the common setup)."""

from __future__ import annotations

import itertools
import math

import numpy as np

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.planners.base import GAMMA, Planner, walks


class FhpeSA(Planner):
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

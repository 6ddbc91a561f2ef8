"""Probabilistic target beliefs (PTB), with the orientation of docs/SPEC.md section 2.

Own belief (Theorem 1, Eq. 1-2):   b_t ∝ Lambda(p_t, z_t) Gamma_hat^T b_{t-1},  b_0 ∝ Lambda(p_0, z_0) b0
Collective belief (Theorem 3, Eq. 6-7): the same with the product of all robots' Lambdas.
Posterior b0 (Theorem 2, Eq. 4-5):  b0 ∝ Lambda_0 b0 with all robots' t = 0 observations.

The paper writes "Gamma b"; its Appendix A sums Gamma(k, j) b(k), i.e. Gamma^T b for a
row-stochastic Gamma. As row vectors (how the batched code stores beliefs) that is ``b @ Gamma``.

Vanishing mass. With eta = 0 some Lambda entries are exactly 0; under a correct model the
posterior never vanishes, but with a wrong Gamma_hat it can (the robot sees the target where
Gamma_hat says it cannot be). Then the filter restarts from the current observation alone:
b ∝ Lambda(p_t, z_t) 1 (a uniform prior), and if even that is 0 (impossible for eta < 0.5 unless
D(p) = V and z = 0 with eta_fn = 0) from the uniform belief. ``BeliefFilter.restarts`` counts these.

Two implementations that must agree (tests/test_belief.py checks them against each other and
against brute-force Bayes):
- ``BeliefFilter`` (here): one robot, numpy float64, O(n + m) per step; what a robot agent runs.
- ``BatchedBelief`` (shared/engine/batched_belief.py): beliefs of shape (..., n) in torch; what the
  simulator, the evaluator and the trainer run.
"""

from __future__ import annotations

import numpy as np

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel

TINY = 1e-30


class BeliefFilter:
    """One robot's own belief, updated in O(n + m) per step (sparse Gamma_hat^T b)."""

    def __init__(self, graph: Graph, model: TargetModel, sensor: Sensor) -> None:
        self.n = graph.n
        self._src = model.src
        self._dst = model.dst
        self._prob = model.prob
        self._b0 = model.b0.copy()
        self._dptr, self._didx = graph.detection_sets(sensor.detection)
        (self._in0, self._in1), (self._out0, self._out1) = sensor.likelihoods()
        self._node_detection = sensor.detection == "node"
        self.belief = self._b0.copy()
        self.restarts = 0

    def weigh(self, x: np.ndarray, p: int, z: int) -> np.ndarray:
        """x (n,) *= Lambda(p, z)'s diagonal (Eq. 2), in place, unnormalised; returns x. The
        collective belief weighs by every robot's observation in turn (Eq. 7)."""
        l_in, l_out = (self._in1, self._out1) if z else (self._in0, self._out0)
        d = p if self._node_detection else self._didx[self._dptr[p] : self._dptr[p + 1]]
        keep = x[d] * l_in
        x *= l_out
        x[d] = keep
        return x

    def _observe(self, prior: np.ndarray, p: int, z: int) -> np.ndarray:
        """prior (n,) -> Lambda(p, z) prior, normalised (Eq. 1-2); the array is reused."""
        total = self.weigh(prior, p, z).sum()
        if total > TINY:
            prior /= total
            return prior
        # vanished mass: restart from the observation alone, then from uniform (module docstring)
        self.restarts += 1
        prior[:] = 1.0
        total = self.weigh(prior, p, z).sum()
        if total > TINY:
            prior /= total
        else:
            prior[:] = 1.0 / self.n
        return prior

    def reset(self, p0: int, z0: int) -> np.ndarray:
        """b_0 ∝ Lambda(p_0, z_0) b0 (the t = 0 case of Theorem 1)."""
        self.belief = self._observe(self._b0.copy(), p0, z0)
        return self.belief

    def predict(self) -> np.ndarray:
        """Gamma_hat^T b of this robot's belief b."""
        return self.predict_of(self.belief)

    def predict_of(self, b: np.ndarray) -> np.ndarray:
        """Gamma_hat^T b: (Gamma^T b)(v) = sum_u Gamma(u, v) b(u); O(nnz) = O(n + m)."""
        return np.bincount(self._dst, weights=self._prob * b[self._src], minlength=self.n)

    def update(self, p: int, z: int, ticks: int = 1) -> np.ndarray:
        """Theorem 1, Eq. 1: b_t ∝ Lambda(p_t, z_t) Gamma_hat^T b_{t-1}; with ``ticks`` k > 1 (a model
        per tick, a reading k ticks after the last) the prediction is made k times, (Gamma_hat^T)^k b."""
        prior = self.belief
        for _ in range(max(1, ticks)):
            prior = self.predict_of(prior)
        self.belief = self._observe(prior, p, z)
        return self.belief

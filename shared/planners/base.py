"""The methods the paper compares CE-PG with (section V), as batched searchers for the evaluator.

This module holds what they share (the collective belief with the true model; FHPE-SA's walks and the
discount are in shared/core/fhpe_sa.py, which a robot agent runs too);
each planner has its own module: fhpe.py (fhpe, fhpe-sa), milp.py (milp, d-milp), oracle.py.

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
  objective the discounted captured mass, horizon h = 5, solved by HiGHS (highspy) with a
  per-solve time limit. The model is built once per episode and team size and only re-bounded
  per decision; each solve starts from a feasible incumbent (the last plan shifted by the step
  taken, or a one-step sequential greedy move), which is what remains if the limit is hit first.
- ``d-milp``: the distributed variant: robots solve one after another, each with the plans of
  the robots before it fixed.
- ``oracle``: robots that always know where the target is, acting on the dynamic-programming
  optimum for N = 1 and N = 2 (``oracle_expected_time`` gives the exact expectation with the
  T_max cut). Its capture time is a lower bound for every method that does not see the target.
  Not computed for N > 2 (the state space is n^(N+1)).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.engine.batched_belief import BatchedBelief, BeliefTracker
from shared.engine.sim import Obs


class Planner:
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
        b_t, _ = self.tracker.update(lik, obs.new)  # Eq. 6 with the true Gamma, (B, 1, n)
        b = b_t[:, 0].numpy()
        pos = obs.pos.numpy()
        act = pos.copy()
        for e in np.nonzero(obs.alive.numpy())[0]:
            active = obs.active[e].numpy()
            act[e] = self.plan(b[e], pos[e], active)
            self.decisions += 1
        return torch.as_tensor(act)

    def plan(self, b: np.ndarray, pos: np.ndarray, active: np.ndarray) -> np.ndarray:
        raise NotImplementedError

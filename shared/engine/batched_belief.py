"""Batched beliefs in torch (docs/SPEC.md section 2), for the simulator, evaluator and trainer.

Beliefs are row vectors of shape (..., n) (B episodes, N robots, n nodes); the prediction
Gamma_hat^T b is ``b @ Gamma``. The same algebra as the agent's numpy ``BeliefFilter``
(shared/core/belief_filter.py), with the same vanishing-mass rule; tests/test_belief.py checks that the
two agree with each other and with brute-force Bayes.

Two representations, the same algebra. Up to ``SPARSE_FROM_NODES`` nodes Gamma_hat is a dense
(n, n) matrix and Lambda a (2, n, n) table (one BLAS call, one gather: fastest on small maps, and
every recorded figure was made with them). Above, both are kept on Gamma_hat's support and the
detection sets: the prediction is a scatter-add over Gamma_hat's nnz = n + 2m entries and Lambda
a scatter into D(p), so memory and time grow with the building's rooms and doors, O(n + m) per
belief, not O(n^2).
"""

from __future__ import annotations

import numpy as np
import torch

from shared.core.belief_filter import TINY
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel, from_matrix

SPARSE_FROM_NODES = 512  # above this many nodes Gamma_hat and Lambda are kept sparse (module docstring)
_GATHER_ELEMENTS = 1 << 24  # a sparse prediction gathers at most this many entries at once (64 MB in float32)


class BatchedBelief:
    """Batched belief algebra in torch; beliefs are row vectors of shape (..., n). ``sparse``:
    None chooses by the map's size (``SPARSE_FROM_NODES``)."""

    gamma: torch.Tensor | None  # (n, n) dense Gamma_hat, or None when sparse

    def __init__(
        self,
        graph: Graph,
        model: TargetModel,
        sensor: Sensor,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        sparse: bool | None = None,
    ) -> None:
        self.n = graph.n
        self.device = torch.device(device)
        self.dtype = dtype
        self.sparse = graph.n > SPARSE_FROM_NODES if sparse is None else sparse
        (in0, in1), (out0, out1) = sensor.likelihoods()
        self.lik_in = torch.tensor([in0, in1], dtype=dtype, device=self.device)  # indexed by z
        self.lik_out = torch.tensor([out0, out1], dtype=dtype, device=self.device)
        if self.sparse:
            # D(p) as an (n, d) table, each row padded with its first member (a repeat writes the same value)
            self.dsets = torch.as_tensor(graph.detection_table(sensor.detection), device=self.device)  # (n, d)
        else:
            detect = torch.as_tensor(graph.detection_matrix(sensor.detection), device=self.device)  # [p, j]: j in D(p)
            # [z, p, j]: Lambda's diagonal entry j for a robot at p seeing z, one gather per update
            self.lik_table = torch.where(detect, self.lik_in.view(2, 1, 1), self.lik_out.view(2, 1, 1))  # (2, n, n)
        self.set_model(model)

    def set_model(self, model: TargetModel) -> None:
        """Use (Gamma_hat, b0) of ``model`` from now on."""
        self.b0 = torch.as_tensor(model.b0, dtype=self.dtype, device=self.device)  # (n,)
        if self.sparse:  # Gamma_hat's support: (Gamma^T b)(v) = sum over entries u -> v of Gamma(u, v) b(u)
            self.gamma = None
            self.src = torch.as_tensor(model.src, device=self.device)
            self.dst = torch.as_tensor(model.dst, device=self.device)
            self.prob = torch.as_tensor(model.prob, dtype=self.dtype, device=self.device)
        else:
            self.gamma = torch.as_tensor(model.dense(), dtype=self.dtype, device=self.device)  # (n, n)

    def dense_gamma(self) -> torch.Tensor:
        """The dense (n, n) Gamma_hat (a ValueError for sparse beliefs): what needs the matrix itself."""
        if self.gamma is None:
            raise ValueError(f"beliefs on {self.n} nodes are sparse: there is no dense Gamma_hat")
        return self.gamma

    def model(self, graph: Graph, kind: str) -> TargetModel:
        """The current (Gamma_hat, b0) as a TargetModel, rows and b0 renormalised in float64."""
        b0 = self.b0.double().cpu().numpy()
        if self.gamma is not None:
            g = self.gamma.double().cpu().numpy()
            return from_matrix(graph, g / g.sum(1, keepdims=True), b0 / b0.sum(), kind=kind)
        src, dst, prob = self.src.cpu().numpy(), self.dst.cpu().numpy(), self.prob.double().cpu().numpy()
        prob = prob / np.bincount(src, weights=prob, minlength=self.n)[src]
        return TargetModel(self.n, src, dst, prob, b0 / b0.sum(), kind)

    def likelihood(self, pos: torch.Tensor, z: torch.Tensor, read: torch.Tensor | None = None) -> torch.Tensor:
        """Diagonal of Lambda (Eq. 2) for robots at ``pos`` seeing ``z``: (...,) -> (..., n).
        ``read`` (...,) bool: where False the robot made no reading (in transit), Lambda = I."""
        zb = z if z.dtype == torch.bool else z != 0
        if self.sparse:  # P(z | outside) everywhere, P(z | inside) scattered into D(p)
            lik = self.lik_out[zb.long()].unsqueeze(-1).expand(*pos.shape, self.n).contiguous()
            inside = self.lik_in[zb.long()].unsqueeze(-1).expand(*pos.shape, self.dsets.shape[1])
            lik.scatter_(-1, self.dsets[pos], inside)
        else:
            # one row gather from the (2n, n) view: row z n + p (index_select is cheaper than a 2-D index)
            rows = torch.where(zb, pos + self.n, pos).reshape(-1)
            lik = self.lik_table.view(2 * self.n, self.n).index_select(0, rows).view(*pos.shape, self.n)
        return lik if read is None else torch.where(read.unsqueeze(-1), lik, torch.ones_like(lik))

    def collective_likelihood(
        self, pos: torch.Tensor, z: torch.Tensor, active: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Diagonal of Lambda_c (Eq. 7): product over robots. (B, N) -> (B, n).

        Robots with ``active`` False (withdrawn) contribute no observation.
        """
        lik = self.likelihood(pos, z)  # (B, N, n)
        if active is not None:
            lik = torch.where(active.unsqueeze(-1), lik, torch.ones_like(lik))
        return lik.prod(dim=-2)

    def predict(self, b: torch.Tensor) -> torch.Tensor:
        """Gamma_hat^T b for each belief row: (..., n) -> (..., n)."""
        if self.gamma is not None:
            return b @ self.gamma
        flat = b.reshape(-1, self.n)
        out = torch.zeros_like(flat)
        rows = max(1, _GATHER_ELEMENTS // max(1, len(self.src)))
        for a in range(0, flat.shape[0], rows):  # O(rows nnz) memory a chunk
            out[a : a + rows].index_add_(1, self.dst, flat[a : a + rows, self.src] * self.prob)
        return out.view(b.shape)

    @staticmethod
    def normalise(x: torch.Tensor, lik: torch.Tensor) -> torch.Tensor:
        """x / sum(x), restarting from ``lik`` (then uniform) where the mass vanished."""
        total = x.sum(-1, keepdim=True)
        ok = total > TINY
        if bool(ok.all()):
            return x / total
        fallback_total = lik.sum(-1, keepdim=True)
        fallback = torch.where(
            fallback_total > TINY, lik / fallback_total.clamp_min(TINY), torch.full_like(lik, 1.0 / lik.shape[-1])
        )
        return torch.where(ok, x / total.clamp_min(TINY), fallback)

    def initial(self, lik: torch.Tensor) -> torch.Tensor:
        """b_0 ∝ Lambda_0 b0 (Theorem 1 at t = 0; Theorem 2 / Eq. 4 with a collective lik)."""
        return self.normalise(lik * self.b0, lik)

    def update(self, b: torch.Tensor, lik: torch.Tensor) -> torch.Tensor:
        """Eq. 1 / Eq. 6: b_t ∝ Lambda Gamma_hat^T b_{t-1}; lik is Lambda's diagonal (..., n)."""
        return self.normalise(lik * self.predict(b), lik)


class BeliefTracker:
    """Each robot's belief across a batch of episodes (Eq. 1, or Eq. 6 with a collective lik):
    b_t ∝ Lambda_t Gamma^T b_{t-1}, restarting from b0 in slots whose episode just began.
    Reuses the prediction Gamma^T b made at the previous decision."""

    def __init__(self, belief: BatchedBelief) -> None:
        self.belief = belief
        self._pred: torch.Tensor | None = None  # Gamma^T b_t from the last update, (B, N, n)

    def update(self, lik: torch.Tensor, new: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """lik (B, N, n), new (B,) -> (b_t, Gamma^T b_t), both (B, N, n)."""
        bel = self.belief
        b0 = bel.b0.expand_as(lik)
        if self._pred is None or self._pred.shape != lik.shape:
            prior = b0
        else:
            prior = torch.where(new.view(-1, 1, 1), b0, self._pred)
        b = bel.normalise(lik * prior, lik)
        self._pred = bel.predict(b)
        return b, self._pred

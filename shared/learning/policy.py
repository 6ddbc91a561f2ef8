"""Per-robot policy networks (docs/SPEC.md section 3), evaluated for the whole team at once.

Robot i's state is s = (onehot(p), b) in R^{2n}; its policy is an MLP 2n -> 2n -> n whose
logits are masked to N[p] before the softmax. One network per robot (theta_i): the N networks'
weights are stacked along a leading robot dimension so that a single batched matmul evaluates
every robot, and ``cross_logits`` evaluates every network on every robot's states (what the
cross-entropy term of Eq. 9 needs).

Shapes: N robots, n nodes, H = 2n hidden units; states are given as positions (..., N) and
beliefs (..., N, n) and never materialised as one-hot vectors (the one-hot half of the first
layer is a row gather).
"""

from __future__ import annotations

import functools
import math

import torch
from torch import nn

NEG_INF = -1e9


def _refresh_blocked(module: TeamPolicy, _incompatible_keys: object) -> None:
    """After load_state_dict: ``blocked`` follows the loaded ``mask`` (a hook must return None)."""
    module.blocked.copy_(~module.mask)


class TeamPolicy(nn.Module):
    """N independent MLPs 2n -> 2n -> n with masked softmax, stacked for batched evaluation."""

    mask: torch.Tensor  # (n, n) bool buffer: mask[p, a] = a in N[p]
    blocked: torch.Tensor  # (n, n) bool buffer: ~mask (not saved)
    row0: torch.Tensor  # (N,) long buffer i n: robot i's first row in w_pos viewed (N n, H) (not saved)

    def __init__(self, n: int, n_robots: int, nbr_mask: torch.Tensor, hidden: int | None = None) -> None:
        super().__init__()
        H = hidden or 2 * n
        self.n, self.N, self.H = n, n_robots, H
        if nbr_mask.shape != (n, n):
            raise ValueError(f"expected an (n, n) = ({n}, {n}) neighbourhood mask, got {tuple(nbr_mask.shape)}")
        self.register_buffer("mask", nbr_mask.bool())  # (n, n): mask[p, a] = a in N[p]
        self.register_buffer("blocked", ~nbr_mask.bool(), persistent=False)  # (n, n): a not in N[p]
        self.register_load_state_dict_post_hook(_refresh_blocked)
        self.register_buffer("row0", torch.arange(n_robots) * n, persistent=False)  # (N,): robot i's first row i n
        k1, k2 = 1 / math.sqrt(2 * n), 1 / math.sqrt(H)
        # layer 1 split into its one-hot(p) half (a gather) and its belief half (a matmul)
        self.w_pos = nn.Parameter(torch.empty(n_robots, n, H).uniform_(-k1, k1))  # (N, n, H)
        self.w_bel = nn.Parameter(torch.empty(n_robots, n, H).uniform_(-k1, k1))  # (N, n, H)
        self.b1 = nn.Parameter(torch.empty(n_robots, H).uniform_(-k1, k1))  # (N, H)
        self.w2 = nn.Parameter(torch.empty(n_robots, H, n).uniform_(-k2, k2))  # (N, H, n)
        self.b2 = nn.Parameter(torch.empty(n_robots, n).uniform_(-k2, k2))  # (N, n)

    def logits(self, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """Each robot's own network on its own state: pos (B, N), belief (B, N, n) -> (B, N, n).

        Entries outside N[p] are NEG_INF.
        """
        # robot-major batched matmuls, the biases added by baddbmm: (N, B, n) @ (N, n, H) + (N, 1, H)
        # (the rollout's hottest call: 18 % faster than the equivalent einsums at B = 256, 38 % at B = 16)
        h = torch.baddbmm(self.b1.unsqueeze(1), belief.transpose(0, 1), self.w_bel).transpose(0, 1)
        # the one-hot half: row (i n + p_i) of w_pos viewed (N n, H), one index_select
        h = h + self.w_pos.view(self.N * self.n, self.H).index_select(0, (pos + self.row0).reshape(-1)).view_as(h)
        out = torch.baddbmm(self.b2.unsqueeze(1), torch.relu(h).transpose(0, 1), self.w2).transpose(0, 1)
        return out.masked_fill(self.blocked[pos], NEG_INF)

    def logits_for(self, nets: torch.Tensor, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """Robot k runs network nets[k] (k robots, any k): pos (B, k), belief (B, k, n) -> (B, k, n)."""
        h = self.w_pos[nets, pos] + torch.einsum("bki,kih->bkh", belief, self.w_bel[nets]) + self.b1[nets]
        out = torch.einsum("bkh,kha->bka", torch.relu(h), self.w2[nets]) + self.b2[nets]
        return out.masked_fill(~self.mask[pos], NEG_INF)

    def cross_logits(self, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """Every network j on every robot i's state: pos (B, N), belief (B, N, n) -> (B, N_i, N_j, n)."""
        B, N, n = belief.shape
        # layer 1's belief half for every (state i, network j) pair as one GEMM: (B N_i, n) @ (n, N_j H)
        hb = (belief.reshape(B * N, n) @ self.w_bel.permute(1, 0, 2).reshape(n, N * self.H)).view(B, N, N, self.H)
        h = torch.relu(hb + self.w_pos[:, pos].permute(1, 2, 0, 3) + self.b1)  # (B, N_i, N_j, H)
        out = torch.einsum("bsnh,nha->bsna", h, self.w2) + self.b2
        return out.masked_fill(~self.mask[pos].unsqueeze(2), NEG_INF)

    @torch.no_grad()
    def cross_probs(self, pos: torch.Tensor, belief: torch.Tensor, chunk: int = 1024) -> torch.Tensor:
        """softmax of ``cross_logits``, without gradient, computed in chunks of states that stay
        in cache: (B, N) , (B, N, n) -> (B, N_i, N_j, n)."""
        out = torch.empty(pos.shape[0], self.N, self.N, self.n, dtype=belief.dtype, device=belief.device)
        for a in range(0, pos.shape[0], chunk):
            out[a : a + chunk] = torch.softmax(self.cross_logits(pos[a : a + chunk], belief[a : a + chunk]), dim=-1)
        return out

    # The action space of the CE-PG rollout and loss (shared/learning/cepg.py): slots of a row of
    # scores. A per-map team scores every node, so its slots are the n nodes themselves.
    def slot_logits(self, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """``logits``: (S, N) , (S, N, n) -> (S, N, n)."""
        return self.logits(pos, belief)

    def slot_allowed(self, pos: torch.Tensor) -> torch.Tensor:
        """The slots robot on ``pos`` (...) may take: (..., n) bool, a in N[p]."""
        return self.mask[pos]

    def slot_nodes(self, pos: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
        """The node rows of the slots chosen at ``pos``: the slots themselves."""
        return slot

    def log_probs(self, pos: torch.Tensor, belief: torch.Tensor) -> torch.Tensor:
        """log pi_i(. | s^i): (B, N, n), -inf-like outside N[p]."""
        return torch.log_softmax(self.logits(pos, belief), dim=-1)


def sample(probs: torch.Tensor, gen: torch.Generator | None, u: torch.Tensor | None = None) -> torch.Tensor:
    """One draw per row of ``probs`` (..., n) by inverting the CDF: (...,) long.

    Same distribution as torch.multinomial, several times faster for many small rows. Entries
    with probability 0 are never drawn: ``<=`` steps over leading zeros when u = 0, and the
    index is capped at the row's last positive entry when rounding puts u * total at the top.
    ``u`` (..., 1) in [0, 1) replaces the random draw (tests).
    """
    if u is None:
        u = torch.rand((*probs.shape[:-1], 1), generator=gen, device=probs.device, dtype=probs.dtype)
    cdf = probs.cumsum(-1)
    idx = (cdf <= u * cdf[..., -1:]).sum(-1)
    last = ((probs > 0) * _ranks(probs.shape[-1], probs.device)).argmax(-1)
    return torch.minimum(idx, last)


@functools.cache
def _ranks(n: int, device: torch.device) -> torch.Tensor:
    """1, 2, ..., n (``sample``'s tie-break toward the last positive entry), made once per size."""
    return torch.arange(1, n + 1, device=device)

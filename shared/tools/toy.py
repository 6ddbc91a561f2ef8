"""The paper's toy scenario (Fig. 4, docs/SPEC.md section 3), trained with the same CE-PG loss.

Two robots wait at a depot; the target waits at its spot. In one step every robot goes to A or
to B and the target goes to A with probability ``p_a`` (0.6), else to B. The team's reward is 1
if any robot meets the target, else 0 (``reward="team"``, docs/SPEC.md section 3); with ``reward="own"``
each robot is rewarded only for its own meeting (the paper's t_cap^(i), robot i's capture).
Each robot has its own network (the MLP of docs/SPEC.md section 3
on a 4-node graph: depot, spot, A, B) whose only allowed actions at the depot are A and B, and
its state is (onehot(depot), b) with b the point mass on the target's spot.

With beta = 0.5 the cross-entropy term pushes the two policies apart and they split (one to A,
one to B: reward 1 every time). With beta = 1 (vanilla PG) and own rewards both go to A, the
likelier node, as in the paper's Fig. 4(c). With beta = 1 and the team's reward, (0.6, 0.6) is a
saddle of the team's return (dJ/dp_2 = 0.6 - p_1): both first drift toward A, and the split
comes only when gradient noise breaks the symmetry, later than with the cross entropy (measured
in tests/test_train.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from shared.learning.cepg import Rollout, cepg_loss
from shared.learning.policy import TeamPolicy, sample

DEPOT, SPOT, A, B = 0, 1, 2, 3


@dataclass
class ToyRun:
    p_a: list[list[float]]  # per update, each robot's probability of going to A
    reward: list[float]  # per update, the batch's mean team reward


def toy_fig4(
    beta: float,
    seed: int = 0,
    updates: int = 300,
    batch: int = 64,
    lr: float = 1e-2,
    eps: float = 0.1,
    p_a: float = 0.6,
    reward: str = "team",
) -> ToyRun:
    """Train the two-robot toy team; returns the learning curves (paper Fig. 4(b), (c))."""
    if reward not in ("team", "own"):
        raise ValueError(f"reward must be 'team' or 'own', got {reward!r}")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tensors of a few dozen numbers: more threads only add overhead
    try:
        return _train_toy(beta, seed, updates, batch, lr, eps, p_a, reward)
    finally:
        torch.set_num_threads(threads)


def _train_toy(
    beta: float, seed: int, updates: int, batch: int, lr: float, eps: float, p_a: float, reward: str
) -> ToyRun:
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed + 1)
    mask = torch.eye(4, dtype=torch.bool)
    mask[DEPOT] = torch.tensor([False, False, True, True])  # at the depot: go to A or to B
    policy = TeamPolicy(4, 2, mask)
    opt = torch.optim.Adam(policy.parameters(), lr=lr)
    pos = torch.full((batch, 2), DEPOT)
    belief = torch.zeros(batch, 2, 4)
    belief[:, :, SPOT] = 1.0
    betas = torch.full((2,), beta)
    run = ToyRun([], [])
    for _ in range(updates):
        with torch.no_grad():
            probs = torch.softmax(policy.logits(pos, belief), dim=-1)  # (batch, 2, 4)
            action = sample(probs, gen)  # (batch, 2)
            target = torch.where(torch.rand(batch, generator=gen) < p_a, A, B)
            met = action == target.unsqueeze(1)  # (batch, 2)
            ret = met.any(1, keepdim=True).float().expand(-1, 2) if reward == "team" else met.float()
        ro = Rollout(
            pos=pos,
            belief=belief,
            action=action,
            t=torch.zeros(batch, dtype=torch.long),
            episode=torch.arange(batch),
            ret=ret,
            length=torch.ones(batch, dtype=torch.long),
            capture_time=torch.ones(batch, dtype=torch.long),
            censored=~met.any(1),
        )
        terms = cepg_loss(policy, ro, betas, eps)
        opt.zero_grad()
        terms.loss.backward()
        opt.step()
        run.p_a.append(probs[0, :, A].tolist())
        run.reward.append(float(met.any(1).float().mean()))
    with torch.no_grad():
        run.p_a.append(torch.softmax(policy.logits(pos[:1], belief[:1]), dim=-1)[0, :, A].tolist())
    return run

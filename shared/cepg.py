"""CE-PG: cross-entropy regularized policy gradient (paper section IV-C, Eq. 9-13). WORK IN PROGRESS:
the update and the rollout are here; snapshots, `mures train`, the EM loop of Algorithm 2 and
scale-out training are not yet (see the trainer issue).

For robot i (Eq. 9), maximised:

    J~(theta_i) = beta_i J(pi_i) + (1 - beta_i)/(N - 1) sum_{j != i} H(pi_j, pi_i)
    H(pi_j, pi_i) = -(1/T_i) sum_t sum_{a in N[p_t]} pi_j(a | s_t^i) log pi_i(a | s_t^i)

Well-behaved cross entropy. H is unbounded above in theta_i: maximising it drives log pi_i to
-inf on the actions pi_j favours. We evaluate it against the epsilon-smoothed policy
pi~_i = (1 - eps) pi_i + eps U(N[p]) (U uniform over the closed neighbourhood), which bounds
H by log(|N[p]| / eps) and equals Eq. 9 as eps -> 0; ``eps`` is a training option.

Scales. Both terms are per-step averages: J's gradient (Eq. 11) uses advantages G_t - b_t
(b_t the batch mean return at step t, a baseline that leaves the gradient unbiased) normalised
by their batch standard deviation, so that beta trades two quantities of order 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from shared.belief import BatchedBelief
from shared.policy import TeamPolicy
from shared.sim import SearchSim


@dataclass
class Rollout:
    """Every decision of B complete episodes, flattened over (episode, t): S steps in all.

    pos (S, N), belief (S, N, n), action (S, N), t (S,), episode (S,); capture_time (B,).
    """

    pos: torch.Tensor
    belief: torch.Tensor
    action: torch.Tensor
    t: torch.Tensor
    episode: torch.Tensor
    capture_time: torch.Tensor
    censored: torch.Tensor


@torch.no_grad()
def rollout(
    sim: SearchSim, policy: TeamPolicy, belief: BatchedBelief, collective: bool, gen: torch.Generator
) -> Rollout:
    """Run sim.B episodes to the end with the team's stochastic policies (Algorithm 1 per robot).

    Only running episodes are evaluated each step (work proportional to the steps taken).
    ``collective``: every robot uses the collective belief (C-CE-PG).
    """
    B, N = sim.B, sim.N

    def lik(pos: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """Lambda's diagonal per robot (B', N, n): own (Eq. 2) or collective (Eq. 7)."""
        if collective:
            return belief.collective_likelihood(pos, z).unsqueeze(1).expand(-1, N, -1)
        return belief.likelihood(pos, z)

    obs = sim.reset()
    b = belief.initial(lik(obs.pos, obs.z))
    logs: dict[str, list[torch.Tensor]] = {k: [] for k in ("pos", "belief", "action", "t", "episode")}
    capture_time = torch.zeros(B, dtype=torch.long, device=sim.device)
    censored = torch.zeros(B, dtype=torch.bool, device=sim.device)
    while sim.any_alive:
        idx = (sim.alive & ~sim.pending).nonzero().squeeze(1)
        pos_a, bel_a = obs.pos[idx], b[idx]
        probs = torch.softmax(policy.logits(pos_a, bel_a), dim=-1)
        act = torch.multinomial(probs.reshape(-1, probs.shape[-1]), 1, generator=gen).view(-1, N)
        actions = obs.pos.clone()
        actions[idx] = act
        for k, v in (("pos", pos_a), ("belief", bel_a), ("action", act), ("t", obs.t[idx]), ("episode", idx)):
            logs[k].append(v)
        obs, res = sim.step(actions)
        capture_time = torch.where(res.done, res.capture_time, capture_time)
        censored = torch.where(res.done, res.censored, censored)
        b[idx] = belief.update(bel_a, lik(obs.pos[idx], obs.z[idx]))
    return Rollout(*(torch.cat(logs[k]) for k in ("pos", "belief", "action", "t", "episode")), capture_time, censored)


@dataclass
class LossTerms:
    loss: torch.Tensor
    pg: torch.Tensor  # (N,) surrogate of J per robot
    ce: torch.Tensor  # (N,) mean over j != i of H(pi_j, pi~_i)


def cepg_loss(policy: TeamPolicy, ro: Rollout, beta: torch.Tensor, eps: float) -> LossTerms:
    """-J~ summed over robots (each theta_i gets only its own gradient, Eq. 10)."""
    N = policy.N
    S = ro.t.shape[0]
    # returns and baseline: reward -1 per step until capture, so G_t = -(t_cap - t)
    G = -(ro.capture_time[ro.episode] - ro.t).to(torch.float32)  # (S,)
    T1 = int(ro.t.max()) + 1
    sums = torch.zeros(T1, device=G.device).index_add_(0, ro.t, G)
    cnts = torch.zeros(T1, device=G.device).index_add_(0, ro.t, torch.ones_like(G))
    adv = G - (sums / cnts)[ro.t]
    adv = adv / (adv.std() + 1e-8)
    # every network on every robot's states: (S, N_i, N_j, n)
    logp = torch.log_softmax(policy.cross_logits(ro.pos, ro.belief), dim=-1)
    robot = torch.arange(N, device=G.device)
    own = logp[:, robot, robot]  # (S, N, n): log pi_i(. | s^i)
    # Eq. 11: sum_t grad log pi_i(a_t | s_t) (G_t - b_t), averaged per step
    logp_a = own.gather(2, ro.action.unsqueeze(2)).squeeze(2)  # (S, N)
    pg = (logp_a * adv.unsqueeze(1)).mean(0)  # (N,)
    # Eq. 12 with the eps-smoothed pi~_i (module docstring); pi_j is a constant for theta_i
    mask = policy.mask[ro.pos]  # (S, N, n)
    uniform = mask / mask.sum(-1, keepdim=True)
    smooth = torch.where(mask, (1 - eps) * own.exp() + eps * uniform, 1.0)  # 1 outside N[p]: log = 0, no NaN grads
    log_smooth = torch.log(smooth)  # (S, N, n)
    pi_j = logp.exp().detach()  # (S, N_i, N_j, n)
    h = -(pi_j * log_smooth.unsqueeze(2)).sum(-1)  # (S, N_i, N_j): H(pi_j, pi~_i) per state
    off = ~torch.eye(N, dtype=torch.bool, device=G.device)
    ce = (h * off).sum(-1).sum(0) / (S * max(N - 1, 1))  # (N,); 0 for a single robot
    objective = beta * pg + (1 - beta) * ce  # Eq. 9 per robot
    return LossTerms(loss=-objective.sum(), pg=pg.detach(), ce=ce.detach())

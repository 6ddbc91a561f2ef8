"""CE-PG: cross-entropy regularized policy gradient (paper section IV-C, Eq. 9-13): the batched
rollout of a team's stochastic policies and the loss whose gradient is the CE-PG update. The
training loop (Algorithm 2) is in shared/learning/train.py.

For robot i (Eq. 9), maximised:

    J~(theta_i) = beta_i J(pi_i) + (1 - beta_i)/(N - 1) sum_{j != i} H(pi_j, pi_i)
    H(pi_j, pi_i) = -(1/T_i) sum_t sum_{a in N[p_t]} pi_j(a | s_t^i) log pi_i(a | s_t^i)

Units. Both terms keep the units Eq. 9 gives them: J is the expected return in steps (-E[t_cap]
for the search task) and its gradient is Eq. 11 summed over an episode's steps; H is in nats,
averaged over the episode's own steps. So beta trades steps of capture time against nats of
disagreement, as in the paper. Measured (OFFICE, N = 4): normalising the advantages to unit
variance instead makes H dominate at beta = 0.5 and the team capture later (26 -> 57 steps).

Well-behaved cross entropy. H is unbounded above in theta_i: maximising it drives log pi_i to
-inf on the actions pi_j favours. We evaluate it against the epsilon-smoothed policy
pi~_i = (1 - eps) pi_i + eps U(N[p]) (U uniform over the allowed actions), which bounds H by
log(|N[p]| / eps) and equals Eq. 9 as eps -> 0. ``eps`` is a training option (default 0.1).

States H is evaluated on (``ce_states``). The paper motivates the cross entropy by robots that hold
exactly the same PTB information and should still decide differently (Section IV-C, Fig. 4). With
``"shared"`` (the default) the term for the pair (i, j) counts only at robot i's states where robot j,
at the same step of the same episode, stands on the same node with the same belief (total variation
< ``same_tol``); ``"all"`` counts it at every state robot i visits, as Eq. 12 is written. Measured
(OFFICE, N = 4, EM beliefs, 10^5 episodes, seeds 0-5, 1500 evaluation episodes each; paired
difference PG - CE-PG, mean and t-based 95% CI over the 6 seeds): ``"all"`` -0.88 +- 0.63 steps
(beta = 0.5 loses to PG in every seed: pushing robot i away from robot j's choice at every state
also pushes it off good moves both should make), ``"shared"`` -0.16 +- 0.39 (not separated from PG).
Neither beats PG there (docs/cepg.md).

Shapes: S decisions in a rollout (episode-major), N robots, n nodes, B episodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from shared.engine.batched_belief import BatchedBelief
from shared.engine.sim import SearchSim
from shared.learning.policy import TeamPolicy, sample


@dataclass
class Rollout:
    """Every decision of B complete episodes, flattened over (episode, t): S decisions in all.

    pos (S, N), belief (S, N, n), action (S, N) the slot each robot chose in its policy's action space
    of A slots (``slot_logits``: the node itself for a per-map team, A = n; a slot of N[p] for the
    general policy, A = max |N[p]|), t (S,), episode (S,) index into the B episodes,
    ret (S,) the team's return from t on, or (S, N) one per robot; length (B,) decisions per episode (T_i of Eq. 12);
    capture_time (B,), censored (B,). With travel times t counts ticks and a row is a tick at which
    some robot of the episode stands on a node: ``decided`` (S, N) marks the robots that decide
    there, and ``decisions`` (B, N) counts each robot's decisions in each episode, its T_i of Eq. 12
    (None: every robot decides at every row, the paper's model, and T_i is ``length``).
    """

    pos: torch.Tensor
    belief: torch.Tensor
    action: torch.Tensor
    t: torch.Tensor
    episode: torch.Tensor
    ret: torch.Tensor
    length: torch.Tensor
    capture_time: torch.Tensor
    censored: torch.Tensor
    decided: torch.Tensor | None = None
    decisions: torch.Tensor | None = None


@torch.no_grad()
def rollout(
    sim: SearchSim, policy: TeamPolicy, belief: BatchedBelief, collective: bool, gen: torch.Generator
) -> Rollout:
    """Run sim.B episodes to the end with the team's stochastic policies (Algorithm 1 per robot).

    Only running episodes are evaluated each step (work proportional to the steps taken).
    ``collective``: every robot uses the collective belief (C-CE-PG). With the simulator's travel
    times (``sim.timed``) every belief predicts once a tick and takes a robot's reading at the tick
    it arrives; only the robots on a node decide (``Rollout.decided``).
    """
    B, N = sim.B, sim.N
    if sim.auto_reset:
        raise ValueError("rollout runs its episodes to their end: the simulator must not restart them (auto_reset)")

    def lik(pos: torch.Tensor, z: torch.Tensor, read: torch.Tensor | None) -> torch.Tensor:
        """Lambda's diagonal per robot (B', N, n): own (Eq. 2) or collective (Eq. 7); ``read`` (B', N)
        marks the robots with a reading this tick (None: all)."""
        if collective:
            return belief.collective_likelihood(pos, z, read).unsqueeze(1).expand(-1, N, -1)
        return belief.likelihood(pos, z, read)

    obs = sim.reset()
    b = belief.initial(lik(obs.pos, obs.z, obs.ready))
    names = ("pos", "belief", "action", "t", "episode", "decided")
    logs: dict[str, list[torch.Tensor]] = {k: [] for k in names}
    censored = torch.zeros(B, dtype=torch.bool, device=sim.device)
    while True:
        idx = (sim.alive & ~sim.pending).nonzero().squeeze(1)  # the episodes that go on
        if idx.numel() == 0:  # every episode has ended (or was caught at t = 0, its capture time 0)
            break
        dec = idx if obs.ready is None else idx[obs.ready[idx].any(1)]  # those where some robot decides now
        pos_a, bel_a = obs.pos[dec], b[dec]
        slot = sample(torch.softmax(policy.slot_logits(pos_a, bel_a), dim=-1), gen)
        for k, v in (("pos", pos_a), ("belief", bel_a), ("action", slot), ("t", obs.t[dec]), ("episode", dec)):
            logs[k].append(v)
        if obs.ready is not None:
            logs["decided"].append(obs.ready[dec])
        act = policy.slot_nodes(pos_a, slot)  # (B', N) node rows
        obs, res = sim.step(obs.pos.index_put((dec,), act))  # the others stand still or travel on
        censored = censored | res.censored
        read = None if obs.ready is None else obs.ready[idx]
        b[idx] = belief.update(b[idx], lik(obs.pos[idx], obs.z[idx], read))
    # a finished episode's clock stops (the simulator does not restart it): t is its capture time
    capture_time = obs.t
    pos, bel, act, t, ep = (torch.cat(logs[k]) for k in names[:-1])
    decided = torch.cat(logs["decided"]) if logs["decided"] else None
    decisions = None if decided is None else torch.zeros(B, N, device=sim.device).index_add_(0, ep, decided.float())
    ret = -(capture_time[ep] - t).to(torch.float32)  # reward -1 per step (tick) until capture
    return Rollout(pos, bel, act, t, ep, ret, capture_time, capture_time, censored, decided, decisions)


@dataclass
class LossTerms:
    loss: torch.Tensor  # scalar: -sum_i J~(theta_i), minimised
    pg: torch.Tensor  # (N,) J's surrogate per robot (its gradient is Eq. 11)
    ce: torch.Tensor  # (N,) mean over j != i of H(pi_j, pi~_i), Eq. 12


def advantages(ro: Rollout, j_unit: float = 1.0) -> torch.Tensor:
    """Eq. 11's weights: the return G_t (in units of ``j_unit`` steps) minus the baseline b_t, the
    batch mean return of the episodes still running at step t (unbiased: it does not depend on the
    action taken at t). (S, 1) for the team's return, (S, N) for per-robot returns."""
    G = (ro.ret / j_unit).reshape(ro.t.shape[0], -1)  # (S, 1) team return, or (S, N) per robot
    T1 = int(ro.t.max()) + 1
    sums = torch.zeros(T1, G.shape[1], device=G.device).index_add_(0, ro.t, G)
    cnts = torch.zeros(T1, device=G.device).index_add_(0, ro.t, torch.ones_like(G[:, 0]))
    return G - (sums / cnts.unsqueeze(1))[ro.t]


def policy_gradient_term(log_pi: torch.Tensor, ro: Rollout, adv: torch.Tensor) -> torch.Tensor:
    """J(pi_i)'s surrogate per robot, (N,): sum over an episode's steps of log pi_i(a_t | s_t) times
    the advantage, averaged over the B episodes; its gradient is Eq. 11 (REINFORCE with a baseline).

    log_pi (S, N, A): each robot's own network on its own states, with gradient."""
    B = ro.length.shape[0]
    logp_a = log_pi.gather(2, ro.action.unsqueeze(2)).squeeze(2)  # (S, N): log pi_i(a_t | s_t)
    if ro.decided is not None:  # travel times: only the decisions robots made on a node
        logp_a = logp_a * ro.decided
    return (logp_a * adv).sum(0) / B


def cross_entropy_term(
    policy: TeamPolicy,
    ro: Rollout,
    log_pi: torch.Tensor,
    eps: float,
    ce_fraction: float = 1.0,
    gen: torch.Generator | None = None,
    ce_states: str = "shared",
    same_tol: float = 0.05,
) -> torch.Tensor:
    """Eq. 12 per robot, (N,): (1/(N-1)) sum_{j != i} H(pi_j, pi~_i), where
    H(pi_j, pi~_i) = -(1/T_i) sum_t sum_{a in N[p_t]} pi_j(a | s_t^i) log pi~_i(a | s_t^i),
    averaged over the B episodes.

    Where this departs from the letter of Eq. 12 (each choice measured: module docstring):
    - pi~_i = (1 - eps) pi_i + eps U(N[p]) replaces pi_i inside the log, which bounds H;
    - with ``ce_states="shared"`` the pair (i, j) counts only at states where robot j stands on
      robot i's node with the same belief (total variation < ``same_tol``) at the same step;
    - the expectation over a in N[p_t] is computed exactly, over every allowed action, rather
      than estimated from the action taken;
    - with ``ce_fraction`` < 1 it is estimated on that random share of the decisions, weighted by
      its inverse (unbiased): the N x N cross evaluation is most of the loss's cost.
    pi_j is a constant for theta_i (Eq. 10), so the cross evaluation runs without gradient.
    """
    N, B, S = policy.N, ro.length.shape[0], ro.t.shape[0]
    device = log_pi.device
    if ce_fraction < 1.0:
        k = max(1, round(ce_fraction * S))
        sub = torch.randperm(S, generator=gen, device=device)[:k]  # the decisions H is estimated on
        weight = S / k
    else:
        sub, weight = torch.arange(S, device=device), 1.0
    pos, bel = ro.pos[sub], ro.belief[sub]
    pairs = ~torch.eye(N, dtype=torch.bool, device=device).expand(sub.shape[0], N, N)  # (K, N_i, N_j): j != i
    decided = None if ro.decided is None else ro.decided[sub]  # (K, N): travel times, robot on a node
    if decided is not None:  # robot i's states are those where it decides
        pairs = pairs & decided.unsqueeze(2)
    if ce_states == "shared":  # only where robot j is in robot i's situation: same node, same belief
        tv = 0.5 * (bel.unsqueeze(2) - bel.unsqueeze(1)).abs().sum(-1)  # (K, N, N)
        pairs = pairs & (pos.unsqueeze(2) == pos.unsqueeze(1)) & (tv < same_tol)
        if decided is not None:  # and robot j decides there too (not in transit from that node)
            pairs = pairs & decided.unsqueeze(1)
        # H is needed only at the decisions where some pair counts (most have none): the same sum,
        # without evaluating N x N networks on states whose every term would be multiplied by 0
        keep = pairs.any(2).any(1).nonzero().squeeze(1)
        sub, pos, bel, pairs = sub[keep], pos[keep], bel[keep], pairs[keep]
    own_s = log_pi[sub]
    pi_j = policy.cross_probs(pos, bel)  # (K, N_i, N_j, A): network j on robot i's states
    mask = policy.slot_allowed(pos)  # (K, N, A): a in N[p]
    uniform = mask / mask.sum(-1, keepdim=True)
    smooth = torch.where(mask, (1 - eps) * own_s.exp() + eps * uniform, 1.0)  # pi~_i; 1 outside N[p]: log 0
    h = -(pi_j * torch.log(smooth).unsqueeze(2)).sum(-1)  # (K, N_i, N_j): H(pi_j, pi~_i) at each state
    h_i = (h * pairs).sum(-1) / max(N - 1, 1)  # (K, N): (1/(N-1)) sum_{j != i}; 0 for a single robot
    if ro.decisions is None:
        T_i = ro.length[ro.episode[sub]].clamp_min(1).to(torch.float32).unsqueeze(1)  # (K, 1): its episode's length
    else:  # travel times: (K, N) each robot's own decisions in the episode
        T_i = ro.decisions[ro.episode[sub]].clamp_min(1)
    return weight * (h_i / T_i).sum(0) / B  # the 1/T_i of Eq. 12, then the mean over episodes


def cepg_loss(
    policy: TeamPolicy,
    ro: Rollout,
    beta: torch.Tensor,
    eps: float,
    ce_fraction: float = 1.0,
    gen: torch.Generator | None = None,
    j_unit: float = 1.0,
    ce_states: str = "shared",
    same_tol: float = 0.05,
) -> LossTerms:
    """The CE-PG loss: -sum_i J~(theta_i) with Eq. 9 per robot,
    J~(theta_i) = beta_i J(pi_i) + (1 - beta_i) (1/(N-1)) sum_{j != i} H(pi_j, pi~_i).
    Each theta_i gets only its own gradient (Eq. 10): robot i's terms use its own network alone.

    Both terms keep their natural units over the rollout's B episodes: J in steps (the return is
    -t_cap), H in nats averaged over each episode's own steps (module docstring, "Units").
    beta (N,) holds beta_i.
    """
    log_pi = torch.log_softmax(policy.slot_logits(ro.pos, ro.belief), dim=-1)  # (S, N, A), with gradient
    pg = policy_gradient_term(log_pi, ro, advantages(ro, j_unit))  # J, Eq. 11
    ce = cross_entropy_term(policy, ro, log_pi, eps, ce_fraction, gen, ce_states, same_tol)  # H, Eq. 12
    objective = beta * pg + (1 - beta) * ce  # Eq. 9 per robot
    return LossTerms(loss=-objective.sum(), pg=pg.detach(), ce=ce.detach())

"""The per-robot policy networks and the CE-PG loss (Eq. 9-13)."""

import math

import torch

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.engine.batched_belief import BatchedBelief
from shared.engine.sim import SearchSim
from shared.learning.cepg import cepg_loss, rollout
from shared.learning.policy import TeamPolicy


def setup(N=3, B=32):
    g = builtin_graph("office")
    m, s = uniform_walk(g), Sensor(0.1, 0.0)
    torch.manual_seed(0)
    pol = TeamPolicy(g.n, N, torch.as_tensor(g.adjacency()))
    gen = torch.Generator().manual_seed(0)
    ro = rollout(SearchSim(g, m, s, N, B, seed=1, auto_reset=False), pol, BatchedBelief(g, m, s), False, gen)
    return g, pol, ro


def test_policy_is_masked_and_cross_matches_own():
    g, pol, ro = setup()
    lp = pol.log_probs(ro.pos, ro.belief)
    probs = lp.exp()
    mask = torch.as_tensor(g.adjacency())[ro.pos]
    assert torch.all(probs[~mask] < 1e-12) and torch.allclose(probs.sum(-1), torch.ones(()))
    cross = pol.cross_logits(ro.pos, ro.belief)
    r = torch.arange(pol.N)
    assert torch.allclose(cross[:, r, r], pol.logits(ro.pos, ro.belief), atol=1e-5)
    assert torch.all(mask.gather(2, ro.action.unsqueeze(2)))  # sampled actions stay in N[p]
    # one decision per step before capture; an episode captured at t = 0 has none
    per_episode = torch.bincount(ro.episode, minlength=32)
    assert torch.equal(per_episode, ro.capture_time) and ro.t.max() < 3 * g.n


def test_each_robot_gets_only_its_own_gradient_and_ce_is_bounded():
    g, pol, ro = setup()
    eps = 0.05
    terms = cepg_loss(pol, ro, torch.full((pol.N,), 0.5), eps)
    assert torch.isfinite(terms.loss)
    assert torch.all(terms.ce <= math.log(int(g.deg_closed.max()) / eps))
    pol.zero_grad()
    cepg_loss(pol, ro, torch.tensor([0.5, 0.0, 0.0]), eps).loss.backward()
    # with beta = 0 for robots 1, 2 their loss is pure CE; all grads finite, none NaN
    for p in pol.parameters():
        assert torch.all(torch.isfinite(p.grad))
    pol.zero_grad()
    lp = pol.log_probs(ro.pos, ro.belief)[:, 0]  # robot 0's own network only
    lp.gather(1, ro.action[:, :1]).sum().backward()
    assert pol.w2.grad[1:].abs().sum() == 0 and pol.w2.grad[0].abs().sum() > 0


def test_sample_never_draws_a_zero_probability_action():
    from shared.learning.policy import sample

    gen = torch.Generator().manual_seed(0)
    probs = torch.tensor([[0.0, 0.5, 0.0, 0.5, 0.0], [0.0, 0.0, 1.0, 0.0, 0.0]]).repeat(50_000, 1)
    draws = sample(probs, gen)
    assert torch.all(probs.gather(1, draws.unsqueeze(1)) > 0)
    assert abs(float((draws[::2] == 1).float().mean()) - 0.5) < 0.01
    # the extreme uniforms: u = 0 and u just below 1 (where u * total can round up to the total)
    rows = torch.tensor([[0.0, 0.3, 0.0, 0.7, 0.0], [0.0, 0.0, 1.0, 0.0, 0.0]])
    for u in (0.0, 1.0 - 2**-24, 1.0 - 2**-30):
        draws = sample(rows, None, torch.full((2, 1), u))
        assert torch.all(rows.gather(1, draws.unsqueeze(1)) > 0), (u, draws)


def test_rollout_reads_capture_and_censoring_from_the_simulator():
    """Episodes cut at T_max are censored with capture time T_max; the others were caught before
    or at T_max; a simulator that restarts finished episodes is refused."""
    import pytest

    g = builtin_graph("office")
    m, s = uniform_walk(g), Sensor()
    torch.manual_seed(0)
    pol = TeamPolicy(g.n, 2, torch.as_tensor(g.adjacency()))
    gen = torch.Generator().manual_seed(0)
    sim = SearchSim(g, m, s, 2, 64, seed=3, auto_reset=False, t_max=4)
    ro = rollout(sim, pol, BatchedBelief(g, m, s), False, gen)
    assert ro.censored.any() and (~ro.censored).any()
    assert torch.all(ro.capture_time[ro.censored] == 4) and torch.all(ro.capture_time <= 4)
    assert torch.equal(torch.bincount(ro.episode, minlength=64), ro.capture_time)
    with pytest.raises(ValueError, match="auto_reset"):
        rollout(SearchSim(g, m, s, 2, 8, seed=3), pol, BatchedBelief(g, m, s), False, gen)


def test_a_loaded_state_dict_brings_its_mask_and_the_blocked_moves_follow():
    g = builtin_graph("office")
    adj = torch.as_tensor(g.adjacency())
    src, dst = TeamPolicy(g.n, 2, adj), TeamPolicy(g.n, 2, torch.ones_like(adj))
    dst.load_state_dict(src.state_dict())  # a warm start: weights and the mask of src
    assert torch.equal(dst.blocked, ~adj.bool())
    pos, bel = torch.zeros(3, 2, dtype=torch.long), torch.full((3, 2, g.n), 1.0 / g.n)
    assert torch.equal(dst.logits(pos, bel), src.logits(pos, bel))

"""CE-PG training, Algorithm 2 of the paper (centralised training in simulation).

Each update simulates a batch of B complete episodes with the team's current stochastic policies
(shared/learning/cepg.py ``rollout``), takes one Adam step on the CE-PG loss (Eq. 9-13), and logs the
batch's capture times. The simulator moves the target with the *true* model; the robots' beliefs
use Gamma_hat and b0, which start at the paper's Gamma_hat_0 = I and uniform b0 (or a given
model) and are re-estimated during training by the engine's EM (shared/engine/estimate.py) from
episode records of missions flown with the current policies: robots' positions and
observations only, exactly what a real fleet reports. ``belief="true"`` lets the robots use the
true model instead (for comparison).

Per-robot learning rates (alpha_i of Eq. 13): Adam's step is linear in its learning rate, so the
optimiser steps with max(alpha) and each robot's change is scaled by alpha_i / max(alpha).

Scale-out: under torch.distributed (``torchrun``; gloo on CPU, nccl on GPU) each of W
processes simulates B / W episodes of every update, gradients are summed with all_reduce, and
every process takes the same step, so the replicas stay identical (checked at the end).
Rank 0 estimates the model and broadcasts it, and is the only one to write files.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from shared.core.clock import TravelTimes
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel, from_matrix, identity_model
from shared.engine.batched_belief import BatchedBelief
from shared.engine.estimate import collect_missions, em, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate
from shared.engine.sim import SearchSim
from shared.learning.cepg import cepg_loss, rollout
from shared.learning.config import TrainConfig
from shared.learning.policy import TeamPolicy
from shared.learning.team_snapshot import PolicySearcher, Snapshot


@dataclass
class TrainResult:
    policy: TeamPolicy
    model: TargetModel  # the robots' belief model at the end
    summary: dict[str, Any]
    interrupted: bool


def _world() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def leave_process_group(code: int) -> None:
    """End a data-parallel (torchrun) process with exit status ``code``; without a process group,
    return at once.

    A barrier once every rank is done (rank 0 has written the snapshot), so that no rank tears its
    connections down while another still works; then the group is destroyed and the process ends
    with ``os._exit`` after flushing its streams, skipping the interpreter's shutdown. That shutdown
    is where gloo aborted about one run in 35 of `mures train` under torchrun here ("terminate
    called without an active exception"; CI saw it twice): gloo's worker thread can still hold the
    barrier's work, which holds the last all-reduce's tensors, when the interpreter finalises;
    dropping them needs the GIL, a finalising interpreter ends the thread instead, and the
    destructor's unwinding aborts the process (gdb on a core: ProcessGroupGloo::runLoop ->
    ~AsyncBarrierWork -> ~AsyncAllreduceWork -> TensorImpl::decref_pyobject -> take_gil ->
    pthread_exit). Nothing of ours runs after this point, so nothing is lost by skipping it."""
    if not (dist.is_available() and dist.is_initialized()):
        return
    dist.barrier()
    dist.destroy_process_group()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _params_digest(policy: TeamPolicy) -> torch.Tensor:
    """A float64 checksum of the parameters, to compare replicas."""
    return torch.stack(
        [p.detach().double().sum() for p in policy.parameters()]
        + [(p.detach().double() ** 2).sum() for p in policy.parameters()]
    )


def train(
    graph: Graph,
    target: TargetModel,
    sensor: Sensor,
    cfg: TrainConfig,
    init_model: TargetModel | None = None,
    init_policy: Snapshot | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    should_stop: Callable[[], bool] | None = None,
    models_per_tick: bool = False,
) -> TrainResult:
    """Train a team (module docstring). ``target`` is the true model the simulator uses;
    ``init_model`` is Gamma_hat_0 (default I); ``init_policy`` warm-starts the networks.

    With ``cfg.speed`` the team trains on the mission clock (``clock_of``): moves take the graph's
    travel times, ``target`` and ``init_model`` (models per step, unless ``models_per_tick``: the
    server's EM fitted per tick) are made a tick's worth, EM fits Gamma_hat per tick from the
    missions' timestamped records, returns count ticks in units of one step's worth of ticks, and
    the result's model is per tick.

    ``progress`` gets a dict after every update; ``should_stop`` is polled after every update
    and ends training early with the last completed update (``interrupted``).
    """
    cfg.check()
    rank, world = _world()
    device = torch.device(cfg.device)
    beta = torch.tensor(cfg.per_robot(cfg.beta, "beta"), device=device)
    lrs = torch.tensor(cfg.per_robot(cfg.lr, "lr"), device=device)
    collective = cfg.variant == "c-cepg"
    policy = _initial_policy(graph, cfg, init_policy, device)
    opt = torch.optim.Adam(policy.parameters(), lr=float(lrs.max()))
    clock = clock_of(graph, cfg)
    if clock is not None and not models_per_tick:  # the models per step made a tick's worth (I stays I)
        target = clock.model(target)
        init_model = None if init_model is None else clock.model(init_model)
    j_unit = cfg.j_unit * (1.0 if clock is None else clock.ticks_per_step)
    model = target if cfg.belief == "true" else (init_model or identity_model(graph))
    belief = BatchedBelief(graph, model, sensor, device)
    sim = SearchSim(
        graph,
        target,
        sensor,
        cfg.robots,
        math.ceil(cfg.batch / world),
        seed=cfg.seed * 7_919 + rank,
        device=device,
        auto_reset=False,
        check_actions=False,  # the policies' softmax is masked to N[p]: every draw is a valid move
        details=False,  # the rollout reads done, capture_time and censored only
        move_ticks=None if clock is None else clock.ticks,
        t_max=None if clock is None else clock.t_max(graph.n),
    )
    gen = torch.Generator(device=device)
    gen.manual_seed(cfg.seed * 104_729 + rank)

    curve = _LearningCurve(every=max(1, cfg.episodes // 200))
    em_log: list[dict[str, Any]] = []
    episodes = env_steps = updates = 0
    next_em = cfg.em_first if cfg.belief == "em" else math.inf
    t0 = time.perf_counter()
    interrupted = False
    scale: float | None = None  # j_unit 0: the running mean capture time
    while episodes < cfg.episodes:
        ro = rollout(sim, policy, belief, collective, gen)  # B episodes with the current policies
        if cfg.j_unit == 0:  # J in units of the run's own capture time (the general policy's training scale)
            mean_ct = float(ro.capture_time.float().mean())
            scale = mean_ct if scale is None else 0.9 * scale + 0.1 * mean_ct
            j_unit = max(scale, 1.0)
        terms = cepg_loss(policy, ro, beta, cfg.eps, cfg.ce_fraction, gen, j_unit, cfg.ce_states)  # Eq. 9-13
        # linear decay of the learning rate over the run: a steadier final policy
        lr = float(lrs.max()) * (1.0 - (1.0 - cfg.lr_final) * min(1.0, episodes / cfg.episodes))
        stats = _update(policy, opt, terms, ro, lrs, lr, world)
        updates += 1
        n_eps, ct_sum, cens_sum, steps, ce = (float(x) for x in stats)
        episodes += int(n_eps)
        env_steps += int(steps)
        curve.add(n_eps, ct_sum, cens_sum, ce)
        if episodes >= next_em:  # Algorithm 2's model update, by EM on the team's own missions
            em_log.append(em_update(graph, target, sensor, cfg, policy, belief, episodes, rank, world, device, clock))
            model = belief.model(graph, em_log[-1].get("kind", "em"))
            next_em = episodes + cfg.em_every
        stop = bool(should_stop and should_stop())
        if curve.due(episodes) or episodes >= cfg.episodes or stop:
            point = curve.point(episodes, time.perf_counter() - t0)
            if progress:
                elapsed = time.perf_counter() - t0
                progress(
                    {
                        **point,
                        "total": cfg.episodes,
                        "updates": updates,
                        "env_steps": env_steps,
                        "episodes_per_second": episodes / max(elapsed, 1e-9),
                        "time_unit": "steps" if clock is None else "ticks",
                    }
                )
        if stop:
            interrupted = episodes < cfg.episodes
            break
    wall = time.perf_counter() - t0
    if world > 1:
        _check_replicas_agree(policy)
    summary = {
        "episodes": episodes,
        "env_steps": env_steps,
        "updates": updates,
        "wall_seconds": round(wall, 3),
        "episodes_per_second": round(episodes / max(wall, 1e-9), 1),
        "env_steps_per_second": round(env_steps / max(wall, 1e-9), 1),
        "processes": world,
        "interrupted": interrupted,
        "final_mean_capture_time": curve.points[-1]["mean_capture_time"] if curve.points else None,
        "belief_model": model.kind,
        "clock": None if clock is None else {**clock.summary(), "unit": "ticks"},
        "em_updates": em_log,
        "learning_curve": curve.points,
    }
    return TrainResult(policy=policy, model=model, summary=summary, interrupted=interrupted)


def clock_of(graph: Graph, cfg: TrainConfig) -> TravelTimes | None:
    """The graph's travel times at ``cfg.speed`` in ticks of ``cfg.tick`` s, or None without a speed
    (the paper's model: every move one step). ValueError for a graph without edge lengths."""
    if cfg.speed is None:
        return None
    return TravelTimes.of(graph, cfg.speed, cfg.tick)


def _initial_policy(graph: Graph, cfg: TrainConfig, init_policy: Snapshot | None, device: torch.device) -> Any:
    """The team's networks, seeded (identical initial weights on every process) or warm-started
    from ``init_policy``'s weights (a TeamPolicy; for the general policy, its network bound to this
    map and cfg.robots robots, any number: shared/learning/general.py ``GraphTeam``, which learns
    each robot's node_bias at ``cfg.node_bias`` times the learning rate, from the snapshot's own
    when it has one for this team)."""
    torch.manual_seed(cfg.seed)
    if init_policy is not None and init_policy.general:  # fine-tune the general policy on this map
        import copy

        from shared.learning.general import GraphTeam

        if len(set(cfg.per_robot(cfg.lr, "lr"))) > 1:
            raise ValueError("the general policy is one network for every robot: give one learning rate")
        start = init_policy.policy.node_bias()  # a fine-tune's, going on from it with the same team
        same_team = start is not None and init_policy.robots == cfg.robots
        return GraphTeam(
            copy.deepcopy(init_policy.policy.net),
            graph,
            cfg.robots,
            node_bias=start.detach().cpu().numpy() if same_team else None,
            bias_rate=cfg.node_bias,
        ).to(device)
    policy = TeamPolicy(graph.n, cfg.robots, torch.as_tensor(graph.adjacency()), hidden=cfg.hidden).to(device)
    if init_policy is not None:
        if init_policy.robots != cfg.robots or init_policy.policy.H != policy.H:
            raise ValueError(
                f"warm start: snapshot has {init_policy.robots} robots and {init_policy.policy.H} hidden units, "
                f"this run {cfg.robots} and {policy.H}"
            )
        policy.load_state_dict(init_policy.policy.state_dict())
    return policy


def _update(
    policy: TeamPolicy, opt: torch.optim.Optimizer, terms: Any, ro: Any, lrs: torch.Tensor, lr: float, world: int
) -> torch.Tensor:
    """One Adam step on the CE-PG loss at learning rate ``lr`` (summed over the W processes'
    gradients), each robot's change scaled by alpha_i / max(alpha) (Eq. 13, module docstring).
    Returns the batch's (episodes, sum of capture times, censored, team steps, mean cross-entropy),
    float64, summed over the processes (the cross-entropy averaged)."""
    opt.zero_grad(set_to_none=False)
    (terms.loss / world).backward()
    stats = torch.tensor(
        [
            float(ro.length.numel()),
            float(ro.capture_time.sum()),
            float(ro.censored.sum()),
            float(ro.length.sum()),
            float(terms.ce.mean()),
        ],
        dtype=torch.float64,
    )
    if world > 1:
        for p in policy.parameters():
            dist.all_reduce(p.grad)
        dist.all_reduce(stats)
        stats[4] /= world
    lr_scale = (lrs / lrs.max()).view(-1, 1, 1)  # (N, 1, 1)
    per_robot_lr = bool((lr_scale != 1).any())  # robots with a smaller rate than the largest
    if per_robot_lr:
        before = [p.detach().clone() for p in policy.parameters()]
    for group in opt.param_groups:
        group["lr"] = lr
    opt.step()
    if per_robot_lr:
        with torch.no_grad():
            for p, p0 in zip(policy.parameters(), before, strict=True):
                scale = lr_scale.view(-1, *([1] * (p.dim() - 1)))
                p.copy_(p0 + scale * (p - p0))
    return stats


class _LearningCurve:
    """The training episodes' capture time, censored fraction and cross-entropy, one point per
    ``every`` episodes (at most 200 a run), each averaged over the updates since the last point."""

    def __init__(self, every: int) -> None:
        self.every, self.next = every, every
        self.points: list[dict[str, Any]] = []
        self.window: list[tuple[float, float, float, float]] = []  # per update: episodes, sum ct, censored, ce

    def add(self, episodes: float, capture_time_sum: float, censored: float, ce: float) -> None:
        self.window.append((episodes, capture_time_sum, censored, ce))

    def due(self, episodes: int) -> bool:
        return episodes >= self.next

    def point(self, episodes: int, wall_seconds: float) -> dict[str, Any]:
        w_eps = sum(w[0] for w in self.window)
        point = {
            "episodes": episodes,
            "mean_capture_time": sum(w[1] for w in self.window) / w_eps,
            "censored_fraction": sum(w[2] for w in self.window) / w_eps,
            "cross_entropy": sum(w[3] for w in self.window) / len(self.window),
            "wall_seconds": round(wall_seconds, 3),
        }
        self.points.append(point)
        self.window.clear()
        self.next = episodes + self.every
        return point


def _check_replicas_agree(policy: TeamPolicy) -> None:
    """Data-parallel replicas must end with the same weights: a RuntimeError when they do not."""
    d = _params_digest(policy)
    ref = d.clone()
    dist.broadcast(ref, 0)
    same = torch.tensor([float(torch.equal(d, ref))], dtype=torch.float64)
    dist.all_reduce(same, op=dist.ReduceOp.MIN)
    if same.item() != 1.0:
        raise RuntimeError("data-parallel replicas diverged: weights differ between processes")


@torch.no_grad()
def em_update(
    graph: Graph,
    target: TargetModel,
    sensor: Sensor,
    cfg: TrainConfig,
    policy: TeamPolicy,
    belief: BatchedBelief,
    episodes: int,
    rank: int,
    world: int,
    device: torch.device,
    clock: TravelTimes | None = None,
) -> dict[str, Any]:
    """Algorithm 2's model update: fly ``em_missions`` missions with the current policies, turn
    them into episode records, and re-estimate Gamma_hat and b0 by EM from those records (with a
    ``clock``: Gamma_hat per tick from the records' times, ``target`` being the model per tick)."""
    t0 = time.perf_counter()
    info: dict[str, Any] = {"episodes": episodes}
    gamma = torch.empty(graph.n, graph.n, dtype=torch.float64)
    b0 = torch.empty(graph.n, dtype=torch.float64)
    if rank == 0:
        current = belief.model(graph, "current")
        snap = Snapshot(
            meta={"variant": cfg.variant, "robots": cfg.robots}, policy=policy, model=current, sensor=sensor
        )
        res = evaluate(
            graph,
            target,
            sensor,
            cfg.robots,
            lambda s: PolicySearcher(snap, graph, sensor, cfg.robots, seed=s, device=device),
            episodes=cfg.em_missions,
            seed=cfg.seed * 31 + episodes,
            device=device,
            record=True,
            clock=clock,
        )
        tick_s = None if clock is None else clock.tick_s
        recs = episode_records(graph, res, sensor, mission_prefix=f"train-{episodes}", tick_s=tick_s)
        data = collect_missions(((0, r) for r in recs), graph, tick_s=tick_s)
        est = em(
            graph,
            data,
            max_iter=cfg.em_max_iter,
            tol=1e-5,
            pseudo_count=cfg.em_pseudo_count,
            b0_pseudo_count=cfg.em_b0_pseudo_count,
        )
        gamma.copy_(torch.as_tensor(est.model.dense()))
        b0.copy_(torch.as_tensor(est.model.b0))
        info.update(
            missions=len(data.length),
            iterations=est.iterations,
            converged=est.converged,
            mean_row_tv_to_true=round(mean_row_tv(est.model, target), 4),
            kind="em",
        )
    if world > 1:
        dist.broadcast(gamma, 0)
        dist.broadcast(b0, 0)
    if belief.sparse:
        belief.set_model(from_matrix(graph, gamma.numpy(), b0.numpy(), kind="em"))
    else:  # the estimate's float64 values as they are, cast once
        belief.gamma = gamma.to(device=device, dtype=belief.dtype)
        belief.b0 = b0.to(device=device, dtype=belief.dtype)
    info["seconds"] = round(time.perf_counter() - t0, 3)
    info.setdefault("kind", "em")
    return info

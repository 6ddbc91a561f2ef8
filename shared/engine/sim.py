"""Batched simulator of the paper setup (docs/SPEC.md section 1), in torch.

B episodes run side by side, each with N robots on a graph of n nodes. One call of ``step``
advances every running episode by one time step, in the order of docs/SPEC.md section 1:

    robots move (a_t in N[p_t])  ->  target moves (e_{t+1} ~ Gamma(e_t, .))  ->  robots observe z_{t+1}

Capture: the first t with e_t in D(p_t^i) and z_t^i = 1 for some robot i (t = 0 included).
Censoring: no capture by T_max = 3n gives t_cap = T_max and ``censored``. A z = 1 with the target
outside D(p) is a false alarm: counted, and the mission goes on.

With ``auto_reset`` (throughput mode, for training) a finished episode's slot immediately starts
a fresh episode; without it (evaluation mode) finished slots freeze until ``reset``. Evaluation
uses the latter so that every started episode is counted, whatever its length (streaming the
first-finished episodes out of an auto-reset batch would bias toward short episodes).

Shapes (B episodes, N robots, n nodes): positions (B, N) rows, target (B,), t (B,), z (B, N).
Deterministic for a seed: all randomness comes from one ``torch.Generator``.

Robustness experiments: ``withdraw_at[i] = k`` withdraws robot i at step k: from t = k on it
stays where it is, observes nothing (z = 0) and cannot capture.

Travel times (``move_ticks``, docs/continuous-world.md "Training on the clock"): t counts ticks of
the mission clock and a move from p to a takes ``move_ticks[p, a]`` >= 1 ticks (a stay one). The
target moves once a tick (its model is a tick's worth, shared/core/clock.py ``tick_model``). A
robot decides only when it stands on a node (``Obs.ready``); in transit it stays at the node it left
(``pos``), observes nothing (z = 0, no reading) and cannot capture, and the actions given for it are
ignored; on arriving it stands on its goal and reads z there. Every move taking one tick is the
paper's model: the same random draws, so the same seeds give the same episodes as without the table.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel

NEVER = 2**62


@dataclass
class Obs:
    """What the robots see after a step. ``new`` marks slots whose episode just started (t = 0)."""

    pos: torch.Tensor  # (B, N) long, node rows
    z: torch.Tensor  # (B, N) bool
    t: torch.Tensor  # (B,) long
    new: torch.Tensor  # (B,) bool
    active: torch.Tensor  # (B, N) bool, False once a robot is withdrawn
    alive: torch.Tensor  # (B,) bool, False for frozen slots (evaluation mode)
    target: torch.Tensor | None = None  # (B,) the hidden target's rows: only the `oracle` baseline reads it
    ready: torch.Tensor | None = None  # (B, N) bool: on a node, read z and decides now (None: every robot)

    def observed(self) -> torch.Tensor:
        """(B, N) bool: the robots whose z is a reading this tick (active and on a node)."""
        return self.active if self.ready is None else self.active & self.ready


@dataclass
class StepResult:
    """Episodes that ended during a step; entries are meaningful where ``done``."""

    done: torch.Tensor  # (B,) bool
    capture_time: torch.Tensor  # (B,) long; T_max when censored
    censored: torch.Tensor  # (B,) bool
    false_alarms: torch.Tensor  # (B,) long, over the whole episode
    captured_by: torch.Tensor  # (B,) long robot index, -1 when censored


class SearchSim:
    """The batched paper-setup simulator. See the module docstring for semantics and shapes."""

    def __init__(
        self,
        graph: Graph,
        target: TargetModel,
        sensor: Sensor,
        n_robots: int,
        batch: int,
        seed: int = 0,
        device: torch.device | str = "cpu",
        auto_reset: bool = True,
        t_max: int | None = None,
        start: int | None = None,
        withdraw_at: list[int | None] | None = None,
        check_actions: bool = True,
        details: bool = True,
        move_ticks: np.ndarray | None = None,
    ) -> None:
        if n_robots < 1:
            raise ValueError(f"expected at least 1 robot, got {n_robots}")
        if batch < 1:
            raise ValueError(f"expected a batch of at least 1 episode, got {batch}")
        if target.n != graph.n:
            raise ValueError(f"target model has {target.n} nodes, graph has {graph.n}")
        dev = torch.device(device)
        self.graph, self.sensor = graph, sensor
        self.n, self.N, self.B = graph.n, n_robots, batch
        self.device = dev
        self.auto_reset = auto_reset
        self.t_max = 3 * graph.n if t_max is None else t_max
        self.start = graph.start if start is None else start
        self.gen = torch.Generator(device=dev)
        self.gen.manual_seed(seed)
        # graph tables
        self.nbr = torch.as_tensor(graph.nbr, device=dev)  # (n, d) N[p], padded with p
        self.deg = torch.as_tensor(graph.deg_closed, device=dev)  # (n,)
        # D(p) padded to (n, d) (shared/core/graph.py detection_table): e in D(p) is one row compare,
        # and nothing here is (n, n), so maps of 10^4 nodes fit
        self.dsets = torch.as_tensor(graph.detection_table(sensor.detection), device=dev)
        # target sampling: per source row, destinations and cumulative probabilities
        counts = np.bincount(target.src, minlength=graph.n)
        k = int(counts.max())
        t_dst = np.repeat(np.arange(graph.n)[:, None], k, axis=1)
        t_cum = np.ones((graph.n, k))
        ptrs = np.concatenate([[0], np.cumsum(counts)])
        for u in range(graph.n):
            a, b = ptrs[u], ptrs[u + 1]
            t_dst[u, : b - a] = target.dst[a:b]
            t_cum[u, : b - a] = np.cumsum(target.prob[a:b])
        t_cum[:, -1] = 2.0  # guard against rounding: the last candidate catches u ~ 1
        self.t_dst = torch.as_tensor(t_dst, device=dev)
        self.t_cum = torch.as_tensor(t_cum, dtype=torch.float64, device=dev)
        self.b0 = torch.as_tensor(target.b0, dtype=torch.float64, device=dev)
        self.eta_fn, self.eta_fp = sensor.eta_fn, sensor.eta_fp
        # False: the caller's actions are known to be in N[p] (the trainer's masked policies), and
        # the check, a gather and a host sync per step, is skipped
        self.check_actions = check_actions
        # False: StepResult's false_alarms and captured_by are not kept up to date (the trainer
        # reads done, capture_time and censored only); saves their bookkeeping every step
        self.details = details
        # travel times: ticks[p, a] per move of N[p] (module docstring); None: every move one tick
        self.timed = move_ticks is not None
        if move_ticks is not None:
            ticks = np.asarray(move_ticks)
            if ticks.shape != (graph.n, graph.n):
                raise ValueError(f"move_ticks: expected an (n, n) = ({graph.n}, {graph.n}) table, got {ticks.shape}")
            if (ticks[np.repeat(np.arange(graph.n), graph.deg_closed), graph.closed_idx] < 1).any():
                raise ValueError("move_ticks: every move of N[p] must take at least 1 tick")
            self.move_ticks = torch.as_tensor(ticks, dtype=torch.long, device=dev)
        drop = [NEVER if w is None else int(w) for w in (withdraw_at or [None] * n_robots)]
        if len(drop) != n_robots:
            raise ValueError(f"withdraw_at has {len(drop)} entries, expected one per robot ({n_robots})")
        self.withdraw_at = torch.tensor(drop, dtype=torch.long, device=dev)  # (N,)
        # without withdrawals every robot stays active: the per-step masking by ``active`` is skipped
        self.withdrawals = any(w != NEVER for w in drop)
        # a perfect sensor reads z = [e in D(p)]: the comparisons with eta are skipped (the draw is
        # still made, so the random stream, and every episode, is the same as with them)
        self.perfect = self.eta_fn == 0.0 and self.eta_fp == 0.0
        # state
        B, N = batch, n_robots
        self.pos = torch.full((B, N), self.start, dtype=torch.long, device=dev)
        self.target = torch.zeros(B, dtype=torch.long, device=dev)
        self.t = torch.zeros(B, dtype=torch.long, device=dev)
        self.z = torch.zeros(B, N, dtype=torch.bool, device=dev)
        self.alive = torch.zeros(B, dtype=torch.bool, device=dev)
        self.pending = torch.zeros(B, dtype=torch.bool, device=dev)  # captured at t = 0
        self.pending_by = torch.full((B,), -1, dtype=torch.long, device=dev)
        self.false_alarms = torch.zeros(B, dtype=torch.long, device=dev)
        self.active = torch.ones(B, N, dtype=torch.bool, device=dev)
        self._new = torch.zeros(B, dtype=torch.bool, device=dev)
        self.moving = torch.zeros(B, dtype=torch.bool, device=dev)  # set by each step
        self.goal = torch.full((B, N), self.start, dtype=torch.long, device=dev)  # where each robot is headed
        self.left = torch.zeros(B, N, dtype=torch.long, device=dev)  # ticks until it stands on its goal
        self.ready = torch.ones(B, N, dtype=torch.bool, device=dev)  # on a node: reads z and decides

    # the episodes' state: what ``state_dict`` saves (the graph's and the models' tables are rebuilt
    # from the same graph, target model and sensor)
    _STATE = (
        "pos", "target", "t", "z", "alive", "pending", "pending_by", "false_alarms", "active", "_new", "moving",
        "goal", "left", "ready",
    )  # fmt: skip

    def state_dict(self) -> dict[str, torch.Tensor]:
        """The running episodes and the generator's state, to continue later exactly where they are
        (a resumable training run's checkpoint): {name: tensor}."""
        return {**{k: getattr(self, k).clone() for k in self._STATE}, "gen": self.gen.get_state()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Continue from ``state_dict()``'s output, taken from a simulator of the same graph, models
        and batch; a ValueError names an entry that is missing or of another shape or type."""
        for k in self._STATE:
            mine, theirs = getattr(self, k), state.get(k)
            if not isinstance(theirs, torch.Tensor) or theirs.shape != mine.shape or theirs.dtype != mine.dtype:
                raise ValueError(f"simulator state {k!r}: expected a {mine.dtype} tensor of shape {tuple(mine.shape)}")
        for k in self._STATE:
            setattr(self, k, state[k].to(self.device).clone())
        self.gen.set_state(state["gen"])

    # ------------------------------------------------------------------ internals
    def _rand(self, *shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=self.gen, device=self.device, dtype=torch.float64)

    def _observe(self) -> tuple[torch.Tensor, torch.Tensor]:
        """z (B, N) and in_D (B, N) for the current positions and target (sensor of docs/SPEC.md section 1)."""
        in_d = (self.dsets[self.pos] == self.target.view(-1, 1, 1)).any(-1)  # (B, N): e in D(p)
        reading = self.active if not self.timed else self.active & self.ready  # robots that read z now
        if self.withdrawals or self.timed:
            in_d = in_d & reading
        u = self._rand(self.B, self.N)
        if self.perfect:  # u >= 0 always, u < 0 never
            return in_d, in_d
        z = torch.where(in_d, u >= self.eta_fn, u < self.eta_fp)
        return (z & reading if self.withdrawals or self.timed else z), in_d

    @staticmethod
    def _first(hits: torch.Tensor) -> torch.Tensor:
        """Index of the first True per row, -1 where none: (B, N) -> (B,)."""
        first = hits.to(torch.int8).argmax(dim=1)
        return torch.where(hits.any(dim=1), first, torch.full_like(first, -1))

    def _start_episodes(self, mask: torch.Tensor) -> None:
        """Start fresh episodes in the slots of ``mask`` (B,): draw e_0 ~ b0, robots on s, observe z_0."""
        e0 = torch.multinomial(self.b0, self.B, replacement=True, generator=self.gen)
        m1 = mask.unsqueeze(1)
        self.target = torch.where(mask, e0, self.target)
        self.pos = torch.where(m1, torch.full_like(self.pos, self.start), self.pos)
        self.t = torch.where(mask, torch.zeros_like(self.t), self.t)
        if self.timed:  # every robot stands on the start node
            self.goal = torch.where(m1, torch.full_like(self.goal, self.start), self.goal)
            self.left = torch.where(m1, torch.zeros_like(self.left), self.left)
            self.ready = self.ready | m1
        if self.withdrawals:  # otherwise every robot stays active throughout
            self.active = torch.where(m1, (self.withdraw_at > 0).expand(self.B, self.N), self.active)
        z, in_d = self._observe()
        self.z = torch.where(m1, z, self.z)
        hits = (in_d if self.perfect else z & in_d) & m1
        self.pending = torch.where(mask, hits.any(1), self.pending)
        if self.details:  # false alarms and who captured at t = 0 (StepResult's details)
            self.false_alarms = torch.where(mask, (z & ~in_d).sum(1), self.false_alarms)
            self.pending_by = torch.where(mask, self._first(hits), self.pending_by)
        self.alive = self.alive | mask
        self._new = mask

    def _obs(self) -> Obs:
        return Obs(
            self.pos,
            self.z,
            self.t,
            self._new,
            self.active,
            self.alive,
            self.target,
            self.ready if self.timed else None,
        )

    # ------------------------------------------------------------------ API
    def reset(self) -> Obs:
        """Start B fresh episodes."""
        self._start_episodes(torch.ones(self.B, dtype=torch.bool, device=self.device))
        return self._obs()

    def step(self, actions: torch.Tensor) -> tuple[Obs, StepResult]:
        """Advance every running episode by one step (a tick with ``move_ticks``). actions: (B, N) node
        rows in N[p]; with ``move_ticks`` only those of robots on a node (``Obs.ready``) count."""
        if actions.shape != (self.B, self.N):
            raise ValueError(f"expected actions of shape {(self.B, self.N)}, got {tuple(actions.shape)}")
        actions = actions.to(device=self.device, dtype=torch.long)
        moving = self.moving = self.alive & ~self.pending  # (B,) the episodes this step advances
        deciding = moving.unsqueeze(1)  # (B, N): the robots whose action counts
        if self.withdrawals:
            deciding = deciding & self.active
        if self.timed:
            deciding = deciding & self.ready
        act = torch.where(deciding, actions, self.pos)
        allowed = (self.nbr[self.pos] == act.unsqueeze(-1)).any(-1) if self.check_actions else None  # a in N[p]
        if allowed is not None and not bool(allowed.all()):
            bad = (~allowed).nonzero()[0]
            b, i = int(bad[0]), int(bad[1])
            raise ValueError(
                f"episode slot {b}, robot {i}: action to node {self.graph.labels[int(act[b, i])]} "
                f"is not in N[{self.graph.labels[int(self.pos[b, i])]}]"
            )
        # robots move, then the target moves (docs/SPEC.md section 1 order)
        if self.timed:  # a robot on a node sets off for its goal; one in transit goes on (module docstring)
            start = self.ready & moving.unsqueeze(1)
            self.goal = torch.where(start, act, self.goal)
            self.left = torch.where(start, self.move_ticks[self.pos, act], self.left)
            self.left = self.left - (moving.unsqueeze(1) & (self.left > 0)).long()
            self.ready = self.left == 0
            self.pos = torch.where(self.ready, self.goal, self.pos)
        else:
            self.pos = act
        u = self._rand(self.B, 1)
        k = (u > self.t_cum.index_select(0, self.target)).sum(1)  # the candidate u falls on
        nxt = self.t_dst.view(-1).index_select(0, self.target * self.t_dst.shape[1] + k)  # t_dst[e, k]
        self.target = torch.where(moving, nxt, self.target)
        self.t = self.t + moving.long()
        if self.withdrawals:
            self.active = self.active & (self.withdraw_at > self.t.unsqueeze(1))
        # observe z_{t+1}
        z, in_d = self._observe()
        self.z = torch.where(moving.unsqueeze(1), z, self.z)
        if self.details:
            self.false_alarms = self.false_alarms + ((z & ~in_d).sum(1) * moving)
        hits = (in_d if self.perfect else z & in_d) & moving.unsqueeze(1)
        captured = hits.any(1)
        censored = moving & ~captured & (self.t >= self.t_max)
        done = captured | censored | (self.alive & self.pending)
        result = StepResult(
            done=done,
            capture_time=self.t,  # never changed in place: the next step makes a new tensor
            censored=censored,
            false_alarms=self.false_alarms.clone() if self.details else self.false_alarms,
            captured_by=torch.where(self.pending, self.pending_by, self._first(hits))
            if self.details
            else self.pending_by,
        )
        self.pending = self.pending & ~done
        self._new = torch.zeros_like(done)
        if self.auto_reset:
            if bool(done.any()):
                self._start_episodes(done)
        else:
            self.alive = self.alive & ~done
        return self._obs(), result

    @property
    def any_alive(self) -> bool:
        return bool(self.alive.any())

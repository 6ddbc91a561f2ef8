"""Evaluation of a searcher on the batched simulator, and capture-time statistics.

Every started episode is counted (evaluation mode, no auto-reset): B = ``episodes`` slots, run
in chunks of at most ``chunk`` slots, each chunk seeded from (seed, chunk index).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from shared.core.clock import TravelTimes
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.core.records import make_record
from shared.engine.searchers import Searcher
from shared.engine.sim import SearchSim

Z95 = 1.959963984540054


@dataclass
class Trajectories:
    """Per-step positions and observations of a fixed batch. pos/z: (T+1, B, N); length: (B,).
    With travel times a step is a tick and ``ready`` (T+1, B, N) marks the robots that stood on a
    node and read z then (None: every robot every step)."""

    pos: np.ndarray
    z: np.ndarray
    length: np.ndarray  # steps recorded per episode: capture_time + 1
    ready: np.ndarray | None = None


def mean_ci95(x: Any) -> tuple[float, float]:
    """Mean and the half-width of its normal-approximation 95% CI (nan for fewer than 2 values)."""
    a = np.asarray(x, dtype=np.float64)
    if len(a) == 0:
        return float("nan"), float("nan")
    half = Z95 * float(a.std(ddof=1)) / math.sqrt(len(a)) if len(a) > 1 else float("nan")
    return float(a.mean()), half


Z999 = 3.2905267314918945  # two-sided 0.1 %


def means_differ(a: Any, b: Any, z: float = Z999) -> tuple[bool, float]:
    """Welch's two-sample z-test of equal means: (differ, z-score). The default level is 0.1 %
    two-sided, so that a check run on every CI build fails by chance once in 1000 runs; asking
    that the means lie within the sum of their 95 % half-widths fails by chance between once in
    20 and once in 180 runs, depending on the two samples' sizes."""
    x, y = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if len(x) < 2 or len(y) < 2:
        raise ValueError("means_differ needs at least 2 values in each sample")
    se = math.sqrt(x.var(ddof=1) / len(x) + y.var(ddof=1) / len(y))
    d = float(x.mean() - y.mean())
    score = d / se if se > 0 else (0.0 if d == 0 else math.copysign(math.inf, d))
    return abs(score) > z, score


@dataclass
class EvalResult:
    capture_time: np.ndarray  # (B,) int
    censored: np.ndarray  # (B,) bool
    false_alarms: np.ndarray  # (B,) int
    captured_by: np.ndarray  # (B,) int, -1 when censored
    seed: int
    wall_seconds: float = 0.0
    trajectories: list[Trajectories] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """The fields docs/SPEC.md section 7 names for `mures evaluate`."""
        ct = self.capture_time.astype(np.float64)
        B = len(ct)
        mean, half = mean_ci95(ct)
        return {
            "episodes": B,
            "mean_capture_time": mean,
            "ci95": [mean - half, mean + half],
            "ci95_halfwidth": half,
            "median": float(np.median(ct)),
            "censored_fraction": float(self.censored.mean()),
            "false_alarms_per_episode": float(self.false_alarms.mean()),
            "seed": self.seed,
        }


def evaluate(
    graph: Graph,
    target: TargetModel,
    sensor: Sensor,
    n_robots: int,
    make_searcher: Callable[[int], Searcher],
    episodes: int = 1500,
    seed: int = 0,
    chunk: int = 4096,
    device: torch.device | str = "cpu",
    withdraw_at: list[int | None] | None = None,
    record: bool = False,
    progress: Callable[[dict[str, Any]], None] | None = None,
    clock: TravelTimes | None = None,
) -> EvalResult:
    """Run ``episodes`` episodes of ``make_searcher(chunk_seed)`` and collect their outcomes.

    ``clock``: moves take the graph's travel times (shared/engine/sim.py ``move_ticks``), capture
    times are in ticks and T_max is 3n steps' worth of ticks; ``target`` is then the model per tick.

    ``record`` keeps every step's positions and observations (for writing episode records);
    ``progress`` gets {"episodes", "total", "episodes_per_second"} after every chunk (a planner's
    chunk is one episode).
    """
    if episodes < 1:
        raise ValueError(f"expected at least 1 episode, got {episodes}")
    t0 = time.perf_counter()
    outs: dict[str, list[np.ndarray]] = {k: [] for k in ("ct", "cens", "fa", "by")}
    trajs: list[Trajectories] = []
    for c, start in enumerate(range(0, episodes, chunk)):
        B = min(chunk, episodes - start)
        chunk_seed = seed * 1_000_003 + c
        sim = SearchSim(
            graph,
            target,
            sensor,
            n_robots,
            B,
            seed=chunk_seed,
            device=device,
            auto_reset=False,
            withdraw_at=withdraw_at,
            move_ticks=None if clock is None else clock.ticks,
            t_max=None if clock is None else clock.t_max(graph.n),
        )
        searcher = make_searcher(chunk_seed + 7919)
        obs = sim.reset()
        ct = torch.zeros(B, dtype=torch.long)
        cens = torch.zeros(B, dtype=torch.bool)
        fa = torch.zeros(B, dtype=torch.long)
        by = torch.full((B,), -1, dtype=torch.long)
        pos_log, z_log = [obs.pos.cpu()], [obs.z.cpu()]
        ready_log = [] if obs.ready is None else [obs.ready.cpu()]
        with torch.no_grad():
            while sim.any_alive:
                obs, res = sim.step(searcher.act(obs))
                d = res.done.cpu()
                ct = torch.where(d, res.capture_time.cpu(), ct)
                cens = torch.where(d, res.censored.cpu(), cens)
                fa = torch.where(d, res.false_alarms.cpu(), fa)
                by = torch.where(d, res.captured_by.cpu(), by)
                if record:
                    pos_log.append(obs.pos.cpu())
                    z_log.append(obs.z.cpu())
                    if obs.ready is not None:
                        ready_log.append(obs.ready.cpu())
        outs["ct"].append(ct.numpy())
        outs["cens"].append(cens.numpy())
        outs["fa"].append(fa.numpy())
        outs["by"].append(by.numpy())
        if progress:
            done = start + B
            progress({"episodes": done, "total": episodes, "episodes_per_second": done / (time.perf_counter() - t0)})
        if record:
            trajs.append(
                Trajectories(
                    pos=torch.stack(pos_log).numpy(),
                    z=torch.stack(z_log).numpy().astype(np.int8),
                    length=ct.numpy() + 1,
                    ready=torch.stack(ready_log).numpy() if ready_log else None,
                )
            )
    return EvalResult(
        capture_time=np.concatenate(outs["ct"]),
        censored=np.concatenate(outs["cens"]),
        false_alarms=np.concatenate(outs["fa"]),
        captured_by=np.concatenate(outs["by"]),
        seed=seed,
        wall_seconds=time.perf_counter() - t0,
        trajectories=trajs,
    )


def episode_records(
    graph: Graph,
    result: EvalResult,
    sensor: Sensor,
    fleet: str = "default",
    mission_prefix: str = "sim",
    tick_s: float | None = None,
) -> Iterator[dict[str, Any]]:
    """Episode records (docs/SPEC.md section 5), one per robot per mission, from a ``record=True`` run.

    Robots are named r0..r{N-1}; missions ``{mission_prefix}-{k:06d}`` in episode order. A run with
    travel times gives each robot's readings only (the ticks it stood on a node), each with its
    ``time_s`` (tick k at k ``tick_s``), as a robot on the mission clock records them.
    """
    if tick_s is None and any(tr.ready is not None for tr in result.trajectories):
        raise ValueError("a run with travel times makes records on the clock: give tick_s")
    k = 0
    for tr in result.trajectories:
        timed = tr.ready is not None
        for b in range(tr.pos.shape[1]):
            length, censored = int(tr.length[b]), bool(result.censored[k])
            for i in range(tr.pos.shape[2]):
                ticks = np.flatnonzero(tr.ready[:length, b, i]) if tr.ready is not None else np.arange(length)
                yield make_record(
                    graph,
                    fleet=fleet,
                    mission_id=f"{mission_prefix}-{k:06d}",
                    robot_id=f"r{i}",
                    nodes=tr.pos[ticks, b, i],
                    z=tr.z[ticks, b, i],
                    sensor=sensor,
                    captured=not censored,
                    # the robot's own reading index of the capture: its last (on the clock, each robot's own count)
                    capture_time=None if censored else (len(ticks) - 1 if timed else int(result.capture_time[k])),
                    captured_by=None if censored else f"r{int(result.captured_by[k])}",
                    times=None if tick_s is None or not timed else ticks * tick_s,
                )
            k += 1

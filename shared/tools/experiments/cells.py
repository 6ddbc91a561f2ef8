"""Cells: one method flown on one (map, N, sensor) for a number of seeded episodes, its row the
capture time and false alarms (mean, 95% CI). Each cell is evaluated once and cached under
results/cells/ by what determines it; while a run is planned, a cell becomes a runner job.
``Reference`` flies random, greedy and the planners; ``teams.Team`` the learned teams."""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.files import atomic_write
from shared.tools.experiments.budget import PLANNERS, SEED
from shared.tools.experiments.context import Context
from shared.tools.experiments.costs import cell_cost
from shared.tools.experiments.teams import Team, noise_label
from shared.tools.runner import Job, directory_files

CELL_VERSION = 1  # bump when evaluation itself changes: cached cells are then evaluated again
# A learned team's decision time (fig8) is timed on one-at-a-time episodes until they add up to this
# many team steps (the cell's mean capture time says how many episodes); three episodes, a few dozen
# steps at N = 5, gave FACMAC 1.75 and then 1.06 ms in two quiet flights. Part of a learned team's
# timed cell's key (not a planner's: planners are timed on their own episodes, as they fly them).
TIMED_TEAM_STEPS = 400


@dataclass(frozen=True)
class Reference:
    """seed -> random, greedy or a planner (true model, all robots' observations)."""

    env: str
    robots: int
    method: str
    sensor: Any
    kw: tuple[tuple[str, Any], ...] = ()

    def ready(self) -> bool:
        return True

    def __call__(self, seed: int) -> Any:
        from shared.core.graph import builtin_graph
        from shared.core.models import uniform_walk
        from shared.planners import make_baseline
        from shared.registry import make_searcher

        g = builtin_graph(self.env)
        if self.method in ("random", "greedy"):
            return make_searcher(self.method, g, uniform_walk(g), self.sensor, seed)
        return make_baseline(self.method, g, uniform_walk(g), self.sensor, self.robots, seed, **dict(self.kw))

    def trained(self) -> dict[str, Any]:
        return {"train_episodes": None, "training_seeds": []}

    def describe(self) -> dict[str, Any]:
        return {"reference": self.method, "kw": dict(self.kw)}


def reference(env: str, robots: int, method: str, sensor: Any, **kw: Any) -> Reference:
    """seed -> searcher for random, greedy and the planners (true model, all robots' observations)."""
    return Reference(env, robots, method, sensor, tuple(sorted(kw.items())))


def cell_row(
    ctx: Context,
    env: str,
    robots: int,
    method: str,
    make: Team | Reference,
    episodes: int,
    seed: int = SEED,
    sensor: Any = None,
    withdraw_at: list[int | None] | None = None,
    latency: bool = False,
    times: bool = False,
) -> dict[str, Any]:
    """One evaluated cell: capture time and false alarms (mean, 95% CI) over ``episodes`` seeded
    episodes; with ``latency``, the decision time per team step, one episode at a time (batch 1,
    so batching does not hide the per-step latency; the simulator's step included); with
    ``times``, the (episodes,) capture times under "capture_times" (for paired comparisons).

    A cell is evaluated once: its row is cached under <results>/cells/ by what determines it (the
    map, N, the method and its team's weights or the planner's settings, the sensor, the episodes
    and seed, a withdrawal). While planning, a cell whose team exists becomes a job for the
    parallel runner (``cell_job``) and a placeholder row is returned."""
    from shared.core.models import Sensor

    sensor = sensor or Sensor()
    nan = float("nan")
    placeholder = {
        "map": env,
        "robots": robots,
        "method": method,
        "mean_capture_time": nan,
        "ci95_halfwidth": nan,
        "false_alarms_per_episode": nan,
        "false_alarms_ci95_halfwidth": nan,
    }
    args = {
        "env": env,
        "robots": robots,
        "method": method,
        "episodes": episodes,
        "seed": seed,
        "sensor": sensor.to_json(),
        "withdraw_at": withdraw_at,
        "latency": latency,
    }
    withdrawn = f", withdrawn {withdraw_at}" if withdraw_at else ""
    team = f", team {make.path.name}" if isinstance(make, Team) else ""  # fig5 flies several teams of one method
    label = (
        f"evaluating {method} {env} N={robots}{noise_label(sensor.eta_fn, sensor.eta_fp)}{withdrawn} "
        f"({episodes} episodes){team}"
    )
    if not make.ready():  # planning: its team is not trained yet
        later = json.dumps({**args, "team": str(getattr(make, "path", ""))}, sort_keys=True)
        ctx.later[later] = (f"{label}, once its team exists", cell_cost(method, args, make))
        return placeholder
    what = {**args, "make": make.describe(), "version": CELL_VERSION}
    if latency and method not in PLANNERS:  # a planner's is timed on its own episodes
        what["timed_team_steps"] = TIMED_TEAM_STEPS
    key = hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:20]
    cached = None if ctx.cells is None else ctx.cells / f"{key}.json"
    if cached is not None and cached.exists():
        row = json.loads(cached.read_text())
    elif ctx.jobs is not None:
        files = None
        if isinstance(make, Team):  # the worker gets the snapshot's files, not this process's objects
            files = directory_files(make.path, make.path)
            make = Team(make.path, make.env, make.sensor, make.robots)
        weight = cell_cost(method, args, make)
        ctx.jobs.append(Job(f"cell-{key}", label, cell_job, (key, args, make, files), weight=weight, reports=True))
        return placeholder
    else:
        row = evaluate_cell(make=make, **args)
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(cached, json.dumps(row).encode())
    out = {k: v for k, v in row.items() if k != "capture_times"}
    if isinstance(make, Team):  # the row names its team: results/snapshots/<team> flies it again
        out["team"] = make.path.name
    if times:
        out["capture_times"] = np.asarray(row["capture_times"], dtype=np.float64)
    return out


def cell_job(
    key: str, args: dict[str, Any], make: Any, files: dict[str, bytes] | None, progress: Any = None
) -> dict[str, bytes]:
    """A cell evaluated by a worker: a team's snapshot comes as its files (no shared file system)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        if files is not None:
            for rel, data in files.items():
                (Path(tmp) / rel).write_bytes(data)
            make = Team(Path(tmp), make.env, make.sensor, make.robots)
        row = evaluate_cell(make=make, **args, progress=progress)
    return {f"cells/{key}.json": json.dumps(row).encode()}


def evaluate_cell(
    env: str,
    robots: int,
    method: str,
    make: Team | Reference,
    episodes: int,
    seed: int,
    sensor: dict[str, Any],
    withdraw_at: list[int | None] | None,
    latency: bool,
    progress: Any = None,
) -> dict[str, Any]:
    """A cell's row (``cell_row``), with its capture times; ``progress`` is told of each chunk of
    episodes (``evaluate``'s)."""
    from shared.core.graph import builtin_graph
    from shared.core.models import Sensor, uniform_walk
    from shared.engine.evaluate import evaluate, mean_ci95

    g = builtin_graph(env)
    sens = Sensor(**sensor)
    t0 = time.perf_counter()
    batched = method not in PLANNERS  # planners plan one episode at a time
    res = evaluate(
        g,
        uniform_walk(g),
        sens,
        robots,
        make,
        episodes=episodes,
        seed=seed,
        chunk=4096 if batched else 1,
        withdraw_at=withdraw_at,
        progress=progress,
    )
    wall = time.perf_counter() - t0
    s = res.summary()
    fa, fa_half = mean_ci95(res.false_alarms)
    row = {
        "map": env,
        "robots": robots,
        "method": method,
        "eta_fn": sens.eta_fn,
        "eta_fp": sens.eta_fp,
        "detection": sens.detection,
        "episodes": episodes,
        "seed": seed,
        **make.trained(),
        "mean_capture_time": round(s["mean_capture_time"], 3),
        "ci95_halfwidth": round(s["ci95_halfwidth"], 3),
        "censored_fraction": round(s["censored_fraction"], 4),
        "false_alarms_per_episode": round(fa, 4),
        "false_alarms_ci95_halfwidth": round(fa_half, 4),
        "team_steps": int(res.capture_time.sum()),
        "wall_seconds": round(wall, 2),
    }
    if latency:
        if batched:  # one episode at a time, about TIMED_TEAM_STEPS team steps in all
            timed = min(episodes, max(3, math.ceil(TIMED_TEAM_STEPS / max(1.0, s["mean_capture_time"]))))
            t1 = time.perf_counter()
            one = evaluate(g, uniform_walk(g), sens, robots, make, episodes=timed, seed=seed + 99, chunk=1)
            row["decision_ms"] = round((time.perf_counter() - t1) / max(1.0, float(one.capture_time.sum())) * 1e3, 4)
            row["timed_team_steps"] = int(one.capture_time.sum())
        else:  # planners already ran one episode at a time
            row["decision_ms"] = round(wall / max(1.0, float(res.capture_time.sum())) * 1e3, 4)
    row["capture_times"] = [int(x) for x in res.capture_time]
    return row


def paired_to_cepg(rows: list[dict[str, Any]], cepg: str = "cepg") -> list[dict[str, Any]]:
    """Rows with "capture_times" lose them and gain, where CE-PG's row (method ``cepg``) flew the
    same episodes, the paired difference (method - cepg) with its 95% CI over those episodes:
    ``diff_to_cepg`` and ``diff_to_cepg_ci95`` (negative: the method captures sooner than CE-PG)."""
    from shared.engine.evaluate import mean_ci95

    ref = next((r for r in rows if r["method"] == cepg and "capture_times" in r), None)
    out = []
    for r in rows:
        times = r.get("capture_times")
        r = {k: v for k, v in r.items() if k != "capture_times"}
        if ref is not None and times is not None and r["method"] != cepg:
            base = ref["capture_times"]
            same = (r["episodes"], r["seed"]) == (ref["episodes"], ref["seed"]) and len(times) == len(base) > 1
            if same:
                dm, dh = mean_ci95(np.asarray(times) - base)
                r.update(diff_to_cepg=round(dm, 3), diff_to_cepg_ci95=round(dh, 3))
        out.append(r)
    return out

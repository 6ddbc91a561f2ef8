"""The MARL baselines' own experiment: each at its default budget on OFFICE and WARD (N = 4) with
learning curves, against random and CE-PG, and a small hyperparameter sweep on OFFICE."""

from __future__ import annotations

import time
from pathlib import Path

import shared.tools.experiments.cells as cells
import shared.tools.experiments.plots as plots
import shared.tools.experiments.teams as teams
from shared.tools.experiments.budget import default_marl_episodes
from shared.tools.experiments.context import Context
from shared.tools.experiments.recording import figure_setup

# A small sweep per method around its defaults (one change at a time), at a tenth of the budget.
MARL_SWEEP: dict[str, list[tuple[str, ...]]] = {
    "mappo": [("lr=0.0003",), ("entropy=0.0",)],
    "masac": [("lr=0.001",), ("updates=8",)],
    "maddpg": [("lr=0.0003",), ("updates=8",)],
    "facmac": [("lr=0.0003",), ("updates=8",)],
    "mambpo": [("real_ratio=0.2",), ("updates=8",)],
}
MARL_MAPS = ("office", "ward")  # the paper's OFFICE and our WARD


def marl(ctx: Context) -> Path:
    """The MARL baselines at their default budgets on OFFICE and WARD, N = 4, with learning
    curves, against random and CE-PG; and a small hyperparameter sweep on OFFICE."""
    b = ctx.budget
    N, rows, curves, sweep = 4, [], {}, []
    sensor = teams.sensor_for("cepg")
    t_start = time.perf_counter()
    for env in MARL_MAPS:
        rnd = cells.reference(env, N, "random", sensor)
        rows.append(cells.cell_row(ctx, env, N, "random", rnd, b.episodes, latency=True))
        cepg = teams.learned_team(ctx, env, N, "cepg")
        rows.append(cells.cell_row(ctx, env, N, "cepg", cepg, b.episodes, latency=True))
        for m in b.marl_methods:
            summary = teams.training_summary(ctx, teams.marl_snapshot(ctx, env, N, m, b.marl_episodes(m), 0))
            row = cells.cell_row(ctx, env, N, m, teams.learned_team(ctx, env, N, m), b.episodes, latency=True)
            row.update(
                train_episodes=summary["episodes"],
                train_wall_seconds=summary["wall_seconds"],
                train_episodes_per_second=summary["episodes_per_second"],
            )
            rows.append(row)
            curves[f"{env}/{m}"] = summary["learning_curve"]
            took = f"{summary['episodes']:,} episodes, {summary['wall_seconds']:.0f} s"
            ctx.say(f"  marl: {env} {m} {row['mean_capture_time']:.2f} ({took})")
    for m in b.marl_methods:
        episodes = b.marl_train or max(1_000, default_marl_episodes(m) // 10)
        for overrides in [(), *MARL_SWEEP[m]]:
            path = teams.marl_snapshot(ctx, "office", N, m, episodes, 0, overrides=overrides)
            row = cells.cell_row(ctx, "office", N, m, teams.Team(path, "office", sensor, N), b.episodes)
            sweep.append({**row, "overrides": list(overrides) or ["defaults"], "train_episodes": episodes})
    wall = round(time.perf_counter() - t_start, 1)
    setup = figure_setup("marl", b, robots=N, maps=list(MARL_MAPS), wall_seconds=wall)
    ctx.record("marl", {**setup, "sweep": sweep, "learning_curves": curves}, rows, by_map=False)
    if not ctx.planned:
        plots.learning_curves(ctx.root / "marl" / "marl_curves.png", curves)
    return ctx.root / "marl"

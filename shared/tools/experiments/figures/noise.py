"""Fig. 9 and 10: CE-PG under a noisy sensor, teams trained and flown with each rate of misses
(eta_fn, Fig. 9: capture time) and of false alarms (eta_fp, Fig. 10: false alarms per episode)."""

from __future__ import annotations

from pathlib import Path

import shared.tools.experiments.cells as cells
import shared.tools.experiments.plots as plots
import shared.tools.experiments.teams as teams
from shared.tools.experiments.budget import ETAS
from shared.tools.experiments.context import Context
from shared.tools.experiments.recording import figure_setup


def noise_sweep(ctx: Context, name: str, eta: str, value: str, ylabel: str) -> Path:
    """CE-PG teams trained and flown with each ``eta`` ("eta_fn" or "eta_fp") of ETAS, the other 0."""
    b = ctx.budget
    rows = []
    for env in b.maps:
        for N in b.sizes(b.teams):
            for x in ETAS:
                team = teams.learned_team(ctx, env, N, "cepg", **{eta: x})
                sensor = teams.sensor_for("cepg", **{eta: x})
                rows.append(cells.cell_row(ctx, env, N, "cepg", team, b.episodes, sensor=sensor))
            ctx.say(f"{name}: {env} N={N}: " + ", ".join(f"{r[value]:.2f}" for r in rows[-len(ETAS) :]))
    rows = ctx.record(name, figure_setup(name, b), rows)
    if not ctx.planned:
        plots.lines_per_team_size(ctx.root / name / f"{name}.png", rows, eta, value, ylabel)
    return ctx.root / name


def fig9(ctx: Context) -> Path:
    """CE-PG's capture time for eta_fn in {0, 0.1, 0.3, 0.5} (eta_fp = 0), teams trained with that
    sensor (paper Fig. 9)."""
    return noise_sweep(ctx, "fig9", "eta_fn", "mean_capture_time", "capture time (steps)")


def fig10(ctx: Context) -> Path:
    """CE-PG's false alarms per episode (the team's total) for eta_fp in {0, 0.1, 0.3, 0.5}
    (eta_fn = 0), teams trained with that sensor (paper Fig. 10)."""
    return noise_sweep(ctx, "fig10", "eta_fp", "false_alarms_per_episode", "false alarms per episode")

"""Fig. 6: CE-PG against its variants CE-PG+ (each robot senses N[p]) and C-CE-PG (collective belief)."""

from __future__ import annotations

from pathlib import Path

import shared.tools.experiments.cells as cells
import shared.tools.experiments.plots as plots
import shared.tools.experiments.teams as teams
from shared.tools.experiments.context import Context
from shared.tools.experiments.recording import figure_setup

VARIANTS = ("cepg", "cepg+", "c-cepg")


def fig6(ctx: Context) -> Path:
    """CE-PG vs CE-PG+ (sensing N[p]) vs C-CE-PG (collective belief) for N in the sweep (paper Fig. 6)."""
    b = ctx.budget
    rows = []
    for env in b.maps:
        for N in b.sizes(b.teams):
            for m in VARIANTS:
                team = teams.learned_team(ctx, env, N, m)
                rows.append(cells.cell_row(ctx, env, N, m, team, b.episodes, sensor=teams.sensor_for(m)))
            said = ", ".join(f"{r['method']} {r['mean_capture_time']:.1f}" for r in rows[-len(VARIANTS) :])
            ctx.say(f"fig6: {env} N={N}: {said}")
    rows = ctx.record("fig6", figure_setup("fig6", b), rows)
    if not ctx.planned:
        plots.bars(ctx.root / "fig6" / "fig6.png", rows, "robots", "capture time (steps)")
    return ctx.root / "fig6"

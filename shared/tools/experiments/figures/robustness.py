"""Fig. 12 and 13: robustness to losing robots, one withdrawn during a search (Fig. 12) and a
5-robot team flown by fewer robots (Fig. 13)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import shared.tools.experiments.cells as cells
import shared.tools.experiments.plots as plots
import shared.tools.experiments.teams as teams
from shared.tools.experiments.context import Context
from shared.tools.experiments.recording import figure_setup


def fig12(ctx: Context) -> Path:
    """Robustness: a 4-robot team loses robot 4 at t = 5 (paper Fig. 12), against the intact team."""
    b = ctx.budget
    N, rows = 4, []
    sensor = teams.sensor_for("cepg")
    for env in b.maps:
        for withdraw in (None, [None, None, None, 5]):
            label = "none" if withdraw is None else "r4@t5"
            for m in ("random", "greedy", "pg", "cepg", *b.marl_methods):
                make = (
                    cells.reference(env, N, m, sensor)
                    if m in ("random", "greedy")
                    else teams.learned_team(ctx, env, N, m)
                )
                row = cells.cell_row(ctx, env, N, m, make, b.episodes, withdraw_at=withdraw)
                rows.append({**row, "withdrawn": label})
    rows = ctx.record("fig12", figure_setup("fig12", b), rows)
    if not ctx.planned:
        plots.bars(ctx.root / "fig12" / "fig12.png", rows, "withdrawn", "capture time (steps), N = 4")
    return ctx.root / "fig12"


def fig13(ctx: Context) -> Path:
    """Robustness: a team trained for 5 robots flown by k = 1..5 of them (paper Fig. 13), against
    teams trained for k. Each row's ``diff_to_cepg`` pairs it with CE-PG's team of the same
    training (trained for 5, or for k) on the same episodes."""
    b = ctx.budget
    methods = ("cepg", *b.marl_methods)
    rows = []
    sensor = teams.sensor_for("cepg")
    for env in b.maps:
        flown: dict[tuple[str, int, str], dict[str, Any]] = {}
        for m in methods:
            path = (
                teams.cepg_snapshot(ctx, env, 5, 0.5, b.train, 0)
                if m == "cepg"
                else teams.marl_snapshot(ctx, env, 5, m, b.marl_episodes(m), 0)
            )
            for k in range(1, 6):
                for trained, make in (
                    ("5", teams.Team(path, env, sensor, k)),
                    ("k", teams.learned_team(ctx, env, k, m)),
                ):
                    row = cells.cell_row(ctx, env, k, f"{m} trained for {trained}", make, b.episodes, times=True)
                    flown[trained, k, m] = {**row, "trained_for": 5 if trained == "5" else k}
        # every cell of a k flies the same episodes: each team's difference to CE-PG's of the same
        # training (for 5, or for k) is paired episode by episode
        for k in range(1, 6):
            for trained in ("5", "k"):
                group = [flown[trained, k, m] for m in methods]
                paired = cells.paired_to_cepg(group, cepg=f"cepg trained for {trained}")
                flown.update(((trained, k, m), r) for m, r in zip(methods, paired, strict=True))
        rows += [flown[trained, k, m] for m in methods for k in range(1, 6) for trained in ("5", "k")]
    rows = ctx.record("fig13", figure_setup("fig13", b), rows)
    if not ctx.planned:
        plots.bars(ctx.root / "fig13" / "fig13.png", rows, "robots", "capture time (steps)")
    return ctx.root / "fig13"

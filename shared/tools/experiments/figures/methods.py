"""Fig. 7, 8 and 11: every method of the paper's comparison, by team size (Fig. 7, with the decision
times of Fig. 8) and under the sensor's misses eta_fn (Fig. 11)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import shared.tools.experiments.cells as cells
import shared.tools.experiments.plots as plots
import shared.tools.experiments.teams as teams
from shared.tools.experiments.budget import ETAS, LEARNED, PLANNERS
from shared.tools.experiments.context import Context
from shared.tools.experiments.recording import figure_setup, planner_setup


def all_methods(ctx: Context, env: str, N: int, eta_fn: float = 0.0) -> list[dict[str, Any]]:
    """Every method of the paper's comparison on one (map, N, eta_fn), with decision times.

    random, greedy and the learned teams fly the same ``b.episodes`` episodes (one batch, seed
    SEED: the target's path and every random draw of an episode do not depend on the robots'
    moves), so each one's difference to CE-PG is paired episode by episode: ``paired_to_cepg``."""
    b = ctx.budget
    sensor = teams.sensor_for("cepg", eta_fn)
    rows = [
        cells.cell_row(
            ctx, env, N, m, cells.reference(env, N, m, sensor), b.episodes, sensor=sensor, latency=True, times=True
        )
        for m in ("random", "greedy")
    ]
    for m in (*LEARNED, *b.marl_methods):
        team = teams.learned_team(ctx, env, N, m, eta_fn)
        sensed = teams.sensor_for(LEARNED[m][0] if m in LEARNED else "cepg", eta_fn)
        rows.append(cells.cell_row(ctx, env, N, m, team, b.episodes, sensor=sensed, latency=True, times=True))
    rows = cells.paired_to_cepg(rows)
    for m in PLANNERS:
        if m == "fhpe" and N > 3:
            continue  # 36^4 joint paths and more per decision: see the report
        kw = {"time_limit": b.milp_limit} if "milp" in m else {}
        planner = cells.reference(env, N, m, sensor, **kw)
        rows.append(cells.cell_row(ctx, env, N, m, planner, b.planner_episodes(m), sensor=sensor, latency=True))
    if N <= 2:
        oracle = cells.reference(env, N, "oracle", sensor)
        rows.append(cells.cell_row(ctx, env, N, "oracle", oracle, b.episodes, sensor=sensor, latency=True))
    ctx.say(f"  {env} N={N} eta_fn={eta_fn}: " + ", ".join(f"{r['method']} {r['mean_capture_time']:.1f}" for r in rows))
    return rows


def fig7(ctx: Context) -> Path:
    """All methods, N = 1..5, OFFICE and MUSEUM (paper Fig. 7), and their decision times (Fig. 8)."""
    b = ctx.budget
    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    for env in b.maps:
        for N in b.sizes(range(1, 6)):
            ctx.say(f"fig7: {env} N={N}")
            rows += all_methods(ctx, env, N)
    setup = figure_setup(
        "fig7",
        b,
        team_sizes=list(b.sizes(range(1, 6))),
        **planner_setup(b),
        horizons={"fhpe": 2, "fhpe-sa": 5, "milp": 5, "d-milp": 5},
        discount=0.97,
        wall_seconds=round(time.perf_counter() - t_start, 1),
    )
    rows = ctx.record("fig7", setup, rows)
    if not ctx.planned:
        plots.team_size_lines(
            ctx.root / "fig7" / "fig7.png", rows, "mean_capture_time", "capture time (steps)", half="ci95_halfwidth"
        )
        fig8(ctx, rows, setup)
    return ctx.root / "fig7"


def fig8(ctx: Context, rows: list[dict[str, Any]], setup: dict[str, Any]) -> None:
    """Fig. 8 from fig7's rows: the decision time per team step of each method."""
    timed = [{k: r[k] for k in ("map", "robots", "method", "decision_ms")} for r in rows]
    about = {
        "experiment": "fig8",
        "from": "fig7",
        "quick": setup["quick"],
        "machine": setup["machine"],
        "note": "ms per team step, one episode at a time, simulator step included",
    }
    ctx.record("fig8", about, timed, by_map=False)
    plots.team_size_lines(
        ctx.root / "fig8" / "fig8.png", timed, "decision_ms", "decision time per team step (ms)", log=True
    )


def fig11(ctx: Context) -> Path:
    """All methods at N = 4 for eta_fn in {0, 0.1, 0.3, 0.5} (paper Fig. 11)."""
    b = ctx.budget
    rows = []
    t_start = time.perf_counter()
    for env in b.maps:
        for eta in ETAS:
            rows += all_methods(ctx, env, 4, eta_fn=eta)
    wall = round(time.perf_counter() - t_start, 1)
    rows = ctx.record("fig11", figure_setup("fig11", b, robots=4, **planner_setup(b), wall_seconds=wall), rows)
    if not ctx.planned:
        plots.bars(ctx.root / "fig11" / "fig11.png", rows, "eta_fn", "capture time (steps), N = 4")
    return ctx.root / "fig11"

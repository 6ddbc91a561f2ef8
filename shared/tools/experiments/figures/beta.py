"""Fig. 5: CE-PG's beta of Eq. 9 (N = 4), teams of several training seeds flown on the same episodes."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

import shared.tools.experiments.cells as cells
import shared.tools.experiments.plots as plots
import shared.tools.experiments.teams as teams
from shared.tools.experiments.budget import BETAS, SEED, Budget
from shared.tools.experiments.context import Context
from shared.tools.experiments.recording import figure_setup


def fig5(ctx: Context) -> Path:
    """beta in {0.1, 0.3, 0.5, 0.7, 0.9} and 1 (PG) for a 4-robot team on OFFICE and MUSEUM (paper
    Fig. 5), a team per training seed of ``b.seeds``. Every team is flown on the same evaluation
    episodes (seed SEED), so a beta's team and the PG team of the same training seed meet the same
    target paths: their difference is paired episode by episode. Each row: the capture time pooled
    over the seeds' episodes, each seed's mean, and the paired difference to beta = 1 with two 95%
    CIs, over the pooled episodes (evaluation noise only) and over the training seeds (Student t,
    S - 1 degrees of freedom: what another training run would give)."""
    b = ctx.budget
    N, rows = 4, []
    for env in b.maps:
        rows += fig5_rows(ctx, env, N)
        said = ", ".join(f"beta {r['beta']} {r['mean_capture_time']:.2f}" for r in rows[-len(BETAS) :])
        ctx.say(f"fig5: {env}: {said}")
    rows = ctx.record("fig5", figure_setup("fig5", b, robots=N, training_seeds=list(b.seeds)), rows)
    if not ctx.planned:
        plots.bars(ctx.root / "fig5" / "fig5.png", rows, "beta", "capture time (steps), N = 4")
    return ctx.root / "fig5"


def fig5_rows(ctx: Context, env: str, N: int = 4) -> list[dict[str, Any]]:
    """fig5's rows of one map, a row per beta (``fig5``), its teams trained first where missing."""
    b = ctx.budget
    sensor = teams.sensor_for("cepg")
    times: dict[tuple[float, int], np.ndarray] = {}
    trained: dict[float, Any] = {}  # the episodes the teams ran (whole batches), as the cells say
    flown: dict[float, list[dict[str, Any]]] = {beta: [] for beta in BETAS}
    for beta in BETAS:
        for s in b.seeds:
            team = teams.Team(teams.cepg_snapshot(ctx, env, N, beta, b.train, s), env, sensor, N)
            row = cells.cell_row(ctx, env, N, "pg" if beta == 1.0 else "cepg", team, b.episodes, times=True)
            times[beta, s] = row.pop("capture_times", np.zeros(0))
            trained[beta] = row.get("train_episodes", b.train)
            flown[beta].append(row)
    return [
        {
            **beta_row(env, N, beta, b, None if ctx.planned else times),
            "train_episodes": trained[beta],
            "teams": [c.get("team") for c in flown[beta]],  # one per training seed
            "wall_seconds": round(sum(c.get("wall_seconds", 0.0) for c in flown[beta]), 2),
        }
        for beta in BETAS
    ]


def beta_row(
    env: str, N: int, beta: float, b: Budget, times: dict[tuple[float, int], np.ndarray] | None
) -> dict[str, Any]:
    """fig5's row of one beta from the capture times of every (beta, training seed) team (None:
    a planned run's placeholder)."""
    from scipy.stats import t as student_t

    from shared.engine.evaluate import mean_ci95

    nan = float("nan")
    row: dict[str, Any] = {
        "map": env,
        "robots": N,
        "method": "pg" if beta == 1.0 else "cepg",
        "beta": beta,
        "train_episodes": b.train,
        "training_seeds": list(b.seeds),
        "episodes": b.episodes,
        "seed": SEED,
    }
    if times is None:
        return {**row, "mean_capture_time": nan, "ci95_halfwidth": nan}
    pooled = np.concatenate([times[beta, s] for s in b.seeds])
    m, h = mean_ci95(pooled)
    row.update(
        mean_capture_time=round(m, 3),
        ci95_halfwidth=round(h, 3),
        per_seed_mean=[round(float(times[beta, s].mean()), 3) for s in b.seeds],
    )
    if beta != 1.0:
        diffs = [times[beta, s] - times[1.0, s] for s in b.seeds]  # same episodes, same target paths
        dm, dh = mean_ci95(np.concatenate(diffs))
        seed_means = np.array([d.mean() for d in diffs])
        S = len(seed_means)
        sh = float(student_t.ppf(0.975, S - 1) * seed_means.std(ddof=1) / np.sqrt(S)) if S > 1 else nan
        row.update(
            diff_to_pg=round(dm, 3),
            diff_to_pg_ci95_episodes=round(dh, 3),
            diff_to_pg_ci95_seeds=round(sh, 3),
            diff_to_pg_per_seed=[round(float(x), 3) for x in seed_means],
        )
    return row

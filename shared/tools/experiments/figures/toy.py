"""Fig. 4: the paper's toy (two robots, one step, A with 0.6, B with 0.4)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.tools.experiments.context import Context
from shared.tools.experiments.plots import pyplot
from shared.tools.experiments.recording import machine
from shared.tools.toy import toy_fig4


def fig4(ctx: Context) -> Path:
    """The toy of paper Fig. 4: P(A) of both robots over updates, CE-PG (beta 0.5) vs PG (beta 1)."""
    plt = pyplot()
    quick = ctx.budget.quick
    seeds = range(3 if quick else 10)
    updates = 150 if quick else 400
    rows = []
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    for ax, beta in zip(axes, (0.5, 1.0), strict=True):
        for s in seeds:
            run = toy_fig4(beta, seed=s, updates=updates, reward="own")
            pa = np.asarray(run.p_a)
            ax.plot(pa[:, 0], color="C0", alpha=0.5)
            ax.plot(pa[:, 1], color="C1", alpha=0.5)
            split = bool(max(pa[-1]) >= 0.9 and min(pa[-1]) <= 0.1)
            rows.append(
                {
                    "beta": beta,
                    "seed": s,
                    "updates": updates,
                    "p_a_robot1": round(float(pa[-1, 0]), 4),
                    "p_a_robot2": round(float(pa[-1, 1]), 4),
                    "split": split,
                }
            )
        ax.set_title(f"{'CE-PG' if beta < 1 else 'PG'} (beta = {beta})")
        ax.set_xlabel("update")
    axes[0].set_ylabel("P(go to A)")
    fig.tight_layout()
    out = ctx.root / "fig4"
    ctx.record(
        "fig4", {"experiment": "fig4", "quick": quick, "reward": "own", "machine": machine()}, rows, by_map=False
    )
    fig.savefig(out / "fig4.png", dpi=110)
    plt.close(fig)
    return out

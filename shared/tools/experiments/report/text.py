"""How the report states a figure's setup (its runs, budgets, cost) and its numbers."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from shared.tools.experiments.budget import MARL_OWN
from shared.tools.experiments.costs import duration
from shared.tools.experiments.recording import describe_pairs
from shared.tools.experiments.teams import training_summary


def fmt_ci(mean: float, half: float, episodes: int) -> str:
    """mean ± CI half-width; a cell of fewer than 2 episodes has no CI and says how many it had."""
    if episodes < 2 or not math.isfinite(half):
        return f"{mean:.2f} ({episodes} ep.)"
    return f"{mean:.2f} ± {half:.2f}"


def runs_of(setup: dict[str, Any]) -> list[dict[str, Any]]:
    """The runs a figure's rows come from, when more than one (`--add`; ``_merge``), else []."""
    parts = setup.get("parts") or []
    return parts if len(parts) > 1 else []


def trained_for(setup: dict[str, Any]) -> str:
    """The learned teams' training budget as a setup states it."""
    return "the budget of each run below" if runs_of(setup) else f"{setup['training_episodes']:,} episodes"


def runs_lines(setup: dict[str, Any]) -> list[str]:
    """A figure recorded in several runs: what each covers and at which budgets."""
    runs = runs_of(setup)
    if not runs:
        return []
    said = []
    for p in runs:
        where = describe_pairs(p["covers"])
        planners = (
            f", planners {p['planner_episodes']} (fhpe-sa {p['fhpe_sa_episodes']}, d-milp "
            f"{p.get('d_milp_episodes', p['planner_episodes'])})"
            if "planner_episodes" in p
            else ""
        )
        said.append(
            f"{where}: learned teams trained for {p['training_episodes']:,} episodes, MARL baselines "
            f"{marl_budget(p)}; {p['episodes']} episodes per cell{planners}; quick={p['quick']}; "
            f"{p['machine']['date']}"
        )
    return [
        f"Recorded in {len(runs)} runs (`--add`), each row with its own training budget (train_episodes in the "
        "data): " + "; and ".join(said) + ".",
        "",
    ]


def marl_budget(setup: dict[str, Any]) -> str:
    """The MARL baselines' training budget as a setup states it (older results have none)."""
    if runs_of(setup):
        return "the budget of each run below"
    given = setup.get("marl_training_episodes")
    if given is None:
        return "(not recorded)"
    by = setup.get("marl_training_episodes_by_method") or {}
    if isinstance(given, int):
        said = f"{given:,} episodes"
    elif given == MARL_OWN:
        said = "each method's own budget"
    elif by:
        said = "each method's default budget"
    else:  # files from before the setup listed the defaults: they were other budgets then
        said = "each method's default budget when recorded (each row's training episodes)"
    return said + (" (" + ", ".join(f"{m.upper()} {e:,}" for m, e in by.items()) + ")" if by else "")


def cost_line(root: Path, rows: list[dict[str, Any]]) -> str:
    """What a figure cost on the machines that made it: its cells' evaluation and the training of the
    teams its rows name (each team once, from its snapshot's wall time in ``root``'s cache)."""
    said = f"evaluating the cells of its {len(rows)} rows {duration(sum(r.get('wall_seconds', 0.0) for r in rows))}"
    teams = {t for r in rows for t in (r.get("teams") or [r.get("team")]) if t}
    snaps = [root / "snapshots" / t for t in sorted(teams)]
    walls = [float(training_summary(None, d).get("wall_seconds", 0.0)) for d in snaps if (d / "policy.json").exists()]
    if teams:
        cached = "" if len(walls) == len(teams) else f" ({len(walls)} of them in the cache)"
        said += f"; training the {len(teams)} teams its rows name{cached} {duration(sum(walls))}"
    unnamed = sum(1 for r in rows if r.get("train_episodes") is not None and not ({"team", "teams"} & r.keys()))
    if unnamed:
        said += f"; {unnamed} learned rows were recorded before rows named their team, their training not counted"
    return f"Cost (wall time, one core a job, often beside another job): {said}."


def team_size_table(
    rows: list[dict[str, Any]], env: str, methods: list[str], cell: Callable[[dict[str, Any]], str]
) -> list[str]:
    """A markdown table of one map's rows: a line per method, a column per team size N, ``cell(row)``
    in each (— where the method has no row at that N)."""
    Ns = sorted({r["robots"] for r in rows if r["map"] == env})
    out = ["| method | " + " | ".join(f"N={n}" for n in Ns) + " |", "| --- |" + " --- |" * len(Ns)]
    for m in methods:
        at: dict[int, dict[str, Any]] = {}
        for r in rows:
            if r["map"] == env and r["method"] == m:
                at.setdefault(r["robots"], r)  # the first row of a size, as the figure's own order
        out.append(f"| {m} | " + " | ".join(cell(at[n]) if n in at else "—" for n in Ns) + " |")
    return out

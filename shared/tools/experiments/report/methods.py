"""The report's sections on Fig. 7 (every method's capture time by team size, and its reading
against CE-PG) and Fig. 8 (their decision times)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from shared.tools.experiments.budget import PAPER_MAPS
from shared.tools.experiments.cells import TIMED_TEAM_STEPS
from shared.tools.experiments.recording import maps_in
from shared.tools.experiments.report.readings import fig7_reading, training_spread
from shared.tools.experiments.report.text import (
    cost_line,
    marl_budget,
    runs_lines,
    runs_of,
    team_size_table,
    trained_for,
)


def section(root: Path, rel: str) -> list[str]:
    """Fig. 7's and Fig. 8's sections; ``rel``: the results directory relative to the report."""
    f7 = root / "fig7" / "fig7.json"
    if not f7.exists():
        return []
    d = json.loads(f7.read_text())
    return [*fig7_section(root, rel, d), "", *fig8_section(rel, d)]


def fig7_section(root: Path, rel: str, d: dict[str, Any]) -> list[str]:
    """Fig. 7 from its recorded data ``d``: the setup, a table per map, the reading."""
    rows = d["rows"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lines = [
        f"## Fig. 7: capture time of all methods, N = {', '.join(map(str, sorted({r['robots'] for r in rows})))}",
        "",
        f"Setup: {d['episodes']} episodes per cell for random, greedy, the learned teams and oracle; "
        f"{d['planner_episodes']} for fhpe and milp, {d.get('d_milp_episodes', d['planner_episodes'])} for "
        f"d-milp, {d['fhpe_sa_episodes']} for fhpe-sa "
        f"(planners are slow; see Fig. 8); seed {d['seed']}; learned teams trained for "
        f"{trained_for(d)} with EM-estimated beliefs (Gamma_hat_0 = I); horizons "
        f"{d['horizons']}, discount {d['discount']}, MILP time limit {d['milp_time_limit_s']} s per solve "
        f"(HiGHS); quick={d['quick']}; {d['machine']['cpus']} CPUs, {d['machine']['date']}; maps "
        f"{', '.join(m.upper() for m in d.get('maps', PAPER_MAPS))}, N = "
        f"{', '.join(str(n) for n in d.get('team_sizes', range(1, 6)))}; the last run, its cells cached "
        f"or not, took {d['wall_seconds']:.0f} s. "
        "MARL baselines (maddpg, masac, facmac, mambpo, mappo) trained "
        f"for {marl_budget(d)} with EM-estimated beliefs, executed decentralised as CE-PG.",
        "",
        *runs_lines(d),
        "The planners (fhpe, fhpe-sa, milp, d-milp) and the oracle get the true target model and see all "
        "robots' observations (centralised); pg, cepg and cepg+ robots use only their own observations "
        "and an estimated model (cepg+ robots sense N[p], a broader field of view than the others' "
        "node); c-cepg robots share all observations (collective belief); oracle robots see the target "
        "(a lower bound, exact DP, N <= 2 only). fhpe is not run for N > 3: the joint paths per decision "
        "exceed 10^6.",
        "",
        cost_line(root, rows),
        "",
    ]

    def capture(r: dict[str, Any]) -> str:
        half = f" ± {r['ci95_halfwidth']:.1f}" if math.isfinite(r["ci95_halfwidth"]) else ""
        return f"{r['mean_capture_time']:.1f}{half} ({r['episodes']})"

    for env in maps_in(rows):
        lines += [f"### {env.upper()} (mean capture time ± 95% CI half-width, episodes)", ""]
        lines += [*team_size_table(rows, env, methods, capture), ""]
    lines += [
        f"![fig7]({rel}/fig7/fig7.png)",
        "",
        "### Reading (computed from the table)",
        "",
        (
            "CE-PG's teams here were trained for the budget of each run above (every row states its own), "
            "the paper's 400,000 episodes or less; the MARL baselines likewise"
            if runs_of(d)
            else f"CE-PG's teams here were trained for {d['training_episodes']:,} episodes, "
            f"{100 * d['training_episodes'] / 400_000:.1f}% of the paper's budget of 400,000; the MARL "
            f"baselines for {marl_budget(d)}"
        )
        + (
            ", and the planners ran on one to four episodes: a quick run, not the paper's protocol."
            if d["quick"]
            else "."
        ),
        "",
    ]
    lines += [
        "CE-PG is compared with each method flown on the same episodes (random, greedy, the learned "
        "teams) by the paired difference, method - cepg, and its 95% CI over those episodes; with the "
        "planners, which fly fewer episodes one at a time, by non-overlapping 95% CIs.",
        "",
    ]
    lines += training_spread(root, d)
    lines += fig7_reading(rows)

    return lines


def fig8_section(rel: str, d: dict[str, Any]) -> list[str]:
    """Fig. 8 from fig7's recorded data ``d``: decision times per map, and their ratios to CE-PG's."""
    rows = d["rows"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lines = [
        "## Fig. 8: decision time per team step",
        "",
        "Milliseconds per team step, one episode at a time (batch 1), the simulator's step included "
        "(about 0.1 ms), measured as Fig. 7's cells ran: a planner's over its cell's episodes, the "
        f"others' over extra episodes of about {TIMED_TEAM_STEPS} team steps in all (a row's "
        "timed_team_steps; rows without it were timed on three episodes, a few dozen steps at N = 5). "
        "The paper shows MUSEUM.",
    ]
    for env in maps_in(rows):
        lines += ["", f"{env.upper()}:", ""]
        lines += team_size_table(rows, env, methods, lambda r: f"{r['decision_ms']:.3g}")
        r4 = {r["method"]: r for r in rows if r["map"] == env and r["robots"] == 4}
        if "cepg" in r4:
            ratios = [
                f"{m} / cepg = {r4[m]['decision_ms'] / r4['cepg']['decision_ms']:.0f}x"
                for m in ("fhpe-sa", "milp", "d-milp")
                if m in r4
            ]
            lines += ["", f"Decision-time ratios at N = 4 on {env.upper()}: {', '.join(ratios)}."]
    lines += [
        "",
        f"HiGHS stops each MILP solve at {d['milp_time_limit_s']} s (d-milp solves once per robot), so "
        "the MILPs' times here are bounded by that limit, not by what an optimal solve would take.",
    ]
    lines += ["", f"![fig8]({rel}/fig8/fig8.png)", ""]
    return lines

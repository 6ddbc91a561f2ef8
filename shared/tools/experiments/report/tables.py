"""The report's sections on the figures recorded as tables (Fig. 5, 6 and 9 to 13): the setup, a
table per map, and each figure's reading against the paper's claims."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

from shared.tools.experiments.budget import MARL
from shared.tools.experiments.recording import maps_in
from shared.tools.experiments.report.readings import (
    beta_reading,
    dropout_reading,
    ranking_reading,
    trend_reading,
    unmoved_reading,
    variants_reading,
    withdrawal_reading,
)
from shared.tools.experiments.report.text import cost_line, fmt_ci, marl_budget, runs_lines, trained_for

Rows = list[dict[str, Any]]


class Table(NamedTuple):
    """How a figure is tabled: a line per ``row_key``, a column per ``key``, ``value`` ± ``half``
    in each cell; ``note`` adds to the setup; ``reading`` (one map's rows, the table, the results
    directory) says what the table shows against the paper."""

    fig: str
    title: str
    row_key: str
    key: str
    value: str
    half: str
    note: str
    reading: Callable[[Rows, Table, Path], list[str]]


CAPTURE = ("mean_capture_time", "ci95_halfwidth")
FALSE_ALARMS = ("false_alarms_per_episode", "false_alarms_ci95_halfwidth")
TABLES = (
    Table(
        "fig5",
        "Fig. 5: beta of Eq. 9 (N = 4; beta = 1 is PG)",
        "method",
        "beta",
        *CAPTURE,
        "",
        lambda rows, t, root: beta_reading(rows),
    ),
    Table(
        "fig6",
        "Fig. 6: CE-PG vs CE-PG+ vs C-CE-PG",
        "method",
        "robots",
        *CAPTURE,
        "CE-PG+ robots sense N[p] (their own, broader field of view); C-CE-PG robots share every observation "
        "(collective belief); CE-PG robots sense their node and use their own observations.",
        lambda rows, t, root: variants_reading(rows, root),
    ),
    Table(
        "fig9",
        "Fig. 9: eta_fn and CE-PG's capture time (eta_fp = 0)",
        "robots",
        "eta_fn",
        *CAPTURE,
        "Each team is trained and flown with that sensor.",
        lambda rows, t, root: trend_reading(rows, t.key, t.value, t.half),
    ),
    Table(
        "fig10",
        "Fig. 10: eta_fp and CE-PG's false alarms per episode (eta_fn = 0)",
        "robots",
        "eta_fp",
        *FALSE_ALARMS,
        "False alarms: the team's total number of z = 1 readings with the target outside D(p), per episode.",
        lambda rows, t, root: trend_reading(rows, t.key, t.value, t.half) + unmoved_reading(rows, t.key),
    ),
    Table(
        "fig11",
        "Fig. 11: all methods under eta_fn (N = 4)",
        "method",
        "eta_fn",
        *CAPTURE,
        "Planners know eta_fn (their capture probability is (1 - eta_fn) per detection) and see all robots' "
        "observations; fhpe is not run at N = 4; cepg+ senses N[p].",
        lambda rows, t, root: ranking_reading(rows),
    ),
    Table(
        "fig12",
        "Fig. 12: one robot withdrawn during execution (N = 4)",
        "method",
        "withdrawn",
        *CAPTURE,
        "",
        lambda rows, t, root: withdrawal_reading(rows),
    ),
    Table(
        "fig13",
        "Fig. 13: a team trained for 5 robots, flown by k of them",
        "method",
        "robots",
        *CAPTURE,
        "",
        lambda rows, t, root: dropout_reading(rows),
    ),
)


def sections(root: Path, rel: str) -> list[str]:
    """The sections of the tabled figures recorded under ``root``; ``rel``: ``root`` relative to the report."""
    lines: list[str] = []
    for t in TABLES:
        f = root / t.fig / f"{t.fig}.json"
        if f.exists():
            lines += section(root, rel, t, json.loads(f.read_text()))
    return lines


def section(root: Path, rel: str, t: Table, d: dict[str, Any]) -> list[str]:
    """One tabled figure's section from its recorded data ``d``."""
    rows = d["rows"]
    lines = [
        f"## {t.title}",
        "",
        f"Setup: {d['episodes']} episodes per cell, seed {d['seed']}; learned teams "
        f"trained for {trained_for(d)}; "
        # fig13's methods are "maddpg trained for 5" and the like
        + (f"MARL baselines: {marl_budget(d)}; " if any(r["method"].split()[0] in MARL for r in rows) else "")
        + f"quick={d['quick']}; {d['machine']['date']}. "
        + (
            f"Planners: {d['planner_episodes']} episodes (fhpe-sa {d['fhpe_sa_episodes']}, d-milp "
            f"{d.get('d_milp_episodes', d['planner_episodes'])}), MILP time limit "
            f"{d['milp_time_limit_s']} s per solve. "
            if "planner_episodes" in d
            else ""
        )
        + t.note,
        "",
        *runs_lines(d),
        cost_line(root, rows),
        "",
    ]
    for env in maps_in(rows):
        sel = [r for r in rows if r["map"] == env]
        lines += [*table(sel, env, t), "", *t.reading(sel, t, root)]
    return [*lines, f"![{t.fig}]({rel}/{t.fig}/{t.fig}.png)", ""]


def table(rows: Rows, env: str, t: Table) -> list[str]:
    """One map's table: a line per ``t.row_key``, a column per ``t.key`` (— where no row has both)."""
    groups = list(dict.fromkeys(r[t.key] for r in rows))
    labels = list(dict.fromkeys(r[t.row_key] for r in rows))
    head = "N" if t.row_key == "robots" else t.row_key
    lines = [
        f"{env.upper()} ({t.value.replace('_', ' ')} ± 95% CI half-width):",
        "",
        f"| {head} | " + " | ".join(f"{t.key} {gk}" for gk in groups) + " |",
        "| --- |" + " --- |" * len(groups),
    ]
    for label in labels:
        said = []
        for gk in groups:
            r = next((x for x in rows if x[t.key] == gk and x[t.row_key] == label), None)
            said.append("—" if r is None else fmt_ci(r[t.value], r[t.half], r["episodes"]))
        lines.append(f"| {label} | " + " | ".join(said) + " |")
    return lines

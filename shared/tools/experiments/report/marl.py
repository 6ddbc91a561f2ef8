"""The report's section on the MARL baselines: budgets, capture times against random and CE-PG,
learning curves, the sweep, and teams trained past their budget."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from shared.tools.experiments.report.text import fmt_ci, marl_budget


def section(root: Path, rel: str) -> list[str]:
    """The MARL baselines' section: budgets, capture times against random and CE-PG, the sweep."""
    f = root / "marl" / "marl.json"
    if not f.exists():
        return []
    d = json.loads(f.read_text())
    rows, lines = d["rows"], []
    budget = marl_budget(d)
    lines += [
        "## The MARL baselines (N = 4, OFFICE and our WARD)",
        "",
        f"Setup: each method trained once (seed 0), {budget}, with EM-estimated beliefs as CE-PG's (CE-PG: "
        f"{d['training_episodes']:,} episodes); every team evaluated on {d['episodes']} episodes, seed {d['seed']}; "
        f"quick={d['quick']}; {d['machine']['cpus']} CPUs, {d['machine']['date']}. Training throughput is "
        "episodes per second of the whole run (EM included). "
        "Decision time: per team step, one episode at a time.",
        "",
        "| map | method | capture time | vs random | training episodes | training wall s | episodes/s | "
        "within 10% of final (episodes, s) | decision ms |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for env in d["maps"]:
        sel = [r for r in rows if r["map"] == env]
        rnd = next((r for r in sel if r["method"] == "random"), None)
        for r in sel:
            vs = (
                "—"
                if rnd is None or r is rnd
                else f"{100 * (1 - r['mean_capture_time'] / rnd['mean_capture_time']):+.0f} %"
            )
            reach = _plateau(d["learning_curves"].get(f"{env}/{r['method']}", []))
            trained = "—" if r.get("train_episodes") is None else f"{r['train_episodes']:,}"
            lines.append(
                f"| {env.upper()} | {r['method']} "
                f"| {fmt_ci(r['mean_capture_time'], r['ci95_halfwidth'], r['episodes'])} "
                f"| {vs} | {trained} "
                f"| {r.get('train_wall_seconds', '—')} | {r.get('train_episodes_per_second', '—')} "
                f"| {'—' if reach is None else f'{reach[0]:,}, {reach[1]:.0f}'} | {r.get('decision_ms', '—')} |"
            )
    lines += [
        "",
        '"vs random": how much sooner than random the team captures (negative: later). "Within 10% of final": '
        "the first point of the learning curve (training episodes' capture time, smoothed over 10 points) within "
        "10% of the smoothed value at the end of the run: where the curve flattens.",
        "",
        f"![marl curves]({rel}/marl/marl_curves.png)",
        "",
        "Sweep on OFFICE, N = 4, one change at a time from the defaults (each at the budget shown):",
        "",
        "| method | setting | training episodes | capture time |",
        "| --- | --- | --- | --- |",
    ]
    for r in d["sweep"]:
        lines.append(
            f"| {r['method']} | {', '.join(r['overrides'])} | {r['train_episodes']:,} "
            f"| {fmt_ci(r['mean_capture_time'], r['ci95_halfwidth'], r['episodes'])} |"
        )
    return [*lines, "", *plateau_tables(root)]


def _plateau(curve: list[dict[str, Any]], window: int = 10, within: float = 0.10) -> tuple[int, float] | None:
    """(episodes, wall seconds) of the first learning-curve point whose moving average over
    ``window`` points is within ``within`` of the last moving average; None for a short curve."""
    if len(curve) < 2 * window:
        return None
    ct = np.array([p["mean_capture_time"] for p in curve])
    smooth = np.convolve(ct, np.ones(window) / window, mode="valid")  # point k: mean of k .. k + window - 1
    final = smooth[-1]
    k = int(np.argmax(smooth <= final * (1 + within)))
    p = curve[k + window - 1]
    return int(p["episodes"]), float(p["wall_seconds"])


def plateau_tables(root: Path) -> list[str]:
    """Teams trained past their budget (benchmarks/marl_plateau.py -> marl/plateau*.json, one table
    a file: each file's teams are paired with its own reference team on the same episodes)."""
    files = sorted((root / "marl").glob("plateau*.json"), key=lambda f: (f.name != "plateau.json", f.name))
    return [line for f in files for line in _plateau_table(f)]


def _plateau_table(f: Path) -> list[str]:
    d = json.loads(f.read_text())
    ref = next(r for r in d["rows"] if r.get("reference"))
    lines = [
        f"### Past the budget: {d['map'].upper()}, N = {d['robots']} (marl/{f.name})",
        "",
        f"Teams of one method trained for growing budgets (seed {ref['training_seed']}), each flown on the same "
        f"{d['episodes']} episodes (seed {d['seed']}) as the reference, {ref['algorithm']} trained for "
        f"{ref['train_episodes']:,} episodes "
        f"({fmt_ci(ref['mean_capture_time'], ref['ci95_halfwidth'], d['episodes'])}); "
        "paired: team - reference over those episodes, 95% CI (negative: the team captures sooner). "
        "`python benchmarks/marl_plateau.py` made this table; its docstring has the training commands. "
        "Training curve: the team's capture time while it trained (exploring, on its training episodes) over the "
        "tenth of its run ending at the middle, and over the last tenth; still falling at the end means the "
        "budget was not yet its plateau. Paired vs shorter budget: the team - the same method's next shorter "
        "budget in this table, on the same episodes (where the file kept both teams' capture times); a longer "
        "budget that does not capture sooner than the shorter one is past the plateau.",
        "",
        "| method | training episodes | training wall s | capture time | paired vs reference "
        "| paired vs shorter budget | training curve: middle -> end |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]

    def said(x: float | None, digits: int = 2) -> str:
        return "—" if x is None else f"{x:.{digits}f}"

    for r in d["rows"]:
        paired = (
            "reference" if r.get("reference") else f"{r['diff_to_reference']:+.2f} ± {r['diff_to_reference_ci95']:.2f}"
        )
        shorter = (
            f"{r['diff_to_shorter_budget']:+.2f} ± {r['diff_to_shorter_budget_ci95']:.2f} "
            f"(vs {r['shorter_budget_episodes']:,})"
            if "diff_to_shorter_budget" in r
            else "—"
        )
        lines.append(
            f"| {r['algorithm']} | {r['train_episodes']:,} | {said(r['train_wall_seconds'], 0)} "
            f"| {fmt_ci(r['mean_capture_time'], r['ci95_halfwidth'], d['episodes'])} | {paired} | {shorter} "
            f"| {said(r.get('curve_at_half'))} -> {said(r.get('curve_at_end'))} |"
        )
    return [*lines, ""]

"""`mures experiment` and `mures report`: data, plots and a report generated from recorded data."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from shared.tools.cli import main
from shared.tools.experiments.report import report


def test_fig4_quick_and_report(tmp_path, capsys):
    res = tmp_path / "results"
    assert main(["experiment", "fig4", "--quick", "--results", str(res)]) == 0
    data = json.loads((res / "fig4" / "fig4.json").read_text())
    assert (res / "fig4" / "fig4.png").stat().st_size > 1000 and (res / "fig4" / "fig4.csv").exists()
    split = {b: sum(r["split"] for r in data["rows"] if r["beta"] == b) for b in (0.5, 1.0)}
    assert split[0.5] == 3 and split[1.0] == 0  # with own-meeting rewards CE-PG splits, PG does not
    out = tmp_path / "docs" / "results.md"
    assert main(["report", "--results", str(res), "--out", str(out)]) == 0
    text = out.read_text()
    assert "| 0.5 | 3 | 3 |" in text and "| 1.0 | 3 | 0 |" in text and "../results/fig4/fig4.png" in text


def test_report_reading_follows_the_numbers(tmp_path):
    rows = []
    for method, mean, half in (
        ("cepg", 10.0, 0.5),
        ("random", 26.0, 1.0),
        ("milp", 8.0, 0.5),
        ("greedy", 10.4, 0.6),
        ("oracle", 5.0, 0.2),
    ):
        rows.append(
            {
                "map": "office",
                "robots": 4,
                "method": method,
                "episodes": 100,
                "seed": 1,
                "mean_capture_time": mean,
                "ci95_halfwidth": half,
                "censored_fraction": 0.0,
                "team_steps": 1,
                "wall_seconds": 1.0,
                "decision_ms": 1.0,
            }
        )
    (tmp_path / "fig7").mkdir()
    setup = {
        "episodes": 100,
        "planner_episodes": 2,
        "fhpe_sa_episodes": 8,
        "seed": 1,
        "training_episodes": 10,
        "horizons": {},
        "discount": 0.97,
        "milp_time_limit_s": 1.0,
        "quick": True,
        "wall_seconds": 1.0,
        "machine": {"cpus": 2, "date": "today"},
    }
    (tmp_path / "fig7" / "fig7.json").write_text(json.dumps({**setup, "rows": rows}))
    text = report(tmp_path, tmp_path / "results.md").read_text()
    line = next(x for x in text.splitlines() if x.startswith("- OFFICE N=4"))
    assert "sooner than random 26.0" in line and "later than milp 8.0" in line
    assert "not separated from greedy 10.4" in line and "oracle bound 5.0" in line
    # flown on CE-PG's episodes, greedy is compared by its paired difference: here separated
    rows[3].update(diff_to_cepg=0.4, diff_to_cepg_ci95=0.3)
    (tmp_path / "fig7" / "fig7.json").write_text(json.dumps({**setup, "rows": rows}))
    line = next(x for x in report(tmp_path, tmp_path / "r.md").read_text().splitlines() if x.startswith("- OFFICE"))
    assert "sooner than random 26.0, greedy 10.4 (paired +0.40 ± 0.30)" in line
    # a team that captures exactly when CE-PG does in every episode (C-CE-PG at N = 1) is said so
    rows.append({**rows[0], "method": "c-cepg", "diff_to_cepg": 0.0, "diff_to_cepg_ci95": 0.0})
    (tmp_path / "fig7" / "fig7.json").write_text(json.dumps({**setup, "rows": rows}))
    line = next(x for x in report(tmp_path, tmp_path / "r.md").read_text().splitlines() if x.startswith("- OFFICE"))
    assert line.endswith("; the same capture time as CE-PG in every episode: c-cepg; oracle bound 5.0.")
    assert "not separated from c-cepg" not in line
    rows.pop()
    # a protocol run flies one team per method: with fig5's training seeds recorded, the reading
    # says how far a team moved with its training run there (not for quick runs, nor without fig5)
    from shared.tools.experiments.report.readings import training_spread

    assert "Each method here is one team" not in report(tmp_path, tmp_path / "r.md").read_text()
    assert training_spread(tmp_path, {"quick": False, "rows": []}) == []
    (tmp_path / "fig5").mkdir()
    per_seed = {"method": "cepg", "beta": 0.5, "training_seeds": [0, 1, 2], "diff_to_pg_per_seed": [-0.2, 0.9, 0.4]}
    one_seed = {**per_seed, "beta": 0.5, "training_seeds": [0], "diff_to_pg_per_seed": [0.3]}
    (tmp_path / "fig5" / "fig5.json").write_text(
        json.dumps({"rows": [{"map": "museum", **per_seed}, {"map": "office", **one_seed}]})
    )
    text = " ".join(training_spread(tmp_path, {"quick": False, "rows": [{"training_seeds": [0]}, {}]}))
    assert "one team (training seed 0)" in text
    assert "paired difference to PG ranges MUSEUM -0.20 to +0.90 over seeds [0, 1, 2];" in text
    assert "OFFICE" not in text and training_spread(tmp_path, {"quick": True, "rows": []}) == []


def test_fig8_tables_and_plots_every_map(tmp_path):
    """Decision times are reported for every map fig7 covers, in fig7's order, each with its own
    team sizes, and plotted one panel per map."""
    from shared.tools.experiments import QUICK, Context
    from shared.tools.experiments.figures.methods import fig8

    rows = [
        {"map": env, "robots": n, "method": m, "decision_ms": ms, "episodes": 10, "seed": 1}
        | {"mean_capture_time": 9.0, "ci95_halfwidth": 1.0, "censored_fraction": 0.0, "team_steps": 1}
        for env, sizes in (("office", (1, 4)), ("museum", (4,)))
        for n in sizes
        for m, ms in (("cepg", 1.0 * n), ("milp", 1000.0))
    ]
    setup = {"quick": True, "machine": {"cpus": 2, "date": "today"}, "milp_time_limit_s": 1.0, "seed": 1}
    setup |= {"episodes": 10, "planner_episodes": 2, "fhpe_sa_episodes": 8, "training_episodes": 10}
    setup |= {"horizons": {}, "discount": 0.97, "wall_seconds": 1.0}
    (tmp_path / "fig7").mkdir()
    (tmp_path / "fig7" / "fig7.json").write_text(json.dumps({**setup, "rows": rows}))
    fig8(Context(tmp_path, QUICK), rows, setup)
    assert len(json.loads((tmp_path / "fig8" / "fig8.json").read_text())["rows"]) == 6
    assert (tmp_path / "fig8" / "fig8.png").stat().st_size > 1000
    section = report(tmp_path, tmp_path / "results.md").read_text().split("## Fig. 8")[1].split("\n## ")[0]
    office, museum = section.index("OFFICE:"), section.index("MUSEUM:")
    assert office < museum
    assert "| method | N=1 | N=4 |" in section[office:museum] and "| method | N=4 |" in section[museum:]
    assert "| cepg | 1 | 4 |" in section[office:museum] and "| cepg | 4 |" in section[museum:]
    assert "OFFICE: milp / cepg = 250x" in section and "MUSEUM: milp / cepg = 250x" in section


def test_paired_differences_to_cepg_are_over_the_same_episodes():
    from shared.tools.experiments.cells import paired_to_cepg

    base = {"map": "office", "robots": 4, "seed": 1, "mean_capture_time": 0.0, "ci95_halfwidth": 0.0}
    rows = [
        {**base, "method": "cepg", "episodes": 4, "capture_times": np.array([3.0, 5.0, 7.0, 9.0])},
        {**base, "method": "pg", "episodes": 4, "capture_times": np.array([4.0, 6.0, 8.0, 10.0])},
        {**base, "method": "milp", "episodes": 2, "capture_times": np.array([1.0, 2.0])},
        {**base, "method": "fhpe-sa", "episodes": 8},
    ]
    out = paired_to_cepg(rows)
    assert all("capture_times" not in r for r in out)
    assert out[1]["diff_to_cepg"] == 1.0 and out[1]["diff_to_cepg_ci95"] == 0.0  # one step later in every episode
    assert "diff_to_cepg" not in out[0] and "diff_to_cepg" not in out[2] and "diff_to_cepg" not in out[3]


def test_fig6_reading_uses_fig7_paired_differences_where_it_has_them(tmp_path):
    """The variants against CE-PG: fig7's paired difference for the same map and N when fig7 flew
    the same cells (both rows as fig6's), else whether the two CIs are disjoint."""
    from shared.tools.experiments.report.readings import variants_reading

    def row(method, mean, half, N=4):
        return {"map": "museum", "robots": N, "method": method, "mean_capture_time": mean, "ci95_halfwidth": half}

    rows = [row("cepg", 20.0, 1.0), row("cepg+", 7.0, 0.5), row("c-cepg", 21.0, 1.0)]
    (line, _blank) = variants_reading(rows, tmp_path)
    assert "cepg+ captures sooner than CE-PG (7.00 against 20.00, 95% CIs disjoint)" in line
    assert "c-cepg is not separated from CE-PG (21.00 against 20.00, 95% CIs overlap)" in line
    fig7 = tmp_path / "fig7"
    fig7.mkdir()
    paired = {**row("c-cepg", 21.0, 1.0), "diff_to_cepg": 1.0, "diff_to_cepg_ci95": 0.4}
    (fig7 / "fig7.json").write_text(json.dumps({"rows": [row("cepg", 20.0, 1.0), paired]}))
    (line, _blank) = variants_reading(rows, tmp_path)
    assert "c-cepg captures later than CE-PG (fig7's paired difference +1.00 ± 0.40)" in line
    # a fig7 recorded with other teams (its CE-PG flew 19.5): its paired difference is not these teams'
    (fig7 / "fig7.json").write_text(json.dumps({"rows": [row("cepg", 19.5, 1.0), paired]}))
    (line, _blank) = variants_reading(rows, tmp_path)
    assert "c-cepg is not separated from CE-PG (21.00 against 20.00, 95% CIs overlap)" in line
    assert variants_reading([row("cepg+", 7.0, 0.5)], tmp_path) == []  # no CE-PG row to compare with


def test_noise_sweep_reading_says_where_the_value_rises():
    from shared.tools.experiments.report.readings import trend_reading

    rows = [
        {"robots": 4, "eta_fn": x, "mean_capture_time": m, "ci95_halfwidth": 0.5}
        for x, m in ((0.3, 12.0), (0.0, 8.0), (0.1, 8.5))
    ]
    (line, _blank) = trend_reading(rows, "eta_fn", "mean_capture_time", "ci95_halfwidth")
    assert line == (
        "The paper: the mean capture time rises with eta_fn. Here, at N = 4, 0.0 -> 0.1: the 95% CIs overlap "
        "(8.00 to 8.50); 0.1 -> 0.3: rises (8.50 to 12.00)."
    )


def test_fp_sweep_reading_says_whether_the_capture_time_moved():
    from shared.tools.experiments.report.readings import unmoved_reading

    def row(n, fp, m):
        return {"robots": n, "eta_fp": fp, "mean_capture_time": m, "ci95_halfwidth": 0.5, "episodes": 100}

    rows = [row(4, 0.5, 8.8), row(4, 0.0, 8.0), row(4, 0.1, 8.1), row(2, 0.0, 20.0), row(2, 0.5, 22.0)]
    (line, _blank) = unmoved_reading(rows, "eta_fp")
    assert line == (
        "The paper: eta_fp does not change the capture time. Here, at N = 4, eta_fp 0.0 -> 0.5: "
        "8.00 ± 0.50 to 8.80 ± 0.50, 95% CIs overlap; at N = 2, eta_fp 0.0 -> 0.5: 20.00 ± 0.50 to "
        "22.00 ± 0.50, it rises (95% CIs disjoint)."
    )
    assert unmoved_reading([row(4, 0.0, 8.0)], "eta_fp") == []  # one rate: nothing to compare


def test_marl_budgets_per_method():
    """The protocol trains each MARL baseline for its default budget, its plateau on OFFICE, N = 4:
    MAPPO 4x10^5 episodes, MADDPG and MASAC 3x10^5, MAMBPO and FACMAC 2x10^5; --train-episodes
    sets every learned team's budget alike."""
    from shared.learning.marl import hyperparameters
    from shared.tools.experiments import FULL, MARL
    from shared.tools.experiments.recording import figure_setup
    from shared.tools.experiments.report.text import marl_budget

    plateau = {"mappo": 400_000, "maddpg": 300_000, "masac": 300_000, "facmac": 200_000, "mambpo": 200_000}
    assert {m: FULL.marl_episodes(m) for m in MARL} == plateau
    assert {m: hyperparameters(m).episodes for m in MARL} == plateau
    assert marl_budget(figure_setup("fig7", FULL)) == (
        "each method's default budget (MADDPG 300,000, MASAC 300,000, FACMAC 200,000, MAMBPO 200,000, MAPPO 400,000)"
    )
    b = FULL.with_train(5_000)
    assert b.marl_episodes("mappo") == b.marl_episodes("masac") == 5_000
    assert marl_budget(figure_setup("fig7", b)) == "5,000 episodes"
    # a file recorded when the defaults were other budgets does not claim today's
    old = {"marl_training_episodes": "each method's default"}
    assert marl_budget(old) == "each method's default budget when recorded (each row's training episodes)"


def test_withdrawal_reading_names_the_best_learned_team_and_each_rise():
    from shared.tools.experiments.report.readings import withdrawal_reading

    def row(method, withdrawn, mean, half=0.5):
        return {"method": method, "withdrawn": withdrawn, "mean_capture_time": mean, "ci95_halfwidth": half}

    rows = [row("greedy", "none", 20.0), row("cepg", "none", 8.0), row("mappo", "none", 7.0)]
    rows += [row("greedy", "r4@t5", 9.0), row("cepg", "r4@t5", 11.0), row("mappo", "r4@t5", 11.5)]
    (line, _blank) = withdrawal_reading(rows)
    assert (
        "cepg captures soonest of the learned methods (11.00 ± 0.50), then mappo (11.50 ± 0.50; 95% CIs overlap)"
        in line
    )
    assert line.endswith("Rise over the intact team: cepg +3.00, mappo +4.50.")  # greedy is not a learned method
    assert withdrawal_reading(rows[:3]) == []


def test_fig11_reading_ranks_cepg_among_methods_that_sense_as_it_does():
    from shared.tools.experiments.report.readings import ranking_reading

    def row(method, eta, mean, half=0.5, episodes=1500):
        return {
            "method": method,
            "eta_fn": eta,
            "mean_capture_time": mean,
            "ci95_halfwidth": half,
            "episodes": episodes,
        }

    rows = [row("cepg", 0.0, 8.0), row("cepg+", 0.0, 3.0), row("masac", 0.0, 6.0), row("mappo", 0.0, 7.8)]
    rows += [row("milp", 0.0, 1.0, float("nan"), 1), row("random", 0.0, 25.0)]
    rows += [row("cepg", 0.3, 9.0), row("random", 0.3, 26.0)]
    (line, _blank) = ranking_reading(rows)
    # cepg+ (broader sensor) and a one-episode cell are left out; mappo is ahead by mean but not separated
    assert line.endswith(
        "eta_fn 0.0: cepg ranks 3 of 4 (8.00 ± 0.50); sooner, separated: masac 6.00 ± 0.50 (CIs disjoint); "
        "eta_fn 0.3: cepg ranks 1 of 2 (9.00 ± 0.50); none is sooner and separated."
    )
    assert ranking_reading([row("random", 0.0, 25.0), row("masac", 0.0, 6.0)]) == []  # no CE-PG row


def test_fig13_reading_ranks_the_teams_trained_for_five():
    from shared.tools.experiments.report.readings import dropout_reading

    def row(method, k, mean, half=0.5):
        return {"method": method, "robots": k, "mean_capture_time": mean, "ci95_halfwidth": half, "episodes": 1500}

    rows = [row("cepg trained for 5", 2, 20.0), row("masac trained for 5", 2, 15.0), row("cepg trained for k", 2, 9.0)]
    rows += [row("cepg trained for 5", 5, 8.0), row("masac trained for 5", 5, 9.0)]
    (line, _blank) = dropout_reading(rows)
    # the team trained for k is the reference, not ranked; k = 5 is the intact team
    assert line.endswith(
        "of the teams trained for 5: k = 2: cepg trained for 5 ranks 2 of 2 (20.00 ± 0.50); "
        "sooner, separated: masac 15.00 ± 0.50 (CIs disjoint)."
    )
    assert dropout_reading(rows[3:]) == []  # only the intact team


def test_fig13_pairs_each_team_with_cepgs_of_the_same_training(tmp_path, monkeypatch):
    """fig13's cells of one k fly the same episodes: each team's diff_to_cepg is its paired
    difference to CE-PG's team trained as it was (for 5, or for k). Capture times made up so that
    the answer is known: a MARL team trained for 5 takes 2 steps less than CE-PG's in every
    episode, one trained for k 1 + k steps more."""
    from shared.tools.experiments import MARL, Budget, Context, cells, teams
    from shared.tools.experiments.figures.robustness import fig13

    base = np.arange(10.0, 20.0)

    def cell(ctx, env, k, method, make, episodes, times=False, **kw):
        m, _, trained = method.partition(" trained for ")
        shift = 0.0 if m == "cepg" else (-2.0 if trained == "5" else 1.0 + k)
        t = base + (k if trained == "5" else 3 * k) + shift  # CE-PG's two teams differ too
        row = {"map": env, "robots": k, "method": method, "episodes": len(t), "seed": 1}
        return {**row, "mean_capture_time": float(t.mean()), "ci95_halfwidth": 1.0, "capture_times": t}

    monkeypatch.setattr(cells, "cell_row", cell)
    for stub in ("cepg_snapshot", "marl_snapshot", "Team", "learned_team"):
        monkeypatch.setattr(teams, stub, lambda *a, **kw: None)
    b = Budget(quick=True, episodes=10, train=256, planner=1, milp_limit=0.05, teams=(4,), maps=("office",))
    fig13(Context(tmp_path, b))
    rows = json.loads((tmp_path / "fig13" / "fig13.json").read_text())["rows"]
    assert len(rows) == 2 * 5 * (1 + len(MARL)) and not any("capture_times" in r for r in rows)
    for r in rows:
        k, trained = r["robots"], r["method"].rsplit(" ", 1)[1]
        if r["method"].startswith("cepg "):
            assert "diff_to_cepg" not in r
        else:
            assert r["diff_to_cepg"] == (-2.0 if trained == "5" else 1.0 + k) and r["diff_to_cepg_ci95"] == 0.0
    # the table's order: per method, k = 1..5, trained for 5 then for k
    assert [(r["method"], r["robots"]) for r in rows[:4]] == [
        ("cepg trained for 5", 1),
        ("cepg trained for k", 1),
        ("cepg trained for 5", 2),
        ("cepg trained for k", 2),
    ]


def test_unknown_experiment_is_a_clear_error(tmp_path, capsys):
    assert main(["experiment", "fig99", "--results", str(tmp_path)]) == 2
    assert "not implemented" in capsys.readouterr().err


def test_maps_and_team_sizes_are_checked(tmp_path, capsys):
    assert main(["experiment", "fig7", "--maps", "office,mars", "--results", str(tmp_path)]) == 2
    assert "--maps takes office and/or museum" in capsys.readouterr().err
    assert main(["experiment", "fig7", "--robots", "4,6", "--results", str(tmp_path)]) == 2
    assert "--robots takes team sizes 1 to 5" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing trained, nothing written


def test_every_experiment_plans_from_an_empty_cache(tmp_path):
    """Planning (the figure functions on placeholder cells) lists the teams to train for every
    experiment without running anything (fig10 once failed here on a placeholder's missing
    false-alarm figure)."""
    from shared.tools import experiments

    for name in ("fig5", "fig6", "fig7", "fig9", "fig10", "fig11", "fig12", "fig13", "marl"):
        jobs = experiments.plan(name, tmp_path, experiments.QUICK)
        assert jobs and all(j.label.startswith(("training", "evaluating")) for j in jobs), name
        # a progress line names its job: fig5's teams differ by beta and seed only, its cells by team
        assert len({j.label for j in jobs}) == len(jobs), name
    assert not any(tmp_path.iterdir())


def test_plan_says_what_a_run_would_train_and_evaluate_and_runs_nothing(tmp_path, capsys):
    """`--plan` on an empty cache: every team of fig7 (OFFICE, N = 2) to train, the cells that need
    no team now, one cell per team once trained, each with an estimate; nothing is written."""
    import re

    from shared.tools import experiments as E
    from shared.tools.experiments.budget import LEARNED
    from shared.tools.experiments.cells import reference
    from shared.tools.experiments.costs import cell_cost, planner_step_cost, train_cost

    argv = ["experiment", "fig7", "--quick", "--maps", "office", "--robots", "2", "--results", str(tmp_path)]
    assert main([*argv, "--plan"]) == 0
    lines = capsys.readouterr().out.splitlines()
    head = re.match(r"fig7 in .*: (\d+) teams to train, (\d+) cells to evaluate now and (\d+) once", lines[0])
    assert head, lines[0]
    teams, now, later = map(int, head.groups())
    learned = len(LEARNED) + len(E.MARL)
    assert teams == learned and later == learned and now >= 2 + len(E.PLANNERS)  # random, greedy, planners
    assert len(lines) == 1 + teams + now + later
    assert any("training MADDPG office N=2" in ln for ln in lines) and any(
        "evaluating milp office N=2" in ln for ln in lines
    )
    assert not any(tmp_path.iterdir())
    # a team's estimate follows its method's measured cost per episode, map and team size
    assert train_cost("maddpg", "office", 4, 1000) > 10 * train_cost("cepg", "office", 4, 1000)
    assert train_cost("cepg", "museum", 4, 1000) > train_cost("cepg", "office", 4, 1000)
    # and, as a job's steps, it lengthens with the sensor's misses: twice the steps at eta_fn 0.5
    assert train_cost("masac", "office", 4, 1000, eta_fn=0.5) == pytest.approx(
        2 * train_cost("masac", "office", 4, 1000)
    )
    cell = {"env": "office", "robots": 4, "episodes": 30, "sensor": {"eta_fn": 0.5, "eta_fp": 0.0}}
    assert cell_cost("d-milp", cell) == pytest.approx(2 * cell_cost("d-milp", {**cell, "sensor": {"eta_fn": 0}}))
    # a planner's step costs more with every robot it plans for (D-MILP a solve each, FHPE-SA's
    # annealing per robot, FHPE's joint paths), and more on the larger map
    for m in ("d-milp", "fhpe-sa", "fhpe"):
        assert planner_step_cost(m, "office", 3) > planner_step_cost(m, "office", 1)
    assert planner_step_cost("fhpe-sa", "museum", 4) > planner_step_cost("fhpe-sa", "office", 4)
    # a MILP cell is priced at the time limit it solves under (--quick's 0.05 s, the protocol's 1 s)
    from shared.core.models import Sensor

    quick, full = (reference("office", 4, "milp", Sensor(), time_limit=t) for t in (0.05, 1.0))
    cell0 = {**cell, "sensor": {"eta_fn": 0}}
    assert cell_cost("milp", cell0, quick) == pytest.approx(0.05 * cell_cost("milp", cell0, full))
    assert main([*argv, "--plan", "--train-episodes", "10", "--train-fraction", "0.5"]) == 2
    assert "not both" in capsys.readouterr().err


def test_a_run_narrowed_to_one_map_and_team_size(tmp_path):
    """`--maps office --robots 1`: fig6 runs that map and size only, its plot has one panel and
    the report tables OFFICE alone."""
    from shared.tools import experiments as E
    from shared.tools.experiments import Budget
    from shared.tools.experiments.schedule import run_one

    b = Budget(quick=True, episodes=40, train=256, planner=1, milp_limit=0.05, teams=(2, 4))
    narrowed = dataclasses.replace(b, maps=("office",), robots=(1,))
    run_one("fig6", tmp_path, narrowed)  # as `run` does once the teams are trained: cells cached
    d = json.loads((tmp_path / "fig6" / "fig6.json").read_text())
    assert {(r["map"], r["robots"]) for r in d["rows"]} == {("office", 1)} and d["maps"] == ["office"]
    assert (tmp_path / "fig6" / "fig6.png").stat().st_size > 1000
    text = report(tmp_path, tmp_path / "results.md").read_text()
    section = text.split("## Fig. 6")[1].split("\n## ")[0]
    assert "OFFICE (mean capture time" in section and "MUSEUM" not in section
    assert E.plan_lines("fig6", tmp_path, narrowed)[0].startswith("fig6: nothing to train or evaluate")


def test_a_figure_recorded_in_runs_at_different_budgets(tmp_path):
    """`--add`: a run at other team sizes (here at half the budget, `--train-fraction 0.5`) adds
    its rows to the recorded figure, each row with its own budget; a later run of a size already
    recorded replaces that size's rows; the report lists the runs."""
    from shared.tools.experiments import Budget, Context
    from shared.tools.experiments.figures.variants import fig6

    b = Budget(quick=True, episodes=30, train=512, planner=1, milp_limit=0.05, teams=(2, 4), maps=("office",))
    fig6(Context(tmp_path, dataclasses.replace(b, robots=(1,))))
    fig6(Context(tmp_path, dataclasses.replace(b.scaled(0.5), robots=(2,), add=True)))
    d = json.loads((tmp_path / "fig6" / "fig6.json").read_text())
    trained = {(r["robots"], r["method"]): r["train_episodes"] for r in d["rows"]}
    assert set(trained) == {(n, m) for n in (1, 2) for m in ("cepg", "cepg+", "c-cepg")}
    assert all(trained[1, m] >= 512 and trained[2, m] < 512 for m in ("cepg", "cepg+", "c-cepg"))
    assert [(p["training_episodes"], p["covers"]) for p in d["parts"]] == [
        (512, [["office", 1]]),
        (256, [["office", 2]]),
    ]
    text = report(tmp_path, tmp_path / "results.md").read_text()
    section = text.split("## Fig. 6")[1].split("\n## ")[0]
    assert "Recorded in 2 runs (`--add`)" in section and "trained for the budget of each run below" in section
    assert "OFFICE N = 1: learned teams trained for 512 episodes" in section
    assert "OFFICE N = 2: learned teams trained for 256 episodes" in section
    assert "| method | robots 1 | robots 2 |" in section

    fig6(Context(tmp_path, dataclasses.replace(b, robots=(2,), add=True)))  # N = 2 again, at the full budget
    d = json.loads((tmp_path / "fig6" / "fig6.json").read_text())
    assert [(p["training_episodes"], p["covers"]) for p in d["parts"]] == [
        (512, [["office", 1]]),
        (512, [["office", 2]]),
    ]
    assert len(d["rows"]) == 6 and all(r["train_episodes"] >= 512 for r in d["rows"])
    # without --add, a run that covers N = 2 only would drop N = 1's rows: refused before it writes
    before = (tmp_path / "fig6" / "fig6.json").read_bytes()
    with pytest.raises(ValueError, match=r"holds rows of OFFICE N = 1, which this run does not cover: --add"):
        fig6(Context(tmp_path, dataclasses.replace(b, robots=(2,))))
    assert (tmp_path / "fig6" / "fig6.json").read_bytes() == before
    fig6(Context(tmp_path, dataclasses.replace(b, robots=(2,), overwrite=True)))  # --overwrite: the run's rows only
    d = json.loads((tmp_path / "fig6" / "fig6.json").read_text())
    assert {r["robots"] for r in d["rows"]} == {2} and "parts" not in d


def test_a_quick_run_does_not_replace_protocol_rows(tmp_path, capsys):
    """A `--quick` run into a results directory whose figure holds the paper's protocol rows (the
    repository's own results/, say) is refused before it trains anything, --add or not, naming the
    rows; `--overwrite` lets it through, and rows of other maps are not protocol rows it loses."""
    from shared.tools.experiments.recording import write_figure

    fig = tmp_path / "fig6"
    protocol = {"experiment": "fig6", "quick": False}
    rows = [{"map": "office", "robots": 4, "method": "cepg", "mean_capture_time": 8.7}]
    write_figure(fig, "fig6", protocol, rows)  # recorded earlier (no Budget: no check)
    before = (fig / "fig6.json").read_bytes()
    argv = ["experiment", "fig6", "--quick", "--maps", "office", "--robots", "4", "--results", str(tmp_path)]
    why = "holds the paper's protocol rows of OFFICE N = 4; a --quick run would replace them"
    for extra in ([], ["--add"]):
        assert main([*argv, *extra]) == 2
        assert why in capsys.readouterr().err, extra
    assert main([*argv, "--plan"]) == 0  # --plan says so above its jobs
    out = capsys.readouterr().out.splitlines()
    assert "fig6: as given, this run would be refused" in out[0] and why in out[0] and "teams to train" in out[1]
    assert (fig / "fig6.json").read_bytes() == before and not (tmp_path / "snapshots").exists()
    assert main([*argv, "--maps", "museum", "--add", "--plan"]) == 0  # MUSEUM beside OFFICE's protocol rows
    assert "refused" not in capsys.readouterr().out
    assert main(["experiment", "fig4", "--overwrite", "--results", str(tmp_path)]) == 2
    assert "fig4 has none" in capsys.readouterr().err


def test_the_remaining_figures_are_recorded_one_map_at_a_time(tmp_path, monkeypatch, capsys):
    """`--add` for fig5, fig11 and fig13 (their protocol runs are recorded a map at a time): a
    MUSEUM run keeps OFFICE's recorded rows. Their cells are stubbed (rows without evaluation): the
    figures' own code, the merge and the plots run. `--add` is refused where it means nothing."""
    from shared.tools import experiments as E
    from shared.tools.experiments import cells, teams
    from shared.tools.experiments.budget import BETAS
    from shared.tools.experiments.figures import beta, methods

    def row(env, N, method, **extra):
        return {
            "map": env,
            "robots": N,
            "method": method,
            "episodes": 3,
            "mean_capture_time": 5.0,
            "ci95_halfwidth": 1.0,
            **extra,
        }

    monkeypatch.setattr(beta, "fig5_rows", lambda ctx, env, N=4: [row(env, N, "cepg", beta=x) for x in BETAS])
    monkeypatch.setattr(
        methods, "all_methods", lambda ctx, env, N, **kw: [row(env, N, m, **kw) for m in ("cepg", "pg")]
    )
    monkeypatch.setattr(cells, "cell_row", lambda ctx, env, k, method, make, episodes, **kw: row(env, k, method))
    for stub in ("cepg_snapshot", "marl_snapshot", "Team", "learned_team"):
        monkeypatch.setattr(teams, stub, lambda *a, **kw: None)
    b = E.Budget(quick=True, episodes=3, train=256, planner=1, milp_limit=0.05, teams=(4,))
    for name in ("fig5", "fig11", "fig13"):
        E.RUNNERS[name](E.Context(tmp_path, dataclasses.replace(b, maps=("office",))))
        E.RUNNERS[name](E.Context(tmp_path, dataclasses.replace(b, maps=("museum",), add=True)))
        d = json.loads((tmp_path / name / f"{name}.json").read_text())
        assert d["maps"] == ["office", "museum"] and [p["covers"][0][0] for p in d["parts"]] == ["office", "museum"]
        assert {r["map"] for r in d["rows"]} == {"office", "museum"}, name
        assert (tmp_path / name / f"{name}.png").stat().st_size > 1000
    for name in ("fig4", "marl"):
        assert main(["experiment", name, "--add", "--results", str(tmp_path / "x")]) == 2
        assert f"{name} is not recorded by them" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_budgets_scaled_keep_the_methods_ratios():
    from shared.tools.experiments import FULL
    from shared.tools.experiments.recording import figure_setup
    from shared.tools.experiments.report.text import marl_budget

    b = FULL.scaled(0.25)
    assert (b.train, b.marl_episodes("facmac"), b.marl_episodes("mappo"), b.marl_episodes("maddpg")) == (
        100_000,
        50_000,
        100_000,
        75_000,
    )
    assert marl_budget(figure_setup("fig7", b)) == (
        "each method's own budget (MADDPG 75,000, MASAC 75,000, FACMAC 50,000, MAMBPO 50,000, MAPPO 100,000)"
    )
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ValueError, match="--train-fraction takes a fraction in"):
            FULL.scaled(bad)


def test_report_tables_robustness_results(tmp_path):
    rows = [
        {
            "map": env,
            "robots": 4,
            "method": m,
            "episodes": 10,
            "seed": 1,
            "withdrawn": w,
            "mean_capture_time": mean,
            "ci95_halfwidth": 1.0,
            "censored_fraction": 0.0,
        }
        for env in ("office", "museum")
        for m, w, mean in (("cepg", "none", 20.0), ("cepg", "r4@t5", 27.5))
    ]
    (tmp_path / "fig12").mkdir()
    setup = {"episodes": 10, "seed": 1, "training_episodes": 10, "quick": True, "machine": {"date": "today"}}
    (tmp_path / "fig12" / "fig12.json").write_text(json.dumps({**setup, "rows": rows}))
    text = report(tmp_path, tmp_path / "results.md").read_text()
    assert "| method | withdrawn none | withdrawn r4@t5 |" in text and "| cepg | 20.00 ± 1.00 | 27.50 ± 1.00 |" in text
    assert "fig12" not in text.split("## Not recorded")[1] and "fig11" in text.split("## Not recorded")[1]


def test_sensor_noise_and_variant_experiments_and_their_report(tmp_path):
    """fig10 and fig6 at a tiny budget: the cells say which sensor they were flown with, a noiseless
    sensor never raises a false alarm and eta_fp = 0.5 does, and the report tables both figures."""
    from shared.tools.experiments import Budget, Context
    from shared.tools.experiments.figures.noise import fig10
    from shared.tools.experiments.figures.variants import fig6

    b = Budget(quick=True, episodes=60, train=256, planner=1, milp_limit=0.05, teams=(2,))
    fig10(Context(tmp_path, b))
    rows = json.loads((tmp_path / "fig10" / "fig10.json").read_text())["rows"]
    assert {(r["map"], r["eta_fp"]) for r in rows} == {
        (m, e) for m in ("office", "museum") for e in (0.0, 0.1, 0.3, 0.5)
    }
    for r in rows:
        assert r["episodes"] == 60 and r["robots"] == 2 and r["eta_fn"] == 0.0
        if r["eta_fp"] == 0.0:
            assert r["false_alarms_per_episode"] == 0.0
        if r["eta_fp"] == 0.5:
            assert r["false_alarms_per_episode"] > 1.0  # 2 robots, each reading z = 1 half the time it is away
    fig6(Context(tmp_path, b))
    rows = json.loads((tmp_path / "fig6" / "fig6.json").read_text())["rows"]
    assert {r["method"]: r["detection"] for r in rows} == {"cepg": "node", "cepg+": "neighbourhood", "c-cepg": "node"}
    assert (tmp_path / "fig6" / "fig6.png").stat().st_size > 1000
    text = report(tmp_path, tmp_path / "results.md").read_text()
    assert "## Fig. 10: eta_fp" in text and "| N | eta_fp 0.0 | eta_fp 0.1 | eta_fp 0.3 | eta_fp 0.5 |" in text
    assert "| 2 | 0.00 ± 0.00 |" in text  # N = 2, eta_fp = 0: no false alarm in any episode
    assert "| cepg+ |" in text and "fig6" not in text.split("## Not recorded")[1]
    # every learned row names the snapshot that flew it, and the figure's cost counts those teams' training
    assert all((tmp_path / "snapshots" / r["team"] / "policy.json").exists() for r in rows)
    section = text.split("## Fig. 6")[1].split("\n## ")[0]
    assert f"training the {len({r['team'] for r in rows})} teams its rows name " in section
    assert "recorded before rows named their team" not in section


def test_marl_experiment_and_its_report(tmp_path, monkeypatch):
    """The MARL experiment at a tiny budget (two methods, one sweep setting): rows for random,
    cepg and each method on OFFICE and WARD with training figures and learning curves, the sweep,
    and the report's section."""
    from shared.tools.experiments import Budget, Context
    from shared.tools.experiments.figures import marl

    monkeypatch.setattr(marl, "MARL_SWEEP", {"mappo": [("clip=0.1",)], "maddpg": [("gumbel_tau=0.5",)]})
    b = Budget(quick=True, episodes=40, train=256, planner=1, milp_limit=0.05, teams=(2,), marl_train=300)
    marl.marl(Context(tmp_path, dataclasses.replace(b, marl_methods=("mappo", "maddpg"))))
    d = json.loads((tmp_path / "marl" / "marl.json").read_text())
    assert {(r["map"], r["method"]) for r in d["rows"]} == {
        (m, x) for m in ("office", "ward") for x in ("random", "cepg", "mappo", "maddpg")
    }
    for r in d["rows"]:
        assert r["episodes"] == 40 and r["robots"] == 4 and r["decision_ms"] > 0
        assert r["timed_team_steps"] >= 150  # timed on enough steps (three episodes were about 30 here)
        if r["method"] in ("mappo", "maddpg"):
            assert r["train_episodes"] >= 300 and r["train_wall_seconds"] > 0
    assert set(d["learning_curves"]) == {"office/mappo", "office/maddpg", "ward/mappo", "ward/maddpg"}
    assert [(r["method"], r["overrides"]) for r in d["sweep"]] == [
        ("mappo", ["defaults"]),
        ("mappo", ["clip=0.1"]),
        ("maddpg", ["defaults"]),
        ("maddpg", ["gumbel_tau=0.5"]),
    ]
    meta = json.loads(
        next((tmp_path / "snapshots").glob("office-N4-maddpg-300-s0")).joinpath("policy.json").read_text()
    )
    assert meta["algorithm"] == "maddpg"
    text = report(tmp_path, tmp_path / "results.md").read_text()
    assert "## The MARL baselines" in text and "| WARD | maddpg |" in text and "| mappo | clip=0.1 | 300 |" in text
    assert "### Past the budget" not in text  # until benchmarks/marl_plateau.py has written its table

    # the plateau check: the same episodes for every team, paired with the reference
    snaps = tmp_path / "snapshots"
    ref, team = next(snaps.glob("office-N4-beta0.5-256-s0")), next(snaps.glob("office-N4-maddpg-300-s0"))
    out = tmp_path / "marl" / "plateau.json"
    script = Path(__file__).parents[1] / "benchmarks" / "marl_plateau.py"
    argv = [
        sys.executable,
        str(script),
        "--reference",
        str(ref),
        str(ref),
        str(team),
        "--episodes",
        "30",
        "--out",
        str(out),
    ]
    subprocess.run(argv, check=True, capture_output=True, text=True)
    rows = json.loads(out.read_text())["rows"]
    assert [(r["algorithm"], r.get("reference", False)) for r in rows] == [
        ("cepg", True),
        ("cepg", False),
        ("maddpg", False),
    ]
    assert rows[1]["diff_to_reference"] == 0 and rows[1]["mean_capture_time"] == rows[0]["mean_capture_time"]
    # the learning curve at the middle and at the end of each team's run, from its training summary
    curve = json.loads((team / "training_summary.json").read_text())["learning_curve"]
    last = [p["mean_capture_time"] for p in curve if p["episodes"] > 0.9 * curve[-1]["episodes"]]
    assert rows[2]["curve_at_end"] == pytest.approx(sum(last) / len(last), abs=1e-3)
    assert rows[2]["curve_at_half"] is not None
    text = report(tmp_path, tmp_path / "results.md").read_text()
    row = f"| maddpg | {rows[2]['train_episodes']:,} | {rows[2]['train_wall_seconds']:.0f} | "
    assert "### Past the budget: OFFICE, N = 4" in text and row in text

    # --add: another team's row joins the file, paired with the same reference; the others stay
    mappo = next(snaps.glob("office-N4-mappo-*-s0"))
    subprocess.run([*argv[:4], str(mappo), *argv[6:], "--add"], check=True, capture_output=True, text=True)
    added = json.loads(out.read_text())["rows"]
    assert [r["algorithm"] for r in added] == ["cepg", "cepg", "maddpg", "mappo"]
    assert added[:3] == rows
    # ... but not against another reference, nor with other episodes: an error, and the file unchanged
    kept = out.read_text()
    for wrong in (
        [sys.executable, str(script), "--reference", str(team), str(mappo), *argv[6:], "--add"],
        [*argv[:4], str(mappo), "--episodes", "31", "--out", str(out), "--add"],
    ):
        bad = subprocess.run(wrong, capture_output=True, text=True)
        assert bad.returncode == 2 and ("not the same team" in bad.stderr or "would not be paired" in bad.stderr)
        assert out.read_text() == kept
    # teams paired with another reference go to a file of their own: one table a file in the report
    (out.parent / "plateau-b.json").write_text(kept)
    text = report(tmp_path, tmp_path / "results.md").read_text()
    assert text.count("### Past the budget: OFFICE, N = 4") == 2 and "(marl/plateau-b.json)" in text


def test_plateau_pairs_each_budget_with_the_methods_next_shorter_one(tmp_path):
    """benchmarks/marl_plateau.py's plateau test: each team against the same method's longest shorter
    budget, episode by episode; rows without capture times (files written before they were kept) and
    a method's shortest budget get none. The report shows the column."""
    import importlib.util

    from shared.tools.experiments.report.marl import plateau_tables

    spec = importlib.util.spec_from_file_location(
        "marl_plateau", Path(__file__).parents[1] / "benchmarks" / "marl_plateau.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)

    def row(alg, eps, times=None, **kw):
        r = {"algorithm": alg, "train_episodes": eps, "team": f"{alg}-{eps}", **kw}
        return r if times is None else {**r, "capture_times": times}

    rows = mod.pair_budgets(
        [
            row("mambpo", 400, [4, 6, 6, 4]),
            row("cepg", 400, [5, 5, 5, 5], reference=True),
            row("mambpo", 100, [9, 9, 9, 9]),
            row("mambpo", 200, [5, 7, 5, 7]),
            row("masac", 300),  # no capture times kept
            row("masac", 600, [1, 2, 3, 4]),
            row("cepg", 800, [4, 4, 4, 4]),
        ]
    )
    assert [(r["algorithm"], r["train_episodes"]) for r in rows] == [
        ("cepg", 400),
        ("cepg", 800),
        ("mambpo", 100),
        ("mambpo", 200),
        ("mambpo", 400),
        ("masac", 300),
        ("masac", 600),
    ]
    by = {(r["algorithm"], r["train_episodes"]): r for r in rows}
    assert by["mambpo", 200]["diff_to_shorter_budget"] == -3.0 and by["mambpo", 200]["shorter_budget_episodes"] == 100
    assert by["mambpo", 400]["diff_to_shorter_budget"] == -1.0 and by["mambpo", 400]["shorter_budget_episodes"] == 200
    assert by["mambpo", 400]["diff_to_shorter_budget_ci95"] > 0  # the differences -1, -1, +1, -3 vary
    assert by["cepg", 800]["diff_to_shorter_budget"] == -1.0 and by["cepg", 800]["diff_to_shorter_budget_ci95"] == 0
    assert all("diff_to_shorter_budget" not in by[k] for k in (("cepg", 400), ("mambpo", 100), ("masac", 600)))
    text = mod._dumps({"rows": rows})
    assert '"capture_times": [5, 5, 5, 5]' in text and json.loads(text) == {"rows": rows}

    f = tmp_path / "marl" / "plateau.json"
    f.parent.mkdir()
    common = {"training_seed": 0, "train_wall_seconds": 1.0, "mean_capture_time": 5.0, "ci95_halfwidth": 1.0}
    for r in rows:
        r.update(common, diff_to_reference=0.0, diff_to_reference_ci95=0.0)
    f.write_text(mod._dumps({"map": "office", "robots": 4, "episodes": 4, "seed": 1, "rows": rows}))
    text = "\n".join(plateau_tables(tmp_path))  # the MARL section's tail (that section needs marl.json)
    assert "| mambpo | 400 | 1 | 5.00 ± 1.00 | +0.00 ± 0.00 | -1.00 ± " in text and "(vs 200) |" in text
    assert "| masac | 600 | 1 | 5.00 ± 1.00 | +0.00 ± 0.00 | — |" in text


def _rows(path):
    """An experiment's rows without their timings (which differ from run to run)."""
    rows = json.loads(path.read_text())["rows"]
    return [{k: v for k, v in r.items() if k not in ("wall_seconds", "decision_ms")} for r in rows]


@pytest.mark.slow
def test_teams_trained_by_local_processes_and_by_a_dask_cluster_give_the_same_rows(tmp_path, monkeypatch):
    """fig6 at a tiny budget on OFFICE, its three teams trained and its three cells evaluated three
    ways: in this process, by two local worker processes, and as tasks on a Dask cluster (a
    scheduler and two workers started here on loopback): the same rows; a finished run leaves
    nothing to do."""
    from pathlib import Path

    from shared.tools import experiments
    from shared.tools.experiments import Budget, cells
    from shared.tools.experiments import budget as budgets
    from shared.tools.fleetsim import free_port
    from shared.tools.runner import local_dask_cluster

    tiny = Budget(quick=True, episodes=60, train=256, planner=1, milp_limit=0.05, teams=(2,), maps=("office",))
    monkeypatch.setattr(budgets, "QUICK", tiny)
    experiments.run("fig6", tmp_path / "local", quick=True)
    expected = _rows(tmp_path / "local" / "fig6" / "fig6.json")
    assert len(expected) == 3 and all(r["mean_capture_time"] > 0 for r in expected)

    experiments.run("fig6", tmp_path / "pool", quick=True, workers=2)
    assert _rows(tmp_path / "pool" / "fig6" / "fig6.json") == expected
    # the cells too were evaluated by the workers, and are cached: a run again (or one resumed
    # after a kill) evaluates nothing
    assert len(list((tmp_path / "pool" / "cells").glob("*.json"))) == 3
    evaluate = cells.evaluate_cell
    monkeypatch.setattr(cells, "evaluate_cell", lambda **kw: pytest.fail(f"evaluated again: {kw}"))
    experiments.run("fig6", tmp_path / "pool", quick=True)
    assert _rows(tmp_path / "pool" / "fig6" / "fig6.json") == expected
    monkeypatch.setattr(cells, "evaluate_cell", evaluate)

    with local_dask_cluster(2, tmp_path, Path(__file__).resolve().parent.parent) as address:
        experiments.run("fig6", tmp_path / "dask", quick=True, scheduler=address)
        # with a deadline the jobs go to the cluster as its threads free up: the same rows
        out = experiments.run("fig6", tmp_path / "dask-until", quick=True, scheduler=address, until=time.time() + 3600)
    assert out is not None and _rows(tmp_path / "dask-until" / "fig6" / "fig6.json") == expected
    assert _rows(tmp_path / "dask" / "fig6" / "fig6.json") == expected
    assert experiments.plan("fig6", tmp_path / "dask", tiny) == []  # resumes: every team is cached
    with pytest.raises(ValueError, match="cannot reach the Dask scheduler at tcp://"):
        experiments.run("fig6", tmp_path / "nowhere", quick=True, scheduler=f"tcp://127.0.0.1:{free_port()}")


@pytest.mark.parametrize("workers", [1, 2])
def test_a_deadline_starts_only_the_jobs_that_fit_longest_first(tmp_path, workers):
    """run_jobs with ``until``: a job whose estimate (UNTIL_MARGIN x its weight) would end past the
    deadline is not started and is returned, unrun; the others run, longest first."""
    from shared.tools.runner import UNTIL_MARGIN, Job, run_jobs

    # dict(pairs) is a job that returns its files as they are given (picklable for the workers)
    jobs = [
        Job(name, name, dict, ([(f"{name}.txt", name.encode())],), weight=w)
        for name, w in (("short", 1.0), ("long", 1000.0), ("mid", 2.0))
    ]
    said: list[str] = []
    left = run_jobs(jobs, tmp_path, workers=workers, say=said.append, until=time.time() + 100 * UNTIL_MARGIN)
    assert [j.key for j in left] == ["long"]
    assert not (tmp_path / "long.txt").exists()
    assert (tmp_path / "short.txt").read_bytes() == b"short" and (tmp_path / "mid.txt").read_bytes() == b"mid"
    done = [line.split("] ")[1].split(" done")[0] for line in said if " done;" in line]
    if workers == 1:
        assert done == ["mid", "short"]  # longest first
    else:
        assert sorted(done) == ["mid", "short"]
    assert "1 of 3 jobs not started" in said[-1] and "long" in said[-1]
    assert run_jobs(jobs[:1], tmp_path / "again", until=None) == []  # no deadline: every job runs


def _slow_files(name: str, seconds: float) -> dict[str, bytes]:
    """A job for run_jobs that takes ``seconds`` (module level: worker processes unpickle it)."""
    time.sleep(seconds)
    return {f"{name}.txt": name.encode()}


def test_jobs_on_other_processes_say_when_they_start_and_what_is_still_running(tmp_path):
    """With jobs in worker processes, run_jobs says as each starts and, while none finishes for
    ``heartbeat_s``, which are still running; a job in this process gets neither (nothing could
    speak while it runs) but its own start line."""
    from shared.tools.runner import Job, run_jobs

    jobs = [Job(n, f"job {n}", _slow_files, (n, s), weight=60.0 * w) for n, s, w in (("a", 4.0, 3), ("b", 0.0, 1))]
    said: list[str] = []
    run_jobs(jobs, tmp_path, workers=2, say=said.append, heartbeat_s=0.5)
    assert (tmp_path / "a.txt").read_bytes() == b"a" and (tmp_path / "b.txt").read_bytes() == b"b"
    assert "started: job a" in said and "started: job b" in said
    still = [line for line in said if line.startswith("still running: ")]
    assert still, said
    # b finished at once, so the last of them names a alone, with its 3 min estimate
    assert still[-1].startswith("still running: job a (0 min, estimate 3 min)") and "job b" not in still[-1]
    said.clear()
    run_jobs(jobs, tmp_path / "here", workers=1, say=said.append, heartbeat_s=0.5)
    assert [line for line in said if line.endswith(" ...")] == ["job a ...", "job b ..."]
    assert not any(line.startswith(("still", "started")) for line in said)


def _reporting(name: str, progress: Any = None) -> dict[str, bytes]:
    """A job that ``reports``: it records the label of the progress it was handed."""
    return {f"{name}.txt": progress.label.encode()}


def test_a_training_job_says_how_far_it_has_got(tmp_path):
    """A reporting job gets a JobProgress named by its label; that says, at most once per
    ``every_s``, the episodes done, the rate and the time left at that rate, and nothing for a job
    shorter than that or at its last update (the job's own finished line follows)."""
    import io

    from shared.tools.runner import Job, JobProgress, run_jobs

    run_jobs([Job("t", "training X", _reporting, ("t",), reports=True)], tmp_path, say=lambda _s: None)
    assert (tmp_path / "t.txt").read_bytes() == b"training X"
    out = io.StringIO()
    quiet = JobProgress("training X", every_s=3600, stream=out)
    quiet({"episodes": 100, "total": 400, "episodes_per_second": 10.0})
    assert out.getvalue() == ""
    told = JobProgress("training MAMBPO museum N=2, 200,000 episodes", every_s=0, stream=out)
    told({"episodes": 50_000, "total": 200_000, "episodes_per_second": 25.0})
    told({"episodes": 200_000, "total": 200_000, "episodes_per_second": 25.0})
    lines = out.getvalue().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("training MAMBPO museum N=2, 200,000 episodes: 50,000/200,000 episodes (25 %) in 0 min,")
    assert lines[0].endswith(", 25 episodes/s, about 100 min left")  # 150,000 left at 25/s
    planner = JobProgress("evaluating milp museum N=4 (100 episodes)", every_s=0, stream=out)
    planner({"episodes": 37, "total": 100, "episodes_per_second": 37 / 660})
    assert out.getvalue().splitlines()[-1].endswith(" (37 %) in 0 min, 3.4 episodes/min, about 19 min left")


def test_a_marl_team_job_continues_from_its_checkpoint_and_clears_it(tmp_path, monkeypatch):
    """A MARL team's job is handed a checkpoint directory outside the results directory (under
    $MURES_CHECKPOINTS, so that a checkout laid anew still finds it); planned where a killed run
    left a checkpoint, its label says so and its estimate is what is left; started there, it
    continues from it, and the checkpoint is gone once the team's files are made."""
    from shared.core.graph import builtin_graph
    from shared.core.models import uniform_walk
    from shared.learning.marl import train_marl
    from shared.tools.experiments import QUICK, Context, teams
    from shared.tools.runner import run_jobs

    results, store = tmp_path / "results", tmp_path / "store"
    monkeypatch.setenv(teams.CHECKPOINTS_ENV, str(store))
    args = ("office", 2, "mappo", 96, 0, 0.0, 0.0, ("steps=4", "envs=8"))
    cfg, hyper, rel, _config = teams.marl_config(*args)
    planned = Context.planning(results, QUICK)  # the team's job, as `mures experiment` makes it
    teams.marl_snapshot(planned, *args)
    (job,) = jobs = planned.jobs
    ckpt = teams.checkpoint_dir(results) / rel
    assert job.checkpoint == str(ckpt) and ckpt.is_relative_to(store) and "checkpoint" not in job.label
    g = builtin_graph("office")
    calls = iter(range(100))
    stopped = train_marl(  # what a run killed after its checkpoint at the 4th batch leaves
        "mappo",
        g,
        uniform_walk(g),
        teams.sensor_for("cepg", 0.0, 0.0),
        cfg,
        hyper,
        should_stop=lambda: next(calls) >= 3,
        checkpoint=ckpt,
    )
    assert stopped.interrupted and (ckpt / "state.pt").is_file()
    teams.marl_snapshot(planned, *args)  # planned again: only the rest of its training is left
    done = stopped.summary["episodes"]
    assert jobs[-1].label == f"{job.label}, continuing from its checkpoint at {done:,}"
    assert jobs[-1].weight == pytest.approx(job.weight * (1 - done / 96))
    run_jobs([job], results, say=lambda _s: None)
    summary = json.loads((results / rel / "policy.json").read_text())["summary"]
    assert summary["resumed"][0]["episodes"] == stopped.summary["episodes"] > 0
    assert summary["episodes"] >= 96 and not summary["interrupted"]
    assert not ckpt.exists()


def test_each_results_directory_has_its_own_checkpoint_folder_outside_it(tmp_path, monkeypatch):
    """checkpoint_dir: one folder per results directory (the same path always gets the same
    one, another path another), under $MURES_CHECKPOINTS, else $XDG_CACHE_HOME/mures/checkpoints."""
    from shared.tools.experiments import CHECKPOINTS_ENV, checkpoint_dir

    monkeypatch.delenv(CHECKPOINTS_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    a, b = tmp_path / "one" / "results", tmp_path / "two" / "results"
    assert checkpoint_dir(a) == checkpoint_dir(tmp_path / "one" / ".." / "one" / "results")
    assert checkpoint_dir(a) != checkpoint_dir(b)
    assert checkpoint_dir(a).parent == tmp_path / "cache" / "mures" / "checkpoints"
    assert checkpoint_dir(a).name.startswith("results-")
    monkeypatch.setenv(CHECKPOINTS_ENV, str(tmp_path / "elsewhere"))
    assert checkpoint_dir(a).parent == tmp_path / "elsewhere"


def test_evaluate_tells_its_progress_after_every_chunk():
    """A planner's cell (chunks of one episode) says how far it has got, as a team's training does;
    the outcomes are those of a run without it."""
    from shared.core.graph import builtin_graph
    from shared.core.models import Sensor, uniform_walk
    from shared.engine.evaluate import evaluate
    from shared.registry import make_searcher

    g = builtin_graph("office")

    def run(progress: Any = None) -> Any:
        make = lambda s: make_searcher("random", g, uniform_walk(g), Sensor(), s)  # noqa: E731
        return evaluate(g, uniform_walk(g), Sensor(), 2, make, episodes=5, seed=3, chunk=2, progress=progress)

    told: list[dict[str, Any]] = []
    res = run(told.append)
    assert [(p["episodes"], p["total"]) for p in told] == [(2, 5), (4, 5), (5, 5)]
    assert all(p["episodes_per_second"] > 0 for p in told)
    assert np.array_equal(res.capture_time, run().capture_time)


def test_jobs_on_a_dask_cluster_say_what_is_still_running(tmp_path, monkeypatch):
    """On a Dask cluster with a deadline the jobs go out as threads free up, so each is named as
    it starts and while running; without one they all go to the scheduler at once, and the
    line while none finishes counts them."""
    from shared.tools.runner import Job, local_dask_cluster, run_jobs

    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).resolve().parent))  # the workers import _slow_files
    with local_dask_cluster(2, tmp_path, Path(__file__).resolve().parent.parent) as address:
        jobs = [Job(n, f"job {n}", _slow_files, (n, s), weight=60.0) for n, s in (("a", 3.0), ("b", 3.0))]
        said: list[str] = []
        until = time.time() + 3600
        run_jobs(jobs, tmp_path / "until", scheduler=address, say=said.append, until=until, heartbeat_s=0.5)
        assert "started: job a" in said and "started: job b" in said
        assert any(line.startswith("still running: job a (0 min, estimate 1 min); job b") for line in said), said
        said.clear()
        run_jobs(jobs, tmp_path / "all", scheduler=address, say=said.append, heartbeat_s=0.5)
        assert not any(line.startswith("started") for line in said)
        assert any(line.startswith(f"2 jobs not finished on Dask scheduler {address}") for line in said), said
    for d in ("until", "all"):
        assert (tmp_path / d / "a.txt").read_bytes() == b"a" and (tmp_path / d / "b.txt").read_bytes() == b"b"


def test_an_experiment_stopped_by_hours_writes_no_figure(tmp_path, monkeypatch, capsys):
    """`mures experiment --hours H` with too little time for any job: exit status 3, no figure and
    no team written, and it says so; a bad --hours is a clear error."""
    from shared.tools.experiments import Budget
    from shared.tools.experiments import budget as budgets

    tiny = Budget(quick=True, episodes=60, train=256, planner=1, milp_limit=0.05, teams=(2,), maps=("office",))
    monkeypatch.setattr(budgets, "QUICK", tiny)
    root = tmp_path / "results"
    assert main(["experiment", "fig6", "--quick", "--hours", "1e-7", "--results", str(root)]) == 3
    out = capsys.readouterr()
    assert "stopped with jobs left (past the --hours limit, above)" in out.out and "jobs not started" in out.err
    assert not (root / "fig6").exists() and not list(root.rglob("policy.json"))
    for bad in ("0", "-1", "nan", "soon"):
        with pytest.raises(SystemExit) as e:
            main(["experiment", "fig6", "--quick", "--hours", bad, "--results", str(root)])
        assert e.value.code == 2
    assert "expected a number of hours above 0" in capsys.readouterr().err


def test_only_runs_the_jobs_whose_labels_match(tmp_path, monkeypatch, capsys):
    """`mures experiment --only REGEX`: --plan lists the matching jobs only; a run trains and
    evaluates those, writes no figure while others are left (exit status 3), and the same command
    without --only then runs just the rest; a pattern that does not compile is a clear error."""
    from shared.tools.experiments import Budget, teams
    from shared.tools.experiments import budget as budgets

    tiny = Budget(quick=True, episodes=60, train=256, planner=1, milp_limit=0.05, teams=(2,), maps=("office",))
    monkeypatch.setattr(budgets, "QUICK", tiny)
    root = tmp_path / "results"
    quick = ["experiment", "fig6", "--quick", "--results", str(root)]
    assert main([*quick, "--plan", "--only", "^TRAINING CEPG office"]) == 0  # case ignored
    listed = capsys.readouterr().out.splitlines()
    # of the three teams (CE-PG, CE-PG+, C-CE-PG) and their three cells, the CE-PG team only
    assert "(--only '^TRAINING CEPG office'): 1 teams to train, 0 cells to evaluate now and 0 once" in listed[0]
    assert [line.split(None, 2)[2] for line in listed[1:]] == ["training CEPG office N=2, 256 episodes"]

    trained: list[str] = []
    train = teams.train_cepg
    monkeypatch.setattr(teams, "train_cepg", lambda *a, **k: trained.append(a[0]) or train(*a, **k))
    assert main([*quick, "--only", "^training cepg office"]) == 3
    out = capsys.readouterr()
    assert "outside --only" in out.out and "3 jobs of fig6 left that --only" in out.err
    assert not (root / "fig6").exists() and len(list(root.rglob("policy.json"))) == len(trained) == 1
    assert main(quick) == 0  # the rest, and only the rest: two teams and the three cells
    assert len(trained) == 3 and len(set(trained)) == 3
    assert len(_rows(root / "fig6" / "fig6.json")) == 3
    for extra in ([], ["--plan"]):
        assert main([*quick, *extra, "--only", "(unclosed"]) == 2
        assert "--only '(unclosed' is not a regular expression" in capsys.readouterr().err


def test_fig5_pairs_each_beta_with_pg_of_the_same_training_seed(tmp_path):
    """The paired difference and its two CIs, on capture times made up so that the answer is known:
    beta 0.5 is PG minus 1 on every episode of seed 0 and minus 3 on seed 1."""
    import numpy as np
    from scipy.stats import t as student_t

    from shared.tools.experiments import QUICK
    from shared.tools.experiments.figures.beta import beta_row
    from shared.tools.experiments.report.readings import beta_reading

    rng = np.random.default_rng(0)
    b = dataclasses.replace(QUICK, seeds=(0, 1), episodes=400)
    pg = {s: rng.integers(5, 40, 400).astype(float) for s in (0, 1)}
    times = {(1.0, s): pg[s] for s in (0, 1)}
    times |= {(0.5, 0): pg[0] - 1, (0.5, 1): pg[1] - 3}
    row = beta_row("office", 4, 0.5, b, times)
    assert row["training_seeds"] == [0, 1] and row["train_episodes"] == b.train
    assert row["diff_to_pg"] == -2.0 and row["diff_to_pg_per_seed"] == [-1.0, -3.0]
    assert row["diff_to_pg_ci95_seeds"] == round(float(student_t.ppf(0.975, 1) * np.std([-1, -3], ddof=1) / 2**0.5), 3)
    assert 0 < row["diff_to_pg_ci95_episodes"] < 0.1  # the episodes differ by 1 or 3: little spread
    assert row["mean_capture_time"] == round(float(np.concatenate([pg[0] - 1, pg[1] - 3]).mean()), 3)
    pg_row = beta_row("office", 4, 1.0, b, times)
    assert "diff_to_pg" not in pg_row and pg_row["method"] == "pg"
    text = "\n".join(beta_reading([row, pg_row]))
    assert "| 0.5 | -2.00 |" in text and "no beta < 1 captures sooner" in text  # the seeds' CI includes 0
    # the episodes' CI excludes 0: said too, with what it does not show
    assert "Over the pooled episodes (these teams, not the training's variation): beta in [0.5] captures sooner" in text
    assert "not separated from the seed-to-seed spread" in text

"""`mures experiment` and `mures report`: the paper's figures as data and plots, and docs/results.md."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from shared.learning.config import positive_int
from shared.tools.cli_args import CliError, map_names, positive_hours, team_sizes


def cmd_experiment(args: argparse.Namespace) -> int:
    from shared.tools.experiments import plan_lines, run
    from shared.tools.experiments.budget import budget

    t0 = time.perf_counter()
    if args.plan:
        try:
            b = budget(
                args.name,
                args.quick,
                args.train_episodes,
                args.maps,
                args.robots,
                args.train_fraction,
                args.add,
                args.overwrite,
            )
            lines = plan_lines(args.name, Path(args.results), b, args.only)
        except ValueError as exc:
            raise CliError(str(exc)) from None
        print("\n".join(lines))
        return 0
    try:
        out = run(
            args.name,
            Path(args.results),
            args.quick,
            args.train_episodes,
            workers=args.workers,
            scheduler=args.dask_scheduler,
            maps=args.maps,
            robots=args.robots,
            train_fraction=args.train_fraction,
            add=args.add,
            until=None if args.hours is None else time.time() + 3600 * args.hours,
            only=args.only,
            overwrite=args.overwrite,
        )
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if out is None:
        why = " or ".join(
            w for w, given in (("past the --hours limit", args.hours), ("outside --only", args.only)) if given
        )
        print(
            f"{args.name}: stopped with jobs left ({why}, above), nothing written but the finished jobs' cache; "
            f"the same command{' without --only' if args.only else ''} goes on from there "
            f"({time.perf_counter() - t0:.0f} s)"
        )
        return 3
    print(f"{args.name}: wrote {out} in {time.perf_counter() - t0:.0f} s")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from shared.tools.experiments.report import report

    out = report(Path(args.results), Path(args.out))
    print(f"wrote {out}")
    return 0


def add_experiment_commands(sub: Any) -> None:
    """The experiment and report subcommands of `mures` (``sub``: its subparsers)."""
    p = sub.add_parser("experiment", help="regenerate one of the paper's figures as data and a plot")
    p.add_argument("name", help="fig4 .. fig13 (fig8 comes with fig7), marl (the MARL baselines), or all")
    p.add_argument(
        "--quick", action="store_true", help="small runs: all experiments together in minutes (barely trained teams)"
    )
    p.add_argument(
        "--train-episodes",
        type=positive_int,
        metavar="N",
        help="training episodes per learned team (default: 400000, or 2000 with --quick)",
    )
    p.add_argument(
        "--train-fraction",
        type=float,
        metavar="F",
        help="every learned team's budget times F, in (0, 1] (CE-PG 4x10^5 F, each MARL method's F times its "
        "own): for team sizes whose full budget does not fit; every row states its budget",
    )
    p.add_argument(
        "--add",
        action="store_true",
        help="fig5 to fig13: keep the recorded rows of the maps and team sizes this run does not cover (e.g. N = 4 "
        "at the full budget, then --robots 1,2,3,5 --train-fraction 0.25 --add; or --maps office, then --maps "
        "museum --add)",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="fig5 to fig13: let this run drop the recorded rows it does not cover (without --add) or replace "
        "protocol rows with --quick ones; without it such a run is refused before it starts",
    )
    p.add_argument("--results", default="results", help="results directory (default results/)")
    p.add_argument(
        "--plan",
        action="store_true",
        help="say what the run would train and evaluate with this results directory's cache, each job with its "
        "estimated time on one core, and run nothing",
    )
    p.add_argument(
        "--maps",
        type=map_names,
        metavar="MAP[,MAP]",
        help="run on these of the paper's maps only: office, museum (default both)",
    )
    p.add_argument(
        "--robots",
        type=team_sizes,
        metavar="N[,N...]",
        help="team sizes of fig6, fig7, fig9 and fig10 (default: 1..5 for fig7, 1..5 or 2,4 with --quick for the "
        "others); the N = 4 figures keep N = 4",
    )
    p.add_argument(
        "--workers",
        type=positive_int,
        default=1,
        metavar="K",
        help="train the teams the experiment needs in K local processes, in parallel (default 1)",
    )
    p.add_argument(
        "--dask-scheduler",
        metavar="tcp://HOST:PORT",
        help="train them as tasks on this Dask distributed cluster instead (the cluster extra)",
    )
    p.add_argument(
        "--hours",
        type=positive_hours,
        metavar="H",
        help="start no job whose estimate (x1.7) would end more than H hours from now, longest jobs first; if "
        "any is left, write no figure and exit with status 3: the same command later goes on from the cache "
        "(a job stopped mid-way would be lost: a team's files are written when it ends)",
    )
    p.add_argument(
        "--only",
        metavar="REGEX",
        help="run (or with --plan list) only the jobs whose labels, as --plan shows them, match this regular "
        "expression, case ignored (e.g. 'training (pg|c?-?cepg)' for the CE-PG family's teams); if others are "
        "left, write no figure and exit with status 3, as --hours does",
    )
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser("report", help="write docs/results.md from the recorded results")
    p.add_argument("--results", default="results", help="results directory (default results/)")
    p.add_argument("--out", default="docs/results.md")
    p.set_defaults(func=cmd_report)

"""Running an experiment: ``plan`` (the jobs its figures need and the caches lack), ``run`` (those
jobs on shared/tools/runner.py, round after round, then the figure from the cache) and
``plan_lines`` (`mures experiment NAME --plan`)."""

from __future__ import annotations

import re
import sys
import time
from collections.abc import Callable
from pathlib import Path

from shared.tools.experiments.budget import EXPERIMENTS, Budget, budget
from shared.tools.experiments.cells import cell_job
from shared.tools.experiments.context import Context
from shared.tools.experiments.costs import duration
from shared.tools.experiments.figures.beta import fig5
from shared.tools.experiments.figures.marl import marl
from shared.tools.experiments.figures.methods import fig7, fig11
from shared.tools.experiments.figures.noise import fig9, fig10
from shared.tools.experiments.figures.robustness import fig12, fig13
from shared.tools.experiments.figures.toy import fig4
from shared.tools.experiments.figures.variants import fig6
from shared.tools.runner import Job, run_jobs

# the figures planned and run by map and team size (fig4 is run alone; fig8 comes from fig7)
RUNNERS: dict[str, Callable[[Context], Path]] = {
    "marl": marl,
    "fig5": fig5,
    "fig6": fig6,
    "fig7": fig7,
    "fig9": fig9,
    "fig10": fig10,
    "fig11": fig11,
    "fig12": fig12,
    "fig13": fig13,
}


def run(
    name: str,
    root: Path,
    quick: bool,
    train_episodes: int | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    maps: tuple[str, ...] | None = None,
    robots: tuple[int, ...] | None = None,
    train_fraction: float | None = None,
    add: bool = False,
    until: float | None = None,
    only: str | None = None,
    overwrite: bool = False,
) -> Path | None:
    """Run one experiment (``all``: every one in turn); returns its results directory.
    ``train_episodes`` overrides the learned teams' training budget, ``train_fraction`` scales
    every method's (``Budget.scaled``); ``add`` keeps a figure's recorded rows of the maps and
    team sizes this run does not cover (fig5 to fig13; ``_merge``; refused for fig4 and marl,
    which are not recorded by map and team size); a run that would drop recorded rows it does not
    cover, or put --quick rows in place of protocol ones, is refused before it starts unless
    ``overwrite`` (`--overwrite`; ``refuse_loss``). The teams the experiment
    needs and the cache lacks are trained first and its cells evaluated (``plan``, round after
    round: a cell needs its team), as jobs of shared/tools/runner.py: in this process, in
    ``workers`` local processes, or on a Dask ``scheduler``'s cluster, each with one torch thread,
    so the numbers are the same every way; the experiment then runs on the cached teams and cells.
    With ``until`` (a time.time() instant; `--hours`) no job starts that its estimate says would
    end past it (``run_jobs``); if any is left the figure is not written and None is returned:
    the same call later goes on from the cache. With ``only`` (a regular expression; `--only`)
    only the jobs whose labels (as ``plan_lines`` lists them) match it run; if others are left,
    likewise no figure and None."""
    b = budget(name, quick, train_episodes, maps, robots, train_fraction, add, overwrite)
    match = label_filter(only)
    for _round in range(3):  # the teams (and the planners' cells), then the learned teams' cells
        planned_run = outlook(name, root, b)
        if planned_run.refused:
            raise ValueError(planned_run.refused[0])
        planned = planned_run.jobs or []
        jobs = [j for j in planned if match(j.label)]
        if not jobs:
            break  # what is planned now is what --only leaves
        if run_jobs(jobs, root, workers, scheduler, say=say, until=until):  # a progress line per job, an ETA
            return None
    else:
        planned = plan(name, root, b) if only is not None else []
    if only is not None and planned:
        say(
            f"{len(planned)} jobs of {name} left that --only {only!r} does not match "
            f"({duration(sum(j.weight for j in planned))} on one core; --plan lists them)"
        )
        return None
    if name == "all":
        for e in EXPERIMENTS:
            if e != "fig8":
                t0 = time.perf_counter()
                run_one(e, root, b)
                say(f"{e}: done in {time.perf_counter() - t0:.0f} s")
        return root
    return run_one(name, root, b)


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def run_one(name: str, root: Path, b: Budget) -> Path:
    """Write one figure (or fig8, from fig7) from the cached teams and cells, evaluating any cell
    the cache lacks."""
    ctx = Context(root, b, cells=root / "cells")
    if name == "fig4":
        return fig4(ctx)
    if name == "fig8":
        return fig7(ctx).parent / "fig8"
    return RUNNERS[name](ctx)


def plan(name: str, root: Path, b: Budget) -> list[Job]:
    """The jobs an experiment (or ``all``) needs and the caches lack, without running anything:
    the teams to train, and the cells to evaluate whose teams exist (a cell of a team still to be
    trained comes up in the next plan); the figure functions run with placeholder cells and write
    nothing."""
    return outlook(name, root, b).jobs or []


def outlook(name: str, root: Path, b: Budget) -> Context:
    """An experiment (or ``all``) planned: the returned context's ``jobs`` (``plan``'s, each once),
    ``later`` (the cells that wait for a team of those jobs: (label, estimated seconds on one
    core) each) and ``refused`` (why the run would be refused)."""
    ctx = Context.planning(root, b)
    names = [e for e in EXPERIMENTS if e not in ("fig4", "fig8")] if name == "all" else [name]
    for e in names:
        if e in RUNNERS or e == "fig8":
            RUNNERS["fig7" if e == "fig8" else e](ctx)
    ctx.jobs = list({j.key: j for j in ctx.jobs or []}.values())
    return ctx


def label_filter(only: str | None) -> Callable[[str], bool]:
    """`--only`: a job label's test, a case-insensitive regular expression searched in the label
    (None: every label); a pattern that does not compile is a ValueError that says so."""
    if only is None:
        return lambda _label: True
    try:
        rx = re.compile(only, re.IGNORECASE)
    except re.error as exc:
        raise ValueError(f"--only {only!r} is not a regular expression: {exc}") from None
    return lambda label: rx.search(label) is not None


def plan_lines(name: str, root: Path, b: Budget, only: str | None = None) -> list[str]:
    """`mures experiment NAME --plan`: what a run would do with this cache, each job with its
    estimated time, and the total (one core of the machine the estimates come from; K workers
    divide it at best by K); with ``only``, the jobs whose labels match it."""
    if name == "fig4":
        return ["fig4: its toy's runs take seconds and are made by the run itself; nothing to plan"]
    match = label_filter(only)
    planned = outlook(name, root, b)
    refused = [f"{name}: as given, this run would be refused: {why}" for why in dict.fromkeys(planned.refused)]
    return refused + _plan_lines(name, root, planned.jobs or [], list(planned.later.values()), only, match)


def _plan_lines(
    name: str,
    root: Path,
    jobs: list[Job],
    later: list[tuple[str, float]],
    only: str | None,
    match: Callable[[str], bool],
) -> list[str]:
    jobs, later = [j for j in jobs if match(j.label)], [(label, w) for label, w in later if match(label)]
    if only is not None and not jobs and not later:
        return [f"{name}: no job to run in {root} matches --only {only!r} (without it, --plan lists them all)"]
    if not jobs and not later:
        return [f"{name}: nothing to train or evaluate in {root}: a run only writes its figure from the cache"]
    cells = [j for j in jobs if j.fn is cell_job]
    teams = [j for j in jobs if j.fn is not cell_job]
    total = sum(j.weight for j in jobs) + sum(w for _, w in later)
    matching = "" if only is None else f" (--only {only!r})"

    lines = [
        f"{name} in {root}{matching}: {len(teams)} teams to train, {len(cells)} cells to evaluate now and "
        f"{len(later)} once their teams exist; about {duration(total)} on one core (K workers: at best that / K), "
        "estimated from this project's measured rates (shared/tools/experiments/costs.py); "
        "nothing was run"
    ]
    lines += [f"  {duration(j.weight):>7}  {j.label}" for j in sorted(jobs, key=lambda j: -j.weight)]
    lines += [f"  {duration(w):>7}  {label}" for label, w in sorted(later, key=lambda x: -x[1])]
    return lines

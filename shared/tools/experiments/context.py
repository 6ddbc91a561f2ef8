"""``Context``: what every figure function is given, one run's results directory, budget and cell
cache, and whether the run is only being planned.

A planned run (``schedule.outlook``) calls the figure functions as a real run does, but nothing is
trained, evaluated or written: the teams they need that are not cached are collected as jobs, cells
whose teams exist become jobs too (placeholders stand in for their rows), cells whose teams do
not are noted for later, and a figure that would lose recorded rows notes why the run would be
refused.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.tools.experiments.budget import Budget
from shared.tools.experiments.recording import refuse_loss, write_figure
from shared.tools.runner import Job, run_jobs


@dataclass
class Context:
    root: Path  # the results directory: results/<figure>/, snapshots/, cells/
    budget: Budget
    cells: Path | None = None  # where evaluated cells are cached (None: evaluated every time)
    jobs: list[Job] | None = None  # a planned run's jobs; None in a real run
    # a planned run's cells that wait for a team still to train: (label, estimated seconds), keyed
    # by the cell's settings and its team's path
    later: dict[str, tuple[str, float]] = field(default_factory=dict)
    refused: list[str] = field(default_factory=list)  # why a planned run would be refused

    @classmethod
    def planning(cls, root: Path, budget: Budget) -> Context:
        return cls(root, budget, cells=root / "cells", jobs=[])

    @property
    def planned(self) -> bool:
        return self.jobs is not None

    def say(self, text: str) -> None:
        """A progress line on stderr (a planned run's placeholder figures are not news)."""
        if not self.planned:
            print(text, file=sys.stderr, flush=True)

    def obtain(self, job: Job) -> None:
        """Run a training job now, in this process, or collect it while planning."""
        if self.jobs is not None:
            self.jobs.append(job)
            return
        run_jobs([job], self.root, say=self.say)  # in this process; the runner restores its thread count

    def record(self, name: str, setup: dict[str, Any], rows: list[dict[str, Any]], by_map: bool = True) -> list[Any]:
        """Write figure ``name``'s data under root/name (``write_figure``); returns the rows written.
        A figure recorded ``by_map`` (fig5 to fig13: by map and team size) keeps, with
        ``budget.add`` (`--add`), the recorded rows of the maps and team sizes this run does not
        cover; a run that would lose recorded rows is refused (``refuse_loss``) unless
        ``budget.overwrite``, and while planned, before any work."""
        out = self.root / name
        recorded = out / f"{name}.json"
        add = by_map and self.budget.add
        if by_map and not self.budget.overwrite and recorded.exists():
            try:
                refuse_loss(recorded, json.loads(recorded.read_text()), setup, rows, add)
            except ValueError as refused:
                if not self.planned:
                    raise
                self.refused.append(str(refused))  # ``run`` raises it before any job, ``plan_lines`` says it
        if self.planned:
            return rows
        return write_figure(out, name, setup, rows, add=add)

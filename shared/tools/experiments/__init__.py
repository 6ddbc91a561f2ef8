"""`mures experiment NAME [--quick]` and `mures report`: the paper's figures as data, plots and a report.

Each experiment writes ``results/<name>/<name>.json`` (every cell with mean, 95% CI, episodes,
seed; the setup; the machine and date), ``<name>.csv`` and ``<name>.png``. Trained snapshots are
cached under ``results/snapshots/`` and reused, evaluated cells under ``results/cells/``.
``mures report`` turns whatever results exist into docs/results.md; nothing in it is typed by hand.

Experiments: fig4 (toy learning curves), fig5 (beta), fig6 (the variants), fig7 (all methods,
N = 1..5, OFFICE and MUSEUM), fig8 (decision time per team step, measured in fig7), fig9 and fig10
(sensor noise: capture time, false alarms), fig11 (all methods under eta_fn), fig12 and fig13
(robustness), marl (the MARL baselines at their default budgets on OFFICE and WARD with learning
curves, and a small hyperparameter sweep). ``all`` runs them in turn. Budgets: ``FULL`` is the
paper's protocol, ``QUICK`` fits CI.

The modules, one job each:

- ``budget``: how large a run is (``Budget``, ``FULL``, ``QUICK``) and what it covers;
- ``context``: ``Context``, what every figure function is given (results directory, budget,
  cell cache, and whether the run is only planned);
- ``teams`` and ``cells``: the cached learned teams and evaluated cells;
- ``costs``: what a job is expected to cost, for the ETA and `--plan`;
- ``figures/``: one module per family of figures; ``plots``: their plots;
- ``recording``: a figure's recorded data, merged across runs (`--add`);
- ``schedule``: ``plan`` and ``run`` (the jobs on shared/tools/runner.py, then the figure);
- ``report/``: docs/results.md (``report.report``), a module per section.
"""

from shared.tools.experiments.budget import EXPERIMENTS, FULL, MARL, PLANNERS, QUICK, Budget
from shared.tools.experiments.context import Context
from shared.tools.experiments.recording import machine
from shared.tools.experiments.schedule import RUNNERS, outlook, plan, plan_lines, run
from shared.tools.experiments.teams import CHECKPOINTS_ENV, checkpoint_dir

__all__ = [
    "CHECKPOINTS_ENV",
    "EXPERIMENTS",
    "FULL",
    "MARL",
    "PLANNERS",
    "QUICK",
    "RUNNERS",
    "Budget",
    "Context",
    "checkpoint_dir",
    "machine",
    "outlook",
    "plan",
    "plan_lines",
    "run",
]

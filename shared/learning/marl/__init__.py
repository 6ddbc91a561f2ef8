"""The MARL baselines of the paper's comparison (Section V, Fig. 7, 12, 13), trained on the
simulator through the TorchRL environment (shared/envs) and saved as ordinary snapshots.

    ALGORITHMS (shared/core/choices.py): cepg (shared/learning/train.py) and the baselines here:
      maddpg  Lowe et al. 2017           shared/learning/marl/maddpg.py
      masac   discrete SAC, CTDE         shared/learning/marl/masac.py
      facmac  Peng et al. 2021           shared/learning/marl/facmac.py
      mambpo  Willemsen et al. 2021      shared/learning/marl/mambpo.py
      mappo   Yu et al. 2022             shared/learning/marl/mappo.py

``hyperparameters(name, overrides)`` gives a method's documented defaults with `--hp KEY=VALUE`
overrides applied; ``train_marl(name, ...)`` sets up the run (``MarlRun``: environment, the team's
actor, bookkeeping), hands it to the method's ``train(run, hyper)`` and returns its
``TrainResult``, as CE-PG's ``train`` does. Given a checkpoint directory, a run is resumable
(``train_marl``; shared/learning/marl/checkpoint.py).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel
from shared.learning.config import TrainConfig
from shared.learning.marl.checkpoint import Checkpointer
from shared.learning.marl.common import CHECKPOINT_EVERY_S, MarlHyper, MarlRun, Progress, apply_overrides
from shared.learning.train import TrainResult

MARL_ALGORITHMS = ("maddpg", "masac", "facmac", "mambpo", "mappo")


def _module(name: str) -> Any:
    if name not in MARL_ALGORITHMS:
        raise ValueError(f"unknown MARL algorithm {name!r} (expected one of {', '.join(MARL_ALGORITHMS)})")
    return importlib.import_module(f"shared.learning.marl.{name}")


def hyperparameters(name: str, overrides: list[str] | None = None, **given: Any) -> MarlHyper:
    """A method's hyperparameters: its defaults, then ``given`` (values that are not None, such
    as `mures train --episodes`), then ``KEY=VALUE`` overrides."""
    hyper: MarlHyper = getattr(_module(name), f"{name.capitalize()}Hyper")()
    for key, value in given.items():
        if value is not None:
            setattr(hyper, key, value)
    return apply_overrides(hyper, overrides or [])


def train_marl(
    name: str,
    graph: Graph,
    target: TargetModel,
    sensor: Sensor,
    cfg: TrainConfig,
    hyper: MarlHyper,
    init_model: TargetModel | None = None,
    progress: Progress | None = None,
    should_stop: Callable[[], bool] | None = None,
    checkpoint: str | Path | None = None,
    checkpoint_every: float = CHECKPOINT_EVERY_S,
    models_per_tick: bool = False,
) -> TrainResult:
    """Train ``name`` with ``hyper`` (see ``hyperparameters``); ``cfg`` gives N, the seed, the
    device, the hidden width of the actors, the belief model (EM as CE-PG's, or true) and, with
    ``cfg.speed``, the mission clock: ``target`` and ``init_model`` are models per
    step made a tick's worth, unless ``models_per_tick`` (the server's EM fitted per tick).

    With ``checkpoint`` (a directory) the run is resumable: it continues from the checkpoint there
    if one exists (of this same run, or a ValueError says what differs), saves one every
    ``checkpoint_every`` seconds and when stopped, and ends the same, bit for bit, as a run
    never interrupted (shared/learning/marl/checkpoint.py). The caller removes the directory once
    the result is safely stored (``remove_checkpoint``)."""
    module = _module(name)
    run = MarlRun(
        name,
        graph,
        target,
        sensor,
        cfg,
        hyper,
        init_model,
        progress,
        should_stop,
        checkpoint,
        checkpoint_every,
        models_per_tick,
    )
    result: TrainResult = module.train(run, hyper)
    return result


def remove_checkpoint(path: str | Path) -> None:
    """Delete a resumable run's checkpoint directory (and a save's leftovers beside it)."""
    Checkpointer(path, {}).remove()

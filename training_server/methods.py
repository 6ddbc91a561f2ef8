"""The methods a training run trains a fleet's teams with, their default budgets, and one team's
training in the training process (training_server/jobs.py), resumable across server restarts.

    cepg    CE-PG (Algorithm 2) with the run's variant and beta, warm-started from the current
            version's team where it is a CE-PG team of the same size, variant and width
    pg      CE-PG with beta = 1 (Eq. 9 without the cross entropy: the paper's PG)
    maddpg, masac, facmac, mambpo, mappo
            the MARL baselines (shared/learning/marl), trained from scratch with their documented
            hyperparameters (docs/SPEC.md section 11) and the run's overrides

Every method trains under the run's EM model with the robots' beliefs on that model (as the robot
agents keep them), and every team is saved in the snapshot format robots already read.

Default budgets (``default_episodes``): the protocol's, the episodes at which each method's
capture time stops improving on OFFICE, N = 4 (CE-PG: 4 x 10^5, shared/tools/experiments/budget.py
FULL; a MARL baseline: its plateau, set in shared/learning/marl/<method>.py). A run's
``budget_fraction`` scales them; its ``episodes`` replaces them.

Resuming (``RunFolder``, ``<data>/runs/<run>/``): a run's EM models are kept after EM (written
after the npz they describe, so models.json means both are whole), each team
once trained, and a MARL team's checkpoint while it trains (every ``CHECKPOINT_EVERY_S`` and when
the server stops), so that a run the server restarts during goes on where it was: EM and the
teams done are not redone, a MARL team continues from its checkpoint (the same numbers as a run
never interrupted), and a CE-PG team in training starts that team again (CE-PG is not
checkpointed; its teams take minutes).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal, get_args

MarlMethod = Literal["maddpg", "masac", "facmac", "mambpo", "mappo"]  # shared.core.choices.ALGORITHMS but cepg
Method = Literal["cepg", "pg", "maddpg", "masac", "facmac", "mambpo", "mappo"]
MARL_METHODS: tuple[str, ...] = get_args(MarlMethod)
METHODS: tuple[str, ...] = get_args(Method)
# what `algorithm: "best"` trains unless told: the methods that were best somewhere in the
# recorded protocol (results/fig7, N = 4): MASAC and MAPPO on OFFICE, PG on MUSEUM, and CE-PG
DEFAULT_CANDIDATES = ("cepg", "pg", "masac", "mappo")
CEPG_EPISODES = 400_000  # the protocol's CE-PG budget (shared/tools/experiments/budget.py FULL.train)
CHECKPOINT_EVERY_S = 60.0  # a MARL team's checkpoint at least this often while it trains on the server


def default_episodes(method: str) -> int:
    """The protocol's training budget of ``method`` (module docstring)."""
    if method in ("cepg", "pg"):
        return CEPG_EPISODES
    from shared.learning.marl import hyperparameters

    return int(hyperparameters(method).episodes)


def check_hyperparameters(method: str, given: dict[str, Any]) -> list[str]:
    """``given`` (name -> value) as `--hp KEY=VALUE` items for ``method``, checked against the
    method's hyperparameters; a ValueError names an unknown one or a value of the wrong type."""
    items = [f"{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in given.items()]
    if method in ("cepg", "pg"):
        if items:
            raise ValueError(f"hyperparameters.{method}: CE-PG takes the run's own fields (beta, lr, variant)")
        return []
    from shared.learning.marl import hyperparameters

    try:
        hyperparameters(method, items)
    except ValueError as exc:
        raise ValueError(f"hyperparameters.{method}: {str(exc).removeprefix('--hp ')}") from None
    return items


@dataclass
class TrainedTeam:
    """A team a run trained: its torch snapshot (policy, meta) and where it came from."""

    method: str
    robots: int
    snapshot: Any  # shared.learning.team_snapshot.Snapshot
    summary: dict[str, Any]


class RunFolder:
    """A run's working directory ``<data>/runs/<run>/`` (module docstring): models.json after EM,
    teams/<method>-<k>/ (a snapshot) once a team is trained, checkpoints/<method>-<k>/ while a
    MARL team trains."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)

    def save_models(self, models: dict[str, Any], info: dict[str, Any]) -> None:
        """The run's EM models, bit for bit (a MARL checkpoint names the model it trains under),
        and what its metrics record of them."""
        import io

        import numpy as np

        from shared.core.files import atomic_write

        arrays: dict[str, Any] = {}
        for name, m in models.items():
            arrays |= {f"{name}.src": m.src, f"{name}.dst": m.dst, f"{name}.prob": m.prob, f"{name}.b0": m.b0}
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic_write(self.path / "models.npz", buf.getvalue())
        kinds = {name: m.kind for name, m in models.items()}
        atomic_write(self.path / "models.json", json.dumps({"kinds": kinds, "info": info}).encode())

    def load_models(self, graph: Any) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """(name -> TargetModel, info) saved after EM, or None before."""
        import numpy as np

        from shared.core.models import TargetModel

        try:
            doc = json.loads((self.path / "models.json").read_text(encoding="utf-8"))
        except FileNotFoundError:
            return None
        with np.load(self.path / "models.npz") as z:
            models = {
                name: TargetModel(graph.n, z[f"{name}.src"], z[f"{name}.dst"], z[f"{name}.prob"], z[f"{name}.b0"], kind)
                for name, kind in doc["kinds"].items()
            }
        return models, doc["info"]

    def team_dir(self, method: str, robots: int) -> Path:
        return self.path / "teams" / f"{method}-{robots}"

    def checkpoint_dir(self, method: str, robots: int) -> Path:
        return self.path / "checkpoints" / f"{method}-{robots}"

    def load_team(self, method: str, robots: int, graph: Any) -> TrainedTeam | None:
        from shared.learning.team_snapshot import load_snapshot

        where = self.team_dir(method, robots)
        if not (where / "policy.json").is_file():
            return None
        snap = load_snapshot(where, graph)
        return TrainedTeam(method, robots, snap, dict(snap.meta.get("summary") or {}))

    def remove(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)


def train_team(
    method: str,
    robots: int,
    episodes: int,
    world: tuple[Any, Any, Any],
    params: Any,
    current: Any,
    folder: RunFolder,
    progress: Callable[[dict[str, Any]], None],
    should_stop: Callable[[], bool],
    speed: float | None = None,
) -> TrainedTeam | None:
    """Train ``method``'s team for ``robots`` robots for ``episodes`` episodes in ``world`` (graph,
    the run's EM model, sensor), save it in ``folder`` and return it; None when stopped first
    (a MARL team's checkpoint then holds where it was). ``speed``: the team trains on the map's
    travel times (CE-PG and every MARL baseline), the EM model being per tick."""
    from shared.learning.config import TrainConfig, fine_tune_defaults
    from shared.learning.team_snapshot import save_snapshot

    graph, model, sensor = world
    if method in ("cepg", "pg"):
        from shared.learning.train import train

        variant = params.variant or (current.variant if current.meta.get("algorithm", "cepg") == "cepg" else "cepg")
        warm = (
            current.robots == robots and current.meta.get("algorithm", "cepg") == "cepg" and current.variant == variant
        )
        # a fine-tune of the general policy takes its own defaults (shared/learning/config.py fine_tune_defaults)
        defaults = {
            **asdict(TrainConfig(robots=robots)),
            **(fine_tune_defaults(graph.n) if warm and current.general else {}),
        }
        beta = 1.0 if method == "pg" else (defaults["beta"][0] if params.beta is None else params.beta)
        cfg = TrainConfig(
            robots=robots,
            episodes=episodes,
            beta=[beta],
            lr=defaults["lr"] if params.lr is None else [params.lr],
            j_unit=defaults["j_unit"],
            batch=defaults["batch"],
            variant=variant,
            belief="true",
            seed=params.seed,
            hidden=current.policy.H if warm else None,
            speed=speed,
        )
        res = train(
            graph,
            model,
            sensor,
            cfg,
            init_policy=current if warm else None,
            progress=progress,
            should_stop=should_stop,
            models_per_tick=speed is not None,
        )
        config = {**cfg.to_dict(), "warm_start": bool(warm)}
        algorithm, beta_list = "cepg", cfg.per_robot(cfg.beta, "beta")
    else:
        from shared.learning.marl import hyperparameters, train_marl

        cfg = TrainConfig(robots=robots, seed=params.seed, belief="true", algorithm=method, speed=speed)
        items = check_hyperparameters(method, params.hyperparameters_of(method))
        hyper = hyperparameters(method, items, episodes=episodes)
        res = train_marl(
            method,
            graph,
            model,
            sensor,
            cfg,
            hyper,
            progress=progress,
            should_stop=should_stop,
            checkpoint=folder.checkpoint_dir(method, robots),
            checkpoint_every=CHECKPOINT_EVERY_S,
            models_per_tick=speed is not None,
        )
        config = {
            **cfg.to_dict(),
            "episodes": hyper.episodes,
            "batch": hyper.envs,
            "lr": [hyper.lr],
            "hyperparameters": hyper.to_dict(),
        }
        variant, algorithm, beta_list = "cepg", method, []
    if res.interrupted:
        return None
    where = folder.team_dir(method, robots)
    config = {**config, "method": method, "target": "em-estimate", "map": graph.name}
    save_snapshot(where, res.policy, graph, model, sensor, variant, beta_list, config, res.summary, algorithm=algorithm)
    if method in MARL_METHODS:
        from shared.learning.marl import remove_checkpoint

        remove_checkpoint(folder.checkpoint_dir(method, robots))
    team = folder.load_team(method, robots, graph)
    assert team is not None
    return team

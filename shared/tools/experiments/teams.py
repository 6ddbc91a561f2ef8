"""The learned teams the figures fly: each trained once (as a runner job), cached as a snapshot
under results/snapshots/ named by its settings, retrained when its recorded training
configuration differs, and flown by ``Team``."""

from __future__ import annotations

import hashlib
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypedDict

from shared.tools.experiments.budget import LEARNED, MARL
from shared.tools.experiments.context import Context
from shared.tools.experiments.costs import train_cost
from shared.tools.runner import Job, directory_files

CHECKPOINTS_ENV = "MURES_CHECKPOINTS"  # where unfinished MARL teams keep their checkpoints (checkpoint_dir)


def sensor_for(variant: str, eta_fn: float = 0.0, eta_fp: float = 0.0) -> Any:
    """The world's sensor for a method: CE-PG+ robots see N[p] (the paper's broader field of view)."""
    from shared.core.models import Sensor

    return Sensor(eta_fn=eta_fn, eta_fp=eta_fp, detection="neighbourhood" if variant == "cepg+" else "node")


class EmSchedule(TypedDict):
    em_first: int
    em_missions: int
    em_max_iter: int


def em_schedule(episodes: int) -> EmSchedule:
    """The EM settings of a cached team of ``episodes`` training episodes: small runs get fewer EM
    missions and iterations (EM is most of a small run)."""
    return {
        "em_first": min(8192, episodes // 2),
        "em_missions": min(512, max(32, episodes // 64)),
        "em_max_iter": 300 if episodes >= 100_000 else 100,
    }


def trained_with(path: Path, config: dict[str, Any]) -> bool:
    """A snapshot at ``path`` trained with exactly ``config`` (code defaults included) exists."""
    meta = path / "policy.json"
    return meta.exists() and json.loads(meta.read_text(encoding="utf-8")).get("training") == json.loads(
        json.dumps(config)
    )


def noise_label(eta_fn: float, eta_fp: float) -> str:
    """A job label's sensor noise: ", eta_fn X, eta_fp Y", each only where nonzero."""
    return f"{f', eta_fn {eta_fn}' if eta_fn else ''}{f', eta_fp {eta_fp}' if eta_fp else ''}"


def seed_label(seed: int) -> str:
    """A job label's training seed, named where it is not the default 0 (fig5's seeds tell its teams apart)."""
    return f", seed {seed}" if seed else ""


def cepg_snapshot(
    ctx: Context,
    env: str,
    robots: int,
    beta: float,
    episodes: int,
    seed: int,
    variant: str = "cepg",
    eta_fn: float = 0.0,
    eta_fp: float = 0.0,
) -> Path:
    """A cached team (beta = 1: PG) trained with EM-estimated beliefs in the world of ``sensor_for``.
    A cached snapshot whose stored training configuration differs (an older default) is retrained."""
    tag = "".join(
        f"-{k}{v}" for k, v in (("", variant if variant != "cepg" else ""), ("fn", eta_fn), ("fp", eta_fp)) if v
    )
    rel = f"snapshots/{env}-N{robots}-beta{beta}-{episodes}-s{seed}{tag}"
    args = (rel, env, robots, beta, episodes, seed, variant, eta_fn, eta_fp)
    if not trained_with(ctx.root / rel, cepg_config(*args[1:])[1]):
        noise = noise_label(eta_fn, eta_fp)
        which = "PG" if beta == 1 else variant.upper() + (f" beta {beta}" if beta != LEARNED[variant][1] else "")
        label = f"training {which} {env} N={robots}{noise}, {episodes:,} episodes{seed_label(seed)}"
        weight = train_cost("cepg", env, robots, episodes, eta_fn)
        ctx.obtain(Job(rel, label, train_cepg, args, weight=weight, reports=True))
    return ctx.root / rel


def cepg_config(
    env: str, robots: int, beta: float, episodes: int, seed: int, variant: str, eta_fn: float, eta_fp: float
) -> tuple[Any, dict[str, Any]]:
    """The TrainConfig of a cached CE-PG team and the configuration its snapshot records."""
    from shared.core.graph import builtin_graph
    from shared.learning.config import TrainConfig

    cfg = TrainConfig(
        robots=robots, episodes=episodes, beta=[beta], seed=seed, variant=variant, **em_schedule(episodes)
    )
    return cfg, {**cfg.to_dict(), "map": builtin_graph(env).name}


def train_cepg(
    rel: str,
    env: str,
    robots: int,
    beta: float,
    episodes: int,
    seed: int,
    variant: str,
    eta_fn: float,
    eta_fp: float,
    progress: Any = None,
) -> dict[str, bytes]:
    """A job (shared/tools/runner.py): train a CE-PG team, return its snapshot's files."""
    import tempfile

    from shared.core.graph import builtin_graph
    from shared.core.models import uniform_walk
    from shared.learning.team_snapshot import save_snapshot
    from shared.learning.train import train

    g = builtin_graph(env)
    cfg, config = cepg_config(env, robots, beta, episodes, seed, variant, eta_fn, eta_fp)
    sensor = sensor_for(variant, eta_fn, eta_fp)
    res = train(g, uniform_walk(g), sensor, cfg, progress=progress)
    with tempfile.TemporaryDirectory() as tmp:
        save_snapshot(Path(tmp) / rel, res.policy, g, res.model, sensor, variant, [beta] * robots, config, res.summary)
        return directory_files(Path(tmp) / rel, Path(tmp))


def marl_snapshot(
    ctx: Context,
    env: str,
    robots: int,
    algorithm: str,
    episodes: int | None,
    seed: int,
    eta_fn: float = 0.0,
    eta_fp: float = 0.0,
    overrides: tuple[str, ...] = (),
) -> Path:
    """A cached team of a MARL baseline (``episodes`` None: the method's default budget), with
    EM-estimated beliefs as CE-PG's, retrained when its stored configuration differs."""
    from shared.learning.marl.checkpoint import saved_episodes

    args = (env, robots, algorithm, episodes, seed, eta_fn, eta_fp, overrides)
    _cfg, _hyper, rel, config = marl_config(*args)
    if not trained_with(ctx.root / rel, config):
        noise = noise_label(eta_fn, eta_fp)
        extra = f" ({', '.join(overrides)})" if overrides else ""
        label = (
            f"training {algorithm.upper()} {env} N={robots}{noise}{extra}, {config['episodes']:,} episodes"
            f"{seed_label(seed)}"
        )
        weight = train_cost(algorithm, env, robots, config["episodes"], eta_fn)
        checkpoint = checkpoint_dir(ctx.root) / rel
        done = saved_episodes(checkpoint)
        if done:  # a killed run's checkpoint: the job continues from it, and only the rest is left
            label += f", continuing from its checkpoint at {done:,}"
            weight *= max(0.0, 1 - done / config["episodes"])
        ctx.obtain(Job(rel, label, train_marl, args, weight=weight, reports=True, checkpoint=str(checkpoint)))
    return ctx.root / rel


def marl_config(
    env: str,
    robots: int,
    algorithm: str,
    episodes: int | None,
    seed: int,
    eta_fn: float,
    eta_fp: float,
    overrides: tuple[str, ...],
) -> tuple[Any, Any, str, dict[str, Any]]:
    """A MARL team's TrainConfig, hyperparameters, snapshot path (relative) and recorded configuration."""
    from shared.core.graph import builtin_graph
    from shared.learning.config import TrainConfig
    from shared.learning.marl import hyperparameters

    hyper = hyperparameters(algorithm, list(overrides), episodes=episodes)
    if hasattr(hyper, "warmup"):
        hyper.warmup = min(hyper.warmup, hyper.episodes // 4)  # small runs learn for most of their budget
    tag = "".join(f"-{k}{v}" for k, v in (("fn", eta_fn), ("fp", eta_fp)) if v)
    tag += "".join(f"-{o.replace('=', '')}" for o in overrides)
    rel = f"snapshots/{env}-N{robots}-{algorithm}-{hyper.episodes}-s{seed}{tag}"
    cfg = TrainConfig(robots=robots, algorithm=algorithm, seed=seed, **em_schedule(hyper.episodes))
    config = {
        **cfg.to_dict(),
        "episodes": hyper.episodes,
        "batch": hyper.envs,
        "lr": [hyper.lr],
        "hyperparameters": hyper.to_dict(),
        "map": builtin_graph(env).name,
    }
    return cfg, hyper, rel, config


def train_marl(
    env: str,
    robots: int,
    algorithm: str,
    episodes: int | None,
    seed: int,
    eta_fn: float,
    eta_fp: float,
    overrides: tuple[str, ...],
    progress: Any = None,
    checkpoint: str | None = None,
) -> dict[str, bytes]:
    """A job (shared/tools/runner.py): train a MARL baseline, return its snapshot's files. With
    ``checkpoint`` (a directory) the training saves its state there every ``CHECKPOINT_EVERY_S``
    seconds and continues from it when the job is started again after being killed; the
    directory is removed once the snapshot's files are made. Where it cannot be made (a Dask
    worker on another machine, without the caller's file system) the team trains without."""
    import tempfile

    from shared.core.graph import builtin_graph
    from shared.core.models import uniform_walk
    from shared.learning.marl import remove_checkpoint, train_marl
    from shared.learning.team_snapshot import save_snapshot

    cfg, hyper, rel, config = marl_config(env, robots, algorithm, episodes, seed, eta_fn, eta_fp, overrides)
    g = builtin_graph(env)
    sensor = sensor_for("cepg", eta_fn, eta_fp)
    if checkpoint is not None:
        try:
            Path(checkpoint).parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            print(f"{rel}: no checkpoints ({exc}); training without", file=sys.stderr, flush=True)
            checkpoint = None
    res = train_marl(algorithm, g, uniform_walk(g), sensor, cfg, hyper, progress=progress, checkpoint=checkpoint)
    with tempfile.TemporaryDirectory() as tmp:
        save_snapshot(
            Path(tmp) / rel, res.policy, g, res.model, sensor, "cepg", [], config, res.summary, algorithm=algorithm
        )
        files = directory_files(Path(tmp) / rel, Path(tmp))
    if checkpoint is not None:
        remove_checkpoint(checkpoint)
    return files


def checkpoint_dir(results: Path) -> Path:
    """Where the unfinished MARL teams of the results directory ``results`` keep their checkpoints:
    under ``$MURES_CHECKPOINTS``, else ``$XDG_CACHE_HOME/mures/checkpoints``, else
    ``~/.cache/mures/checkpoints``, in a folder named after the results directory's absolute path
    (its name and a hash of the path), so that two results directories never share a team's
    checkpoint. Outside the checkout: a checkout laid anew on the same machine (a fresh clone at
    the same place) still finds a killed team's checkpoint and continues it, and
    git never sees it (a checkpoint is a work file, gigabytes for a team with a full replay
    buffer, never a result)."""
    base = os.environ.get(CHECKPOINTS_ENV) or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "mures", "checkpoints"
    )
    where = Path(results).resolve()
    return Path(base) / f"{where.name}-{hashlib.sha256(str(where).encode()).hexdigest()[:12]}"


def learned_team(ctx: Context, env: str, robots: int, method: str, eta_fn: float = 0.0, eta_fp: float = 0.0) -> Team:
    """seed -> searcher for a learned method (pg, cepg, cepg+, c-cepg, or a MARL baseline),
    training it if not cached."""
    if method in MARL:
        path = marl_snapshot(ctx, env, robots, method, ctx.budget.marl_episodes(method), 0, eta_fn, eta_fp)
        return Team(path, env, sensor_for("cepg", eta_fn, eta_fp), robots)
    variant, beta = LEARNED[method]
    path = cepg_snapshot(ctx, env, robots, beta, ctx.budget.train, 0, variant, eta_fn, eta_fp)
    return Team(path, env, sensor_for(variant, eta_fn, eta_fp), robots)


def training_summary(ctx: Context | None, path: Path) -> dict[str, Any]:
    """A cached team's training summary (a stand-in while ``ctx`` is planned)."""
    from shared.core.snapshot_format import read_meta

    if ctx is not None and ctx.planned:
        return {"episodes": 0, "wall_seconds": 0.0, "episodes_per_second": 0.0, "learning_curve": []}
    return dict(read_meta(path)["summary"])


@dataclass
class Team:
    """seed -> the team of the cached snapshot at ``path`` flown by ``robots`` robots (loaded when
    first flown); it says how the team was trained (``trained``) and what it is (``describe``)."""

    path: Path
    env: str
    sensor: Any
    robots: int
    _snap: Any = None

    def ready(self) -> bool:
        return (self.path / "policy.json").exists()

    def _loaded(self) -> Any:
        if self._snap is None:
            from shared.core.graph import builtin_graph
            from shared.learning.team_snapshot import load_snapshot

            self._snap = load_snapshot(self.path, builtin_graph(self.env))
        return self._snap

    def __call__(self, seed: int) -> Any:
        from shared.core.graph import builtin_graph
        from shared.learning.team_snapshot import PolicySearcher

        return PolicySearcher(self._loaded(), builtin_graph(self.env), self.sensor, self.robots, seed=seed)

    def trained(self) -> dict[str, Any]:
        """The episodes the team was trained for (as run: a budget is rounded up to whole batches)
        and its training seed, from the snapshot itself."""
        from shared.core.snapshot_format import read_meta

        meta = read_meta(self.path)
        return {
            "train_episodes": meta.get("summary", {}).get("episodes", meta.get("training", {}).get("episodes")),
            "training_seeds": [meta["training"]["seed"]] if "seed" in meta.get("training", {}) else [],
        }

    def describe(self) -> dict[str, Any]:
        from shared.core.snapshot_format import read_meta

        return {"team": self.path.name, "weights": read_meta(self.path)["weights"]["sha256"]}

"""`mures experiment NAME [--quick]` and `mures report`: the paper's figures as data, plots and a report.

Each experiment writes ``results/<name>/<name>.json`` (every cell with mean, 95% CI, episodes,
seed; the setup; the machine and date), ``<name>.csv`` and ``<name>.png``. Trained snapshots are
cached under ``results/snapshots/`` and reused. ``mures report`` turns whatever results exist into
docs/results.md; nothing in it is typed by hand.

Experiments: fig4 (toy learning curves), fig5 (beta), fig6 (the variants), fig7 (all methods,
N = 1..5, OFFICE and MUSEUM), fig8 (decision time per team step, measured in fig7), fig9 and fig10
(sensor noise: capture time, false alarms), fig11 (all methods under eta_fn), fig12 and fig13
(robustness), marl (the MARL baselines at their default budgets on OFFICE and WARD with learning
curves, and a small hyperparameter sweep). ``all`` runs them in turn. Budgets: ``FULL`` is the
paper's protocol, ``QUICK`` fits CI. Every evaluated cell is cached under ``results/cells/``. With
``--workers K`` or ``--dask-scheduler``, ``plan`` lists the jobs an experiment needs and the caches
lack (teams to train, cells to evaluate whose teams exist), shared/tools/runner.py runs them in
parallel, round after round, and the experiment then runs on the cached teams and cells.
"""

from __future__ import annotations

import csv
import datetime as dt
import hashlib
import itertools
import json
import math
import os
import platform
import re
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TypedDict

import numpy as np

from shared.core.files import atomic_write
from shared.tools.runner import Job, directory_files, run_jobs

EXPERIMENTS = ("fig4", "fig5", "fig6", "fig7", "fig8", "fig9", "fig10", "fig11", "fig12", "fig13", "marl")
PLANNERS = ("fhpe", "fhpe-sa", "milp", "d-milp")


def machine() -> dict[str, Any]:
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


# While an experiment is planned (``plan``), its figure function runs without training or
# evaluating: the teams it needs that are not cached are collected here as jobs, cells are
# placeholders, and nothing is written.
_PLAN: list[Job] | None = None
# ... and the cells it will evaluate once their teams are trained: (label, estimated seconds)
_LATER: dict[str, tuple[str, float]] = {}  # by the cell's settings and its team's path
# ... and why the run would be refused, if it would lose recorded rows (``_refuse_loss``)
_REFUSED: list[str] = []
# Evaluated cells are cached as JSON under <results>/cells/ (set by ``run`` and ``plan``): a killed
# run resumes from the cells it finished, and cells can be evaluated by the parallel runner too.
_CELLS: Path | None = None
CELL_VERSION = 1  # bump when evaluation itself changes: cached cells are then evaluated again
# A learned team's decision time (fig8) is timed on one-at-a-time episodes until they add up to this
# many team steps (the cell's mean capture time says how many episodes): three episodes, as before,
# were a few dozen steps at N = 5 and gave FACMAC 1.75 and then 1.06 ms in two quiet flights. Part
# of such a cell's key, so that cells timed the old way are timed again (not the planners' cells,
# whose timing did not change).
TIMED_TEAM_STEPS = 400


def _write(
    out: Path, name: str, data: dict[str, Any], rows: list[dict[str, Any]], b: Budget | None = None
) -> list[dict[str, Any]]:
    """Write a figure's data (JSON, and CSV of its rows); returns the rows written. ``b``: the run's
    Budget, for the figures recorded by map and team size (fig5 to fig13). With ``b.add`` (`--add`)
    the rows recorded for maps and team sizes this run did not cover are kept beside the new ones,
    and ``parts`` lists each run's setup and the (map, N) it covers (``_merge``). A run that would
    lose recorded rows is refused (``_refuse_loss``), while it is planned, before any work."""
    recorded = out / f"{name}.json"
    old = json.loads(recorded.read_text()) if b is not None and recorded.exists() else None
    add, overwrite = (False, True) if b is None else (b.add, b.overwrite)
    if old is not None and not overwrite:
        try:
            _refuse_loss(recorded, old, data, rows, add)
        except ValueError as refused:
            if _PLAN is None:
                raise
            _REFUSED.append(str(refused))  # ``run`` raises it before any job, ``plan_lines`` says it
    if _PLAN is not None:
        return rows
    if old is not None and add:
        data, rows = _merge(old, data, rows)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / f"{name}.json", json.dumps({**data, "rows": rows}, indent=1) + "\n")
    if rows:
        with open(out / f"{name}.csv", "w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))  # rows differ
            w.writeheader()
            w.writerows(rows)
    return rows


def _refuse_loss(
    recorded: Path, old: dict[str, Any], data: dict[str, Any], rows: list[dict[str, Any]], add: bool
) -> None:
    """Raise a ValueError, naming what would be lost, where writing this run's rows would drop
    recorded ones without `--overwrite`: without `--add`, rows of maps and team sizes the run does
    not cover (a run narrowed with --maps or --robots would otherwise leave only its own), and a
    `--quick` run's rows in place of the paper's protocol rows of the same map and team size."""
    covers = _covers(rows)
    new = {tuple(c) for c in covers}
    held = old.get("rows") or []
    if not add:
        dropped = [c for c in _covers(held) if tuple(c) not in new]
        if dropped:
            raise ValueError(
                f"{recorded} holds rows of {_pairs(dropped)}, which this run does not cover: --add keeps them "
                "beside this run's, --overwrite drops them; nothing was run or written"
            )
    if data.get("quick"):
        runs = old.get("parts") or [{**old, "covers": _covers(held)}]
        protocol = {tuple(c) for p in runs if p.get("quick") is False for c in p["covers"]}
        lost = [c for c in covers if tuple(c) in protocol]
        if lost:
            raise ValueError(
                f"{recorded} holds the paper's protocol rows of {_pairs(lost)}; a --quick run would replace them "
                "with its own: --results DIR writes elsewhere, --overwrite replaces them; nothing was run or written"
            )


def _pairs(covers: list[list[Any]]) -> str:
    """(map, N) pairs as 'OFFICE N = 1, 2; MUSEUM N = 4'."""
    by_map: dict[str, list[int]] = {}
    for env, N in covers:
        by_map.setdefault(env, []).append(N)
    return "; ".join(f"{env.upper()} N = {', '.join(map(str, Ns))}" for env, Ns in by_map.items())


def _place(env: str, N: int) -> tuple[int, int]:
    """Where a (map, N) goes in a figure: the paper's maps in its order (others after), then N."""
    return (PAPER_MAPS.index(env) if env in PAPER_MAPS else len(PAPER_MAPS), N)


def _covers(rows: list[dict[str, Any]]) -> list[list[Any]]:
    """The (map, N) pairs a figure's rows hold, in ``_place`` order."""
    return [list(p) for p in sorted({(r["map"], r["robots"]) for r in rows}, key=lambda p: _place(*p))]


def _merge(
    old: dict[str, Any], setup: dict[str, Any], rows: list[dict[str, Any]]
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """A recorded figure with a new run's rows added: the new rows replace the recorded ones of
    the same (map, N), the others stay. The setup's top level is the new run's, with ``maps`` and
    ``team_sizes`` widened to all rows, and ``parts``: every run whose rows remain, its setup and
    the (map, N) pairs it still covers, oldest first."""
    covered = {(r["map"], r["robots"]) for r in rows}
    kept = [r for r in old["rows"] if (r["map"], r["robots"]) not in covered]
    earlier = old.get("parts") or [{**{k: v for k, v in old.items() if k != "rows"}, "covers": _covers(old["rows"])}]
    parts = []
    for p in earlier:
        still = [c for c in p["covers"] if tuple(c) not in covered]
        if still:
            parts.append({**p, "covers": still})
    parts.append({**setup, "covers": _covers(rows)})
    merged = sorted(kept + rows, key=lambda r: _place(r["map"], r["robots"]))
    data = {**setup, "parts": parts}
    data["maps"] = list(dict.fromkeys(c[0] for c in _covers(merged)))
    if "team_sizes" in setup:
        data["team_sizes"] = sorted({r["robots"] for r in merged})
    return data, merged


def _say(text: str) -> None:
    if _PLAN is None:  # a planning pass's placeholder figures are not news
        print(text, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------- fig4
def fig4(root: Path, quick: bool) -> Path:
    """The toy of paper Fig. 4: P(A) of both robots over updates, CE-PG (beta 0.5) vs PG (beta 1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from shared.tools.toy import toy_fig4

    seeds = range(3 if quick else 10)
    updates = 150 if quick else 400
    rows = []
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    for ax, beta in zip(axes, (0.5, 1.0), strict=True):
        for s in seeds:
            run = toy_fig4(beta, seed=s, updates=updates, reward="own")
            pa = np.asarray(run.p_a)
            ax.plot(pa[:, 0], color="C0", alpha=0.5)
            ax.plot(pa[:, 1], color="C1", alpha=0.5)
            split = bool(max(pa[-1]) >= 0.9 and min(pa[-1]) <= 0.1)
            rows.append(
                {
                    "beta": beta,
                    "seed": s,
                    "updates": updates,
                    "p_a_robot1": round(float(pa[-1, 0]), 4),
                    "p_a_robot2": round(float(pa[-1, 1]), 4),
                    "split": split,
                }
            )
        ax.set_title(f"{'CE-PG' if beta < 1 else 'PG'} (beta = {beta})")
        ax.set_xlabel("update")
    axes[0].set_ylabel("P(go to A)")
    fig.tight_layout()
    out = root / "fig4"
    _write(out, "fig4", {"experiment": "fig4", "quick": quick, "reward": "own", "machine": machine()}, rows)
    fig.savefig(out / "fig4.png", dpi=110)
    plt.close(fig)
    return out


# ---------------------------------------------------------------------- budgets, teams, cells
PAPER_MAPS = ("office", "museum")


@dataclass(frozen=True)
class Budget:
    """How large each run is: the paper's protocol, or ``--quick`` (every experiment together
    inside CI, minutes on 2 cores: the learned teams are then barely trained, so quick numbers
    show that the pipeline works, not how good the method is)."""

    quick: bool
    episodes: int  # evaluation episodes per cell (the paper: 1500)
    train: int  # training episodes per learned team (the paper: 4 x 10^5)
    planner: int  # episodes for fhpe and milp (one MILP solve per team step); fhpe-sa runs 4x
    milp_limit: float  # HiGHS time limit per solve, seconds
    teams: tuple[int, ...]  # team sizes N of the sweeps (fig6, fig9, fig10)
    marl_train: int | None = None  # training episodes per MARL baseline; None: each method's default budget
    seeds: tuple[int, ...] = (0,)  # training seeds of fig5's teams (the other figures: seed 0)
    d_milp: int | None = None  # episodes for d-milp (N solves per team step); None: ``planner``
    maps: tuple[str, ...] = PAPER_MAPS  # the maps every figure runs on (`--maps`)
    robots: tuple[int, ...] | None = None  # team sizes of fig6, fig7, fig9, fig10 (`--robots`); None: theirs
    marl_train_for: tuple[tuple[str, int], ...] = ()  # (method, episodes): budgets that replace marl_train
    add: bool = False  # `--add`: fig5 to fig13 keep the recorded rows of the maps and team sizes not run
    overwrite: bool = False  # `--overwrite`: a run may drop or replace recorded rows (``_refuse_loss``)

    def with_train(self, episodes: int | None) -> Budget:
        if episodes is None:
            return self
        return replace(self, train=episodes, marl_train=episodes, marl_train_for=())

    def scaled(self, fraction: float) -> Budget:
        """Every learned team's budget times ``fraction`` (`--train-fraction`), the methods' ratios
        kept: a run at team sizes whose full budget does not fit states its own in every row."""
        if not 0 < fraction <= 1:
            raise ValueError(f"--train-fraction takes a fraction in (0, 1], not {fraction:g}")

        def part(episodes: int) -> int:
            return max(1, round(episodes * fraction))

        return replace(
            self,
            train=part(self.train),
            marl_train=None,
            marl_train_for=tuple((m, part(self.marl_episodes(m))) for m in MARL),
        )

    def marl_episodes(self, method: str) -> int:
        """Training episodes of a MARL baseline's teams in the figures: ``marl_train_for``'s, else
        ``marl_train``, else the method's default budget (its plateau on OFFICE, N = 4)."""
        return dict(self.marl_train_for).get(method) or self.marl_train or _marl_hyper_episodes(method)

    def planner_episodes(self, method: str) -> int:
        """Episodes a planner's cell flies: ``planner``, 4x for fhpe-sa, ``d_milp`` for d-milp."""
        return {"fhpe-sa": 4 * self.planner, "d-milp": self.d_milp or self.planner}.get(method, self.planner)

    def sizes(self, default: Iterable[int]) -> tuple[int, ...]:
        """The team sizes of a sweep whose own are ``default``, as ``--robots`` narrows them."""
        return tuple(default) if self.robots is None else self.robots


# The MARL baselines train for their default budgets (marl_train None): each method's plateau on
# OFFICE, N = 4, set with its evidence in shared/learning/marl/<method>.py
FULL = Budget(False, 1500, 400_000, 100, 1.0, (1, 2, 3, 4, 5), seeds=(0, 1, 2), d_milp=30)
QUICK = Budget(True, 200, 2_000, 1, 0.05, (2, 4), marl_train=1_000)
MARL = ("maddpg", "masac", "facmac", "mambpo", "mappo")  # shared.learning.marl.MARL_ALGORITHMS
# a setup's "marl_training_episodes" when no one budget is given: the defaults, or (--train-fraction)
# a fraction of each; "marl_training_episodes_by_method" has the numbers
MARL_DEFAULT, MARL_OWN = "each method's default", "each method's own"
SEED = 1  # evaluation seed of every cell (training seeds: 0)
CHECKPOINTS_ENV = "MURES_CHECKPOINTS"  # where unfinished MARL teams keep their checkpoints (checkpoint_dir)
ETAS = (0.0, 0.1, 0.3, 0.5)  # the paper's sensor-noise grid (Fig. 9-11)
LEARNED = {"pg": ("cepg", 1.0), "cepg": ("cepg", 0.5), "cepg+": ("cepg+", 0.5), "c-cepg": ("c-cepg", 0.5)}


def sensor_for(variant: str, eta_fn: float = 0.0, eta_fp: float = 0.0) -> Any:
    """The world's sensor for a method: CE-PG+ robots see N[p] (the paper's broader field of view)."""
    from shared.core.models import Sensor

    return Sensor(eta_fn=eta_fn, eta_fp=eta_fp, detection="neighbourhood" if variant == "cepg+" else "node")


class _EmSchedule(TypedDict):
    em_first: int
    em_missions: int
    em_max_iter: int


def _em_schedule(episodes: int) -> _EmSchedule:
    """The EM settings of a cached team of ``episodes`` training episodes: small runs get fewer EM
    missions and iterations (EM is most of a small run)."""
    return {
        "em_first": min(8192, episodes // 2),
        "em_missions": min(512, max(32, episodes // 64)),
        "em_max_iter": 300 if episodes >= 100_000 else 100,
    }


def _cached(path: Path, config: dict[str, Any]) -> bool:
    """A snapshot at ``path`` trained with exactly ``config`` (code defaults included) exists."""
    meta = path / "policy.json"
    return meta.exists() and json.loads(meta.read_text(encoding="utf-8")).get("training") == json.loads(
        json.dumps(config)
    )


def _noise(eta_fn: float, eta_fp: float) -> str:
    """A job label's sensor noise: ", eta_fn X, eta_fp Y", each only where nonzero."""
    return f"{f', eta_fn {eta_fn}' if eta_fn else ''}{f', eta_fp {eta_fp}' if eta_fp else ''}"


def _snapshot(
    root: Path,
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
    if not _cached(root / rel, _cepg_config(*args[1:])[1]):
        noise = _noise(eta_fn, eta_fp)
        which = "PG" if beta == 1 else variant.upper() + (f" beta {beta}" if beta != LEARNED[variant][1] else "")
        label = f"training {which} {env} N={robots}{noise}, {episodes:,} episodes{_seed_label(seed)}"
        weight = _train_cost("cepg", env, robots, episodes, eta_fn)
        _obtain(root, Job(rel, label, _train_cepg, args, weight=weight, reports=True))
    return root / rel


def _cepg_config(
    env: str, robots: int, beta: float, episodes: int, seed: int, variant: str, eta_fn: float, eta_fp: float
) -> tuple[Any, dict[str, Any]]:
    """The TrainConfig of a cached CE-PG team and the configuration its snapshot records."""
    from shared.core.graph import builtin_graph
    from shared.learning.config import TrainConfig

    cfg = TrainConfig(
        robots=robots, episodes=episodes, beta=[beta], seed=seed, variant=variant, **_em_schedule(episodes)
    )
    return cfg, {**cfg.to_dict(), "map": builtin_graph(env).name}


def _train_cepg(
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
    from shared.learning.snapshot import save_snapshot
    from shared.learning.train import train

    g = builtin_graph(env)
    cfg, config = _cepg_config(env, robots, beta, episodes, seed, variant, eta_fn, eta_fp)
    sensor = sensor_for(variant, eta_fn, eta_fp)
    res = train(g, uniform_walk(g), sensor, cfg, progress=progress)
    with tempfile.TemporaryDirectory() as tmp:
        save_snapshot(Path(tmp) / rel, res.policy, g, res.model, sensor, variant, [beta] * robots, config, res.summary)
        return directory_files(Path(tmp) / rel, Path(tmp))


def _seed_label(seed: int) -> str:
    """A job label's training seed, named where it is not the default 0 (fig5's seeds tell its teams apart)."""
    return f", seed {seed}" if seed else ""


def _obtain(root: Path, job: Job) -> None:
    """Run a training job now, in this process, or collect it while planning."""
    if _PLAN is not None:
        _PLAN.append(job)
        return
    run_jobs([job], root, say=_say)  # in this process; the runner restores its thread count


def _marl_snapshot(
    root: Path,
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
    _cfg, _hyper, rel, config = _marl_config(*args)
    if not _cached(root / rel, config):
        noise = _noise(eta_fn, eta_fp)
        extra = f" ({', '.join(overrides)})" if overrides else ""
        label = (
            f"training {algorithm.upper()} {env} N={robots}{noise}{extra}, {config['episodes']:,} episodes"
            f"{_seed_label(seed)}"
        )
        weight = _train_cost(algorithm, env, robots, config["episodes"], eta_fn)
        checkpoint = checkpoint_dir(root) / rel
        done = saved_episodes(checkpoint)
        if done:  # a killed run's checkpoint: the job continues from it, and only the rest is left
            label += f", continuing from its checkpoint at {done:,}"
            weight *= max(0.0, 1 - done / config["episodes"])
        _obtain(root, Job(rel, label, _train_marl, args, weight=weight, reports=True, checkpoint=str(checkpoint)))
    return root / rel


def _marl_config(
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
    cfg = TrainConfig(robots=robots, algorithm=algorithm, seed=seed, **_em_schedule(hyper.episodes))
    config = {
        **cfg.to_dict(),
        "episodes": hyper.episodes,
        "batch": hyper.envs,
        "lr": [hyper.lr],
        "hyperparameters": hyper.to_dict(),
        "map": builtin_graph(env).name,
    }
    return cfg, hyper, rel, config


def _train_marl(
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
    from shared.learning.snapshot import save_snapshot

    cfg, hyper, rel, config = _marl_config(env, robots, algorithm, episodes, seed, eta_fn, eta_fp, overrides)
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


def _learned(
    root: Path, env: str, robots: int, method: str, b: Budget, eta_fn: float = 0.0, eta_fp: float = 0.0
) -> _Team:
    """seed -> searcher for a learned method (pg, cepg, cepg+, c-cepg, or a MARL baseline),
    training it if not cached."""
    if method in MARL:
        path = _marl_snapshot(root, env, robots, method, b.marl_episodes(method), 0, eta_fn, eta_fp)
        return _flown(path, env, sensor_for("cepg", eta_fn, eta_fp), robots)
    variant, beta = LEARNED[method]
    path = _snapshot(root, env, robots, beta, b.train, 0, variant, eta_fn, eta_fp)
    return _flown(path, env, sensor_for(variant, eta_fn, eta_fp), robots)


def _summary(path: Path) -> dict[str, Any]:
    """A cached team's training summary (a stand-in while planning)."""
    from shared.core.snapshot import read_meta

    if _PLAN is not None:
        return {"episodes": 0, "wall_seconds": 0.0, "episodes_per_second": 0.0, "learning_curve": []}
    return dict(read_meta(path)["summary"])


@dataclass
class _Team:
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
            from shared.learning.snapshot import load_snapshot

            self._snap = load_snapshot(self.path, builtin_graph(self.env))
        return self._snap

    def __call__(self, seed: int) -> Any:
        from shared.core.graph import builtin_graph
        from shared.learning.snapshot import PolicySearcher

        return PolicySearcher(self._loaded(), builtin_graph(self.env), self.sensor, self.robots, seed=seed)

    def trained(self) -> dict[str, Any]:
        """The episodes the team was trained for (as run: a budget is rounded up to whole batches)
        and its training seed, from the snapshot itself."""
        from shared.core.snapshot import read_meta

        meta = read_meta(self.path)
        return {
            "train_episodes": meta.get("summary", {}).get("episodes", meta.get("training", {}).get("episodes")),
            "training_seeds": [meta["training"]["seed"]] if "seed" in meta.get("training", {}) else [],
        }

    def describe(self) -> dict[str, Any]:
        from shared.core.snapshot import read_meta

        return {"team": self.path.name, "weights": read_meta(self.path)["weights"]["sha256"]}


def _flown(path: Path, env: str, sensor: Any, robots: int) -> _Team:
    """seed -> the cached snapshot's team flown by ``robots`` robots."""
    return _Team(path, env, sensor, robots)


@dataclass(frozen=True)
class _Reference:
    """seed -> random, greedy or a planner (true model, all robots' observations)."""

    env: str
    robots: int
    method: str
    sensor: Any
    kw: tuple[tuple[str, Any], ...] = ()

    def ready(self) -> bool:
        return True

    def __call__(self, seed: int) -> Any:
        from shared.core.graph import builtin_graph
        from shared.core.models import uniform_walk
        from shared.planners import make_baseline
        from shared.registry import make_searcher

        g = builtin_graph(self.env)
        if self.method in ("random", "greedy"):
            return make_searcher(self.method, g, uniform_walk(g), self.sensor, seed)
        return make_baseline(self.method, g, uniform_walk(g), self.sensor, self.robots, seed, **dict(self.kw))

    def trained(self) -> dict[str, Any]:
        return {"train_episodes": None, "training_seeds": []}

    def describe(self) -> dict[str, Any]:
        return {"reference": self.method, "kw": dict(self.kw)}


def _reference(env: str, robots: int, method: str, sensor: Any, **kw: Any) -> _Reference:
    """seed -> searcher for random, greedy and the planners (true model, all robots' observations)."""
    return _Reference(env, robots, method, sensor, tuple(sorted(kw.items())))


def _cell(
    env: str,
    robots: int,
    method: str,
    make: _Team | _Reference,
    episodes: int,
    seed: int = SEED,
    sensor: Any = None,
    withdraw_at: list[int | None] | None = None,
    latency: bool = False,
    times: bool = False,
) -> dict[str, Any]:
    """One evaluated cell: capture time and false alarms (mean, 95% CI) over ``episodes`` seeded
    episodes; with ``latency``, the decision time per team step, one episode at a time (batch 1,
    so batching does not hide the per-step latency; the simulator's step included); with
    ``times``, the (episodes,) capture times under "capture_times" (for paired comparisons).

    A cell is evaluated once: its row is cached under <results>/cells/ by what determines it (the
    map, N, the method and its team's weights or the planner's settings, the sensor, the episodes
    and seed, a withdrawal). While planning, a cell whose team exists becomes a job for the
    parallel runner (``_cell_job``) and a placeholder row is returned."""
    from shared.core.models import Sensor

    sensor = sensor or Sensor()
    nan = float("nan")
    placeholder = {
        "map": env,
        "robots": robots,
        "method": method,
        "mean_capture_time": nan,
        "ci95_halfwidth": nan,
        "false_alarms_per_episode": nan,
        "false_alarms_ci95_halfwidth": nan,
    }
    args = {
        "env": env,
        "robots": robots,
        "method": method,
        "episodes": episodes,
        "seed": seed,
        "sensor": sensor.to_json(),
        "withdraw_at": withdraw_at,
        "latency": latency,
    }
    withdrawn = f", withdrawn {withdraw_at}" if withdraw_at else ""
    team = f", team {make.path.name}" if isinstance(make, _Team) else ""  # fig5 flies several teams of one method
    label = (
        f"evaluating {method} {env} N={robots}{_noise(sensor.eta_fn, sensor.eta_fp)}{withdrawn} ({episodes} episodes)"
        f"{team}"
    )
    if not make.ready():  # planning: its team is not trained yet
        later = json.dumps({**args, "team": str(getattr(make, "path", ""))}, sort_keys=True)
        _LATER[later] = (f"{label}, once its team exists", _cell_cost(method, args, make))
        return placeholder
    what = {**args, "make": make.describe(), "version": CELL_VERSION}
    if latency and method not in PLANNERS:  # a planner's is timed on its own episodes, as before
        what["timed_team_steps"] = TIMED_TEAM_STEPS
    key = hashlib.sha256(json.dumps(what, sort_keys=True).encode()).hexdigest()[:20]
    cached = None if _CELLS is None else _CELLS / f"{key}.json"
    if cached is not None and cached.exists():
        row = json.loads(cached.read_text())
    elif _PLAN is not None:
        files = None
        if isinstance(make, _Team):  # the worker gets the snapshot's files, not this process's objects
            files = directory_files(make.path, make.path)
            make = _Team(make.path, make.env, make.sensor, make.robots)
        weight = _cell_cost(method, args, make)
        _PLAN.append(Job(f"cell-{key}", label, _cell_job, (key, args, make, files), weight=weight, reports=True))
        return placeholder
    else:
        row = _evaluate_cell(make=make, **args)
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(cached, json.dumps(row).encode())
    out = {k: v for k, v in row.items() if k != "capture_times"}
    if isinstance(make, _Team):  # the row names its team: results/snapshots/<team> flies it again
        out["team"] = make.path.name
    if times:
        out["capture_times"] = np.asarray(row["capture_times"], dtype=np.float64)
    return out


# What the jobs cost on one core of the 2-core VM this project is developed on, for the runner's
# ETA and `--plan`'s estimate (never for results): training, ms per episode on OFFICE at N = 4,
# and MUSEUM's cost TRAIN_MAP_COST times OFFICE's, sqrt(4 / N) times for N robots (fewer robots,
# longer episodes: CE-PG at N = 1 and 2 cost 1.9 and 1.2 times N = 4; the baselines' N = 1 teams
# 1.7 to 3.6 times). Calibrated on 2026-12-04 against the cache's 159 teams (wall_seconds in
# training_summary.json, mostly run beside one other job, so a job's share of a busy machine):
# each rate is the geometric mean of its teams' measured / estimated time on each map
# (`python benchmarks/protocol_remaining.py --calibrate`, which should print about 1 for every
# row; single teams lie within 0.25 to 2.7 times their estimate, CE-PG's short runs the most).
# Planners, seconds per team step: MILP at its 1 s limit (every solve at N >= 2 reaches it;
# 0.6 s at N = 1), D-MILP one such solve per robot (0.6 s a step at N = 1, 3.0-3.8 s at N = 4),
# FHPE-SA about 5 ms per robot on OFFICE (7.5 / 9 / 12 / 14 / 24 ms a step at N = 1..5) and FHPE,
# which searches the joint paths, 0.5 / 1.0 / 11 ms a step at N = 1 / 2 / 3 (fig8 OFFICE and the
# cache's wall_seconds / team_steps; FHPE runs at N <= 3 only); MUSEUM's planner steps cost
# MAP_COST times OFFICE's (FHPE-SA at N = 4: 36 against 14 ms; FHPE not measured there); episodes
# of about 8 steps on OFFICE and 17 on MUSEUM at N = 4, 4 / N times that for N robots.
# Both cost as many steps as the episodes take, and a sensor that misses the target with
# probability eta_fn stretches them by about 1 / (1 - eta_fn) (each detection chance succeeds with
# 1 - eta_fn): the cache's OFFICE teams trained under eta_fn 0.1 / 0.3 / 0.5 took 1.08-1.10 /
# 1.34-1.38 / 1.76-1.98 times eta_fn 0's steps per episode (CE-PG, MASAC, MAPPO), against 1.11 /
# 1.43 / 2; D-MILP's 30 episodes there averaged 8.9 / 11.2 / 14.0 steps.
TRAIN_MS_PER_EPISODE = {"cepg": 0.19, "mappo": 1.24, "maddpg": 5.3, "masac": 6.0, "facmac": 5.35, "mambpo": 8.2}
TRAIN_MAP_COST = {"museum": {"cepg": 2.4, "mappo": 3.0, "maddpg": 2.5, "masac": 3.6, "facmac": 2.6, "mambpo": 3.0}}
MAP_COST = {"office": 1.0, "museum": 2.5}  # a planner's (below), and a method's without its own above
STEPS_AT_N4 = {"office": 8.0, "museum": 17.0}
FHPE_SECONDS_PER_STEP = {1: 0.001, 2: 0.002, 3: 0.015}  # by N; beyond N = 3 (not run) the joint search explodes


def _miss_stretch(eta_fn: float) -> float:
    """How much longer episodes get when the sensor misses with probability ``eta_fn``
    (see TRAIN_MS_PER_EPISODE); at most 10x: a sensor that never detects runs every episode to
    T_max, a bounded length, where 1 / (1 - eta_fn) would be infinite."""
    return 1.0 / (1.0 - min(float(eta_fn), 0.9))


def _train_cost(method: str, env: str, robots: int, episodes: int, eta_fn: float = 0.0) -> float:
    """A team's expected training time in seconds on one core (see TRAIN_MS_PER_EPISODE)."""
    per = TRAIN_MS_PER_EPISODE.get(method, TRAIN_MS_PER_EPISODE["cepg"]) / 1000
    per_map = TRAIN_MAP_COST.get(env, {}).get(method, MAP_COST.get(env, 1.0))
    return episodes * per * per_map * (4 / robots) ** 0.5 * _miss_stretch(eta_fn)


def _cell_cost(method: str, args: dict[str, Any], make: Any = None) -> float:
    """A cell's expected time in seconds on one core (see TRAIN_MS_PER_EPISODE): a planner's
    decisions (at the MILP time limit ``make``, a ``_Reference``, passes it; else the protocol's),
    or a learned team's batched episodes (and its decision timing with ``latency``)."""
    steps = args["episodes"] * STEPS_AT_N4.get(args["env"], 10.0) * 4 / args["robots"]
    steps *= _miss_stretch(args["sensor"]["eta_fn"])
    if method in PLANNERS:
        limit = dict(getattr(make, "kw", ())).get("time_limit", FULL.milp_limit)
        return steps * _planner_step_cost(method, args["env"], args["robots"], limit)
    return steps * 2e-4 + (20.0 if args.get("latency") else 0.0)


def _planner_step_cost(method: str, env: str, robots: int, time_limit: float = FULL.milp_limit) -> float:
    """A planner's seconds per team step on one core (see TRAIN_MS_PER_EPISODE); ``time_limit``
    the MILP planners' seconds per solve."""
    if method == "milp":
        return time_limit  # every solve reaches it at N >= 2
    if method == "d-milp":
        return time_limit * robots  # one solve per robot
    per_map = MAP_COST.get(env, 1.0)
    if method == "fhpe-sa":
        return 0.005 * robots * per_map
    return FHPE_SECONDS_PER_STEP.get(robots, 1.0) * per_map


def _cell_job(
    key: str, args: dict[str, Any], make: Any, files: dict[str, bytes] | None, progress: Any = None
) -> dict[str, bytes]:
    """A cell evaluated by a worker: a team's snapshot comes as its files (no shared file system)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        if files is not None:
            for rel, data in files.items():
                (Path(tmp) / rel).write_bytes(data)
            make = _Team(Path(tmp), make.env, make.sensor, make.robots)
        row = _evaluate_cell(make=make, **args, progress=progress)
    return {f"cells/{key}.json": json.dumps(row).encode()}


def _evaluate_cell(
    env: str,
    robots: int,
    method: str,
    make: _Team | _Reference,
    episodes: int,
    seed: int,
    sensor: dict[str, Any],
    withdraw_at: list[int | None] | None,
    latency: bool,
    progress: Any = None,
) -> dict[str, Any]:
    """A cell's row (``_cell``), with its capture times; ``progress`` is told of each chunk of
    episodes (``evaluate``'s)."""
    from shared.core.graph import builtin_graph
    from shared.core.models import Sensor, uniform_walk
    from shared.engine.evaluate import evaluate, mean_ci95

    g = builtin_graph(env)
    sens = Sensor(**sensor)
    t0 = time.perf_counter()
    batched = method not in PLANNERS  # planners plan one episode at a time
    res = evaluate(
        g,
        uniform_walk(g),
        sens,
        robots,
        make,
        episodes=episodes,
        seed=seed,
        chunk=4096 if batched else 1,
        withdraw_at=withdraw_at,
        progress=progress,
    )
    wall = time.perf_counter() - t0
    s = res.summary()
    fa, fa_half = mean_ci95(res.false_alarms)
    row = {
        "map": env,
        "robots": robots,
        "method": method,
        "eta_fn": sens.eta_fn,
        "eta_fp": sens.eta_fp,
        "detection": sens.detection,
        "episodes": episodes,
        "seed": seed,
        **make.trained(),
        "mean_capture_time": round(s["mean_capture_time"], 3),
        "ci95_halfwidth": round(s["ci95_halfwidth"], 3),
        "censored_fraction": round(s["censored_fraction"], 4),
        "false_alarms_per_episode": round(fa, 4),
        "false_alarms_ci95_halfwidth": round(fa_half, 4),
        "team_steps": int(res.capture_time.sum()),
        "wall_seconds": round(wall, 2),
    }
    if latency:
        if batched:  # one episode at a time, about TIMED_TEAM_STEPS team steps in all
            timed = min(episodes, max(3, math.ceil(TIMED_TEAM_STEPS / max(1.0, s["mean_capture_time"]))))
            t1 = time.perf_counter()
            one = evaluate(g, uniform_walk(g), sens, robots, make, episodes=timed, seed=seed + 99, chunk=1)
            row["decision_ms"] = round((time.perf_counter() - t1) / max(1.0, float(one.capture_time.sum())) * 1e3, 4)
            row["timed_team_steps"] = int(one.capture_time.sum())
        else:  # planners already ran one episode at a time
            row["decision_ms"] = round(wall / max(1.0, float(res.capture_time.sum())) * 1e3, 4)
    row["capture_times"] = [int(x) for x in res.capture_time]
    return row


def _all_methods(root: Path, env: str, N: int, b: Budget, eta_fn: float = 0.0) -> list[dict[str, Any]]:
    """Every method of the paper's comparison on one (map, N, eta_fn), with decision times.

    random, greedy and the learned teams fly the same ``b.episodes`` episodes (one batch, seed
    SEED: the target's path and every random draw of an episode do not depend on the robots'
    moves), so each one's difference to CE-PG is paired episode by episode: ``_paired_to_cepg``."""
    sensor = sensor_for("cepg", eta_fn)
    rows = [
        _cell(env, N, m, _reference(env, N, m, sensor), b.episodes, sensor=sensor, latency=True, times=True)
        for m in ("random", "greedy")
    ]
    for m in (*LEARNED, *MARL):
        rows.append(
            _cell(
                env,
                N,
                m,
                _learned(root, env, N, m, b, eta_fn),
                b.episodes,
                sensor=sensor_for(LEARNED[m][0] if m in LEARNED else "cepg", eta_fn),
                latency=True,
                times=True,
            )
        )
    rows = _paired_to_cepg(rows)
    for m in PLANNERS:
        if m == "fhpe" and N > 3:
            continue  # 36^4 joint paths and more per decision: see the report
        kw = {"time_limit": b.milp_limit} if "milp" in m else {}
        rows.append(
            _cell(env, N, m, _reference(env, N, m, sensor, **kw), b.planner_episodes(m), sensor=sensor, latency=True)
        )
    if N <= 2:
        rows.append(
            _cell(env, N, "oracle", _reference(env, N, "oracle", sensor), b.episodes, sensor=sensor, latency=True)
        )
    _say(f"  {env} N={N} eta_fn={eta_fn}: " + ", ".join(f"{r['method']} {r['mean_capture_time']:.1f}" for r in rows))
    return rows


def _paired_to_cepg(rows: list[dict[str, Any]], cepg: str = "cepg") -> list[dict[str, Any]]:
    """Rows with "capture_times" lose them and gain, where CE-PG's row (method ``cepg``) flew the
    same episodes, the paired difference (method - cepg) with its 95% CI over those episodes:
    ``diff_to_cepg`` and ``diff_to_cepg_ci95`` (negative: the method captures sooner than CE-PG)."""
    from shared.engine.evaluate import mean_ci95

    ref = next((r for r in rows if r["method"] == cepg and "capture_times" in r), None)
    out = []
    for r in rows:
        times = r.get("capture_times")
        r = {k: v for k, v in r.items() if k != "capture_times"}
        if ref is not None and times is not None and r["method"] != cepg:
            base = ref["capture_times"]
            same = (r["episodes"], r["seed"]) == (ref["episodes"], ref["seed"]) and len(times) == len(base) > 1
            if same:
                dm, dh = mean_ci95(np.asarray(times) - base)
                r.update(diff_to_cepg=round(dm, 3), diff_to_cepg_ci95=round(dh, 3))
        out.append(r)
    return out


def _planner_setup(b: Budget) -> dict[str, Any]:
    """The planners' budget as the setup of a figure that flies them (fig7, fig11) records it."""
    return {
        "planner_episodes": b.planner,
        "fhpe_sa_episodes": b.planner_episodes("fhpe-sa"),
        "d_milp_episodes": b.planner_episodes("d-milp"),
        "milp_time_limit_s": b.milp_limit,
    }


def _setup(name: str, b: Budget, **extra: Any) -> dict[str, Any]:
    return {
        "experiment": name,
        "quick": b.quick,
        "episodes": b.episodes,
        "training_episodes": b.train,
        "marl_training_episodes": b.marl_train or (MARL_OWN if b.marl_train_for else MARL_DEFAULT),
        **({} if b.marl_train else {"marl_training_episodes_by_method": {m: b.marl_episodes(m) for m in MARL}}),
        "seed": SEED,
        "maps": list(b.maps),
        **extra,
        "machine": machine(),
    }


# ---------------------------------------------------------------------- fig7 / fig8
def fig7(root: Path, b: Budget) -> Path:
    """All methods, N = 1..5, OFFICE and MUSEUM (paper Fig. 7), and their decision times (Fig. 8)."""
    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    for env in b.maps:
        for N in b.sizes(range(1, 6)):
            _say(f"fig7: {env} N={N}")
            rows += _all_methods(root, env, N, b)
    out = root / "fig7"
    setup = _setup(
        "fig7",
        b,
        team_sizes=list(b.sizes(range(1, 6))),
        **_planner_setup(b),
        horizons={"fhpe": 2, "fhpe-sa": 5, "milp": 5, "d-milp": 5},
        discount=0.97,
        wall_seconds=round(time.perf_counter() - t_start, 1),
    )
    rows = _write(out, "fig7", setup, rows, b)
    _plot_fig7(out, rows)
    _plot_fig8(root / "fig8", rows, setup)
    return out


def _plot_fig7(out: Path, rows: list[dict[str, Any]]) -> None:
    _plot_by_team_size(out / "fig7.png", rows, "mean_capture_time", "capture time (steps)", half="ci95_halfwidth")


def _plot_by_team_size(
    path: Path, rows: list[dict[str, Any]], value: str, ylabel: str, half: str | None = None, log: bool = False
) -> None:
    """One panel per map, a line per method over the team sizes N: ``value`` (with ``half`` as
    error bars when given; a log axis with ``log``). Fig. 7's capture times, Fig. 8's decision times."""
    if _PLAN is not None:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, panels = _panels(plt, rows)
    for ax, env in panels:
        for method in dict.fromkeys(r["method"] for r in rows):
            pts = [r for r in rows if r["map"] == env and r["method"] == method]
            if not pts:
                continue
            x, y = [r["robots"] for r in pts], [r[value] for r in pts]
            if half is None:
                ax.plot(x, y, label=method, **_style(method))
            else:
                ax.errorbar(x, y, yerr=[r[half] for r in pts], capsize=3, label=method, **_style(method))
        if log:
            ax.set_yscale("log")
        ax.set_title(env.upper())
        ax.set_xlabel("robots N")
        ax.set_ylabel(ylabel)
        _team_ticks(ax, [r["robots"] for r in rows if r["map"] == env])
    _legend(fig, [ax for ax, _ in panels])
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


# One look per method in every plot: the CE-PG family solid, the MARL baselines dashed, the
# planners dotted, the references (random, greedy, oracle) grey; 16 methods outrun a 10-colour cycle.
_LOOKS = {
    "pg": ("tab:blue", "o", "-"),
    "cepg": ("tab:red", "o", "-"),
    "cepg+": ("tab:purple", "o", "-"),
    "c-cepg": ("tab:brown", "o", "-"),
    "maddpg": ("tab:pink", "s", "--"),
    "masac": ("tab:olive", "s", "--"),
    "facmac": ("tab:cyan", "s", "--"),
    "mambpo": ("tab:orange", "s", "--"),
    "mappo": ("tab:green", "s", "--"),
    "fhpe": ("#9467bd", "^", ":"),
    "fhpe-sa": ("#2ca02c", "^", ":"),
    "milp": ("#1f77b4", "^", ":"),
    "d-milp": ("#d62728", "^", ":"),
    "random": ("0.55", "x", "-."),
    "greedy": ("0.35", "+", "-."),
    "oracle": ("0.1", "*", "-."),
}


def _style(method: str) -> dict[str, Any]:
    """matplotlib keywords of a method's line (``_LOOKS``; others get the default cycle)."""
    if method not in _LOOKS:
        return {"marker": "o"}
    color, marker, line = _LOOKS[method]
    return {"color": color, "marker": marker, "linestyle": line}


def _team_ticks(ax: Any, sizes: list[int]) -> None:
    """Team sizes on the x axis: a tick at each N drawn, half a robot of margin either side."""
    if sizes:
        ticks = sorted(set(sizes))
        ax.set_xticks(ticks)
        ax.set_xlim(ticks[0] - 0.5, ticks[-1] + 0.5)


def _legend(fig: Any, axes: list[Any]) -> None:
    """Lay the panels out, then one legend for the whole figure, right of them, with every method any
    panel drew."""
    seen: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(label, handle)
    fig.tight_layout()
    fig.legend(list(seen.values()), list(seen), fontsize=8, loc="center left", bbox_to_anchor=(1.0, 0.5))


def _plot_fig8(out: Path, rows: list[dict[str, Any]], setup: dict[str, Any]) -> None:
    if _PLAN is not None:
        return
    sel = [{k: r[k] for k in ("map", "robots", "method", "decision_ms")} for r in rows]
    _write(
        out,
        "fig8",
        {
            "experiment": "fig8",
            "from": "fig7",
            "quick": setup["quick"],
            "machine": setup["machine"],
            "note": "ms per team step, one episode at a time, simulator step included",
        },
        sel,
    )
    _plot_by_team_size(out / "fig8.png", sel, "decision_ms", "decision time per team step (ms)", log=True)


# ---------------------------------------------------------------------- fig5, fig6
BETAS = (0.1, 0.3, 0.5, 0.7, 0.9, 1.0)


def fig5(root: Path, b: Budget) -> Path:
    """beta in {0.1, 0.3, 0.5, 0.7, 0.9} and 1 (PG) for a 4-robot team on OFFICE and MUSEUM (paper
    Fig. 5), a team per training seed of ``b.seeds``. Every team is flown on the same evaluation
    episodes (seed SEED), so a beta's team and the PG team of the same training seed meet the same
    target paths: their difference is paired episode by episode. Each row: the capture time pooled
    over the seeds' episodes, each seed's mean, and the paired difference to beta = 1 with two 95%
    CIs, over the pooled episodes (evaluation noise only) and over the training seeds (Student t,
    S - 1 degrees of freedom: what another training run would give)."""

    N, rows = 4, []
    for env in b.maps:
        rows += fig5_rows(root, env, b, N)
        _say(
            f"fig5: {env}: " + ", ".join(f"beta {r['beta']} {r['mean_capture_time']:.2f}" for r in rows[-len(BETAS) :])
        )
    out = root / "fig5"
    rows = _write(out, "fig5", _setup("fig5", b, robots=N, training_seeds=list(b.seeds)), rows, b)
    _bars(out / "fig5.png", rows, "beta", "capture time (steps), N = 4")
    return out


def fig5_rows(root: Path, env: str, b: Budget, N: int = 4) -> list[dict[str, Any]]:
    """fig5's rows of one map, a row per beta (``fig5``), its teams trained first where missing."""
    sensor = sensor_for("cepg")
    times: dict[tuple[float, int], np.ndarray] = {}
    trained: dict[float, Any] = {}  # the episodes the teams ran (whole batches), as the cells say
    cells: dict[float, list[dict[str, Any]]] = {beta: [] for beta in BETAS}
    for beta in BETAS:
        for s in b.seeds:
            team = _flown(_snapshot(root, env, N, beta, b.train, s), env, sensor, N)
            cell = _cell(env, N, "pg" if beta == 1.0 else "cepg", team, b.episodes, times=True)
            times[beta, s] = cell.pop("capture_times", np.zeros(0))
            trained[beta] = cell.get("train_episodes", b.train)
            cells[beta].append(cell)
    return [
        {
            **_beta_row(env, N, beta, b, times),
            "train_episodes": trained[beta],
            "teams": [c.get("team") for c in cells[beta]],  # one per training seed
            "wall_seconds": round(sum(c.get("wall_seconds", 0.0) for c in cells[beta]), 2),
        }
        for beta in BETAS
    ]


def _beta_row(env: str, N: int, beta: float, b: Budget, times: dict[tuple[float, int], np.ndarray]) -> dict[str, Any]:
    """fig5's row of one beta from the capture times of every (beta, training seed) team."""
    from scipy.stats import t as student_t

    from shared.engine.evaluate import mean_ci95

    nan = float("nan")
    row: dict[str, Any] = {
        "map": env,
        "robots": N,
        "method": "pg" if beta == 1.0 else "cepg",
        "beta": beta,
        "train_episodes": b.train,
        "training_seeds": list(b.seeds),
        "episodes": b.episodes,
        "seed": SEED,
    }
    if _PLAN is not None:
        return {**row, "mean_capture_time": nan, "ci95_halfwidth": nan}
    pooled = np.concatenate([times[beta, s] for s in b.seeds])
    m, h = mean_ci95(pooled)
    row.update(
        mean_capture_time=round(m, 3),
        ci95_halfwidth=round(h, 3),
        per_seed_mean=[round(float(times[beta, s].mean()), 3) for s in b.seeds],
    )
    if beta != 1.0:
        diffs = [times[beta, s] - times[1.0, s] for s in b.seeds]  # same episodes, same target paths
        dm, dh = mean_ci95(np.concatenate(diffs))
        seed_means = np.array([d.mean() for d in diffs])
        S = len(seed_means)
        sh = float(student_t.ppf(0.975, S - 1) * seed_means.std(ddof=1) / np.sqrt(S)) if S > 1 else nan
        row.update(
            diff_to_pg=round(dm, 3),
            diff_to_pg_ci95_episodes=round(dh, 3),
            diff_to_pg_ci95_seeds=round(sh, 3),
            diff_to_pg_per_seed=[round(float(x), 3) for x in seed_means],
        )
    return row


def fig6(root: Path, b: Budget) -> Path:
    """CE-PG vs CE-PG+ (sensing N[p]) vs C-CE-PG (collective belief) for N in the sweep (paper Fig. 6)."""
    rows = []
    for env in b.maps:
        for N in b.sizes(b.teams):
            for m in ("cepg", "cepg+", "c-cepg"):
                rows.append(_cell(env, N, m, _learned(root, env, N, m, b), b.episodes, sensor=sensor_for(m)))
            _say(f"fig6: {env} N={N}: " + ", ".join(f"{r['method']} {r['mean_capture_time']:.1f}" for r in rows[-3:]))
    out = root / "fig6"
    rows = _write(out, "fig6", _setup("fig6", b), rows, b)
    _bars(out / "fig6.png", rows, "robots", "capture time (steps)")
    return out


# ---------------------------------------------------------------------- fig9, fig10, fig11
def _noise_sweep(root: Path, b: Budget, name: str, eta: str, value: str, ylabel: str) -> Path:
    """CE-PG teams trained and flown with each ``eta`` ("eta_fn" or "eta_fp") of ETAS, the other 0."""
    rows = []
    for env in b.maps:
        for N in b.sizes(b.teams):
            for x in ETAS:
                rows.append(
                    _cell(
                        env,
                        N,
                        "cepg",
                        _learned(root, env, N, "cepg", b, **{eta: x}),
                        b.episodes,
                        sensor=sensor_for("cepg", **{eta: x}),
                    )
                )
            _say(f"{name}: {env} N={N}: " + ", ".join(f"{r[value]:.2f}" for r in rows[-len(ETAS) :]))
    out = root / name
    rows = _write(out, name, _setup(name, b), rows, b)
    _lines(out / f"{name}.png", rows, eta, value, ylabel)
    return out


def fig9(root: Path, b: Budget) -> Path:
    """CE-PG's capture time for eta_fn in {0, 0.1, 0.3, 0.5} (eta_fp = 0), teams trained with that
    sensor (paper Fig. 9)."""
    return _noise_sweep(root, b, "fig9", "eta_fn", "mean_capture_time", "capture time (steps)")


def fig10(root: Path, b: Budget) -> Path:
    """CE-PG's false alarms per episode (the team's total) for eta_fp in {0, 0.1, 0.3, 0.5}
    (eta_fn = 0), teams trained with that sensor (paper Fig. 10)."""
    return _noise_sweep(root, b, "fig10", "eta_fp", "false_alarms_per_episode", "false alarms per episode")


def fig11(root: Path, b: Budget) -> Path:
    """All methods at N = 4 for eta_fn in {0, 0.1, 0.3, 0.5} (paper Fig. 11)."""
    rows = []
    t_start = time.perf_counter()
    for env in b.maps:
        for eta in ETAS:
            rows += _all_methods(root, env, 4, b, eta_fn=eta)
    out = root / "fig11"
    rows = _write(
        out,
        "fig11",
        _setup(
            "fig11",
            b,
            robots=4,
            **_planner_setup(b),
            wall_seconds=round(time.perf_counter() - t_start, 1),
        ),
        rows,
        b,
    )
    _bars(out / "fig11.png", rows, "eta_fn", "capture time (steps), N = 4")
    return out


# ---------------------------------------------------------------------- fig12, fig13
def fig12(root: Path, b: Budget) -> Path:
    """Robustness: a 4-robot team loses robot 4 at t = 5 (paper Fig. 12), against the intact team."""
    N, rows = 4, []
    sensor = sensor_for("cepg")
    for env in b.maps:
        for withdraw in (None, [None, None, None, 5]):
            label = "none" if withdraw is None else "r4@t5"
            for m in ("random", "greedy", "pg", "cepg", *MARL):
                make = _reference(env, N, m, sensor) if m in ("random", "greedy") else _learned(root, env, N, m, b)
                rows.append({**_cell(env, N, m, make, b.episodes, withdraw_at=withdraw), "withdrawn": label})
    out = root / "fig12"
    rows = _write(out, "fig12", _setup("fig12", b), rows, b)
    _bars(out / "fig12.png", rows, "withdrawn", "capture time (steps), N = 4")
    return out


def fig13(root: Path, b: Budget) -> Path:
    """Robustness: a team trained for 5 robots flown by k = 1..5 of them (paper Fig. 13), against
    teams trained for k. Each row's ``diff_to_cepg`` pairs it with CE-PG's team of the same
    training (trained for 5, or for k) on the same episodes."""

    rows = []
    sensor = sensor_for("cepg")
    for env in b.maps:
        cells: dict[tuple[str, int, str], dict[str, Any]] = {}
        for m in ("cepg", *MARL):
            path = (
                _snapshot(root, env, 5, 0.5, b.train, 0)
                if m == "cepg"
                else _marl_snapshot(root, env, 5, m, b.marl_episodes(m), 0)
            )
            for k in range(1, 6):
                for trained, make in (("5", _flown(path, env, sensor, k)), ("k", _learned(root, env, k, m, b))):
                    row = _cell(env, k, f"{m} trained for {trained}", make, b.episodes, times=True)
                    cells[trained, k, m] = {**row, "trained_for": 5 if trained == "5" else k}
        # every cell of a k flies the same episodes: each team's difference to CE-PG's of the same
        # training (for 5, or for k) is paired episode by episode
        for k in range(1, 6):
            for trained in ("5", "k"):
                group = [cells[trained, k, m] for m in ("cepg", *MARL)]
                paired = _paired_to_cepg(group, cepg=f"cepg trained for {trained}")
                cells.update(((trained, k, m), r) for m, r in zip(("cepg", *MARL), paired, strict=True))
        rows += [cells[trained, k, m] for m in ("cepg", *MARL) for k in range(1, 6) for trained in ("5", "k")]
    out = root / "fig13"
    rows = _write(out, "fig13", _setup("fig13", b), rows, b)
    _bars(out / "fig13.png", rows, "robots", "capture time (steps)")
    return out


def maps_in(rows: list[dict[str, Any]]) -> list[str]:
    """The maps a figure's rows cover, the paper's first, in the paper's order."""
    have = list(dict.fromkeys(r["map"] for r in rows))
    return [m for m in PAPER_MAPS if m in have] + [m for m in have if m not in PAPER_MAPS]


def _panels(plt: Any, rows: list[dict[str, Any]]) -> tuple[Any, list[tuple[Any, str]]]:
    """A figure with one panel per map of ``rows`` (``maps_in``): the figure and (axes, map) pairs."""
    maps = maps_in(rows) or list(PAPER_MAPS)
    fig, axes = plt.subplots(1, len(maps), figsize=(5.5 * len(maps), 4), squeeze=False)
    return fig, list(zip(axes[0], maps, strict=True))


def _bars(path: Path, rows: list[dict[str, Any]], key: str, ylabel: str) -> None:
    if _PLAN is not None:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, panels = _panels(plt, rows)
    for ax, env in panels:
        sel = [r for r in rows if r["map"] == env]
        groups = list(dict.fromkeys(r[key] for r in sel))
        methods = list(dict.fromkeys(r["method"] for r in sel))
        w = 0.8 / len(methods)
        for j, m in enumerate(methods):
            pts = [(i, r) for i, gk in enumerate(groups) for r in sel if r[key] == gk and r["method"] == m]
            ax.bar(
                [i + j * w for i, _ in pts],
                [r["mean_capture_time"] for _, r in pts],
                w,
                yerr=[r["ci95_halfwidth"] for _, r in pts],
                capsize=2,
                label=m,
                color=_style(m).get("color"),
            )
        ax.set_xticks(np.arange(len(groups)) + 0.4 - w / 2, [str(gk) for gk in groups])
        ax.set_xlabel(key)
        ax.set_title(env.upper())
        ax.set_ylabel(ylabel)
    _legend(fig, [ax for ax, _ in panels])
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _lines(path: Path, rows: list[dict[str, Any]], key: str, value: str, ylabel: str) -> None:
    if _PLAN is not None:
        return
    """One line per team size N: ``value`` (with its CI) against ``key``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    half = "ci95_halfwidth" if value == "mean_capture_time" else "false_alarms_ci95_halfwidth"
    fig, panels = _panels(plt, rows)
    for ax, env in panels:
        for N in sorted({r["robots"] for r in rows if r["map"] == env}):
            pts = [r for r in rows if r["map"] == env and r["robots"] == N]
            ax.errorbar(
                [r[key] for r in pts],
                [r[value] for r in pts],
                yerr=[r[half] for r in pts],
                marker="o",
                capsize=3,
                label=f"N = {N}",
            )
        ax.set_title(env.upper())
        ax.set_xlabel(key)
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------- the MARL baselines
# A small sweep per method around its defaults (one change at a time), at a tenth of the budget.
MARL_SWEEP: dict[str, list[tuple[str, ...]]] = {
    "mappo": [("lr=0.0003",), ("entropy=0.0",)],
    "masac": [("lr=0.001",), ("updates=8",)],
    "maddpg": [("lr=0.0003",), ("updates=8",)],
    "facmac": [("lr=0.0003",), ("updates=8",)],
    "mambpo": [("real_ratio=0.2",), ("updates=8",)],
}
MARL_MAPS = ("office", "ward")  # the paper's OFFICE and our WARD


def marl(root: Path, b: Budget) -> Path:
    """The MARL baselines at their default budgets on OFFICE and WARD, N = 4, with learning
    curves, against random and CE-PG; and a small hyperparameter sweep on OFFICE."""

    N, rows, curves, sweep = 4, [], {}, []
    sensor = sensor_for("cepg")
    t_start = time.perf_counter()
    for env in MARL_MAPS:
        rows.append(_cell(env, N, "random", _reference(env, N, "random", sensor), b.episodes, latency=True))
        rows.append(_cell(env, N, "cepg", _learned(root, env, N, "cepg", b), b.episodes, latency=True))
        for m in MARL:
            path = _marl_snapshot(root, env, N, m, b.marl_episodes(m), 0)
            summary = _summary(path)
            row = _cell(env, N, m, _learned(root, env, N, m, b), b.episodes, latency=True)
            row.update(
                train_episodes=summary["episodes"],
                train_wall_seconds=summary["wall_seconds"],
                train_episodes_per_second=summary["episodes_per_second"],
            )
            rows.append(row)
            curves[f"{env}/{m}"] = summary["learning_curve"]
            took = f"{summary['episodes']:,} episodes, {summary['wall_seconds']:.0f} s"
            _say(f"  marl: {env} {m} {row['mean_capture_time']:.2f} ({took})")
    for m in MARL:
        default_budget = _marl_hyper_episodes(m)
        episodes = b.marl_train or max(1_000, default_budget // 10)
        for overrides in [(), *MARL_SWEEP[m]]:
            path = _marl_snapshot(root, "office", N, m, episodes, 0, overrides=overrides)
            row = _cell("office", N, m, _flown(path, "office", sensor, N), b.episodes)
            sweep.append({**row, "overrides": list(overrides) or ["defaults"], "train_episodes": episodes})
    out = root / "marl"
    setup = _setup("marl", b, robots=N, maps=list(MARL_MAPS), wall_seconds=round(time.perf_counter() - t_start, 1))
    _write(out, "marl", {**setup, "sweep": sweep, "learning_curves": curves}, rows)
    _plot_curves(out / "marl_curves.png", curves)
    return out


def _marl_hyper_episodes(method: str) -> int:
    from shared.learning.marl import hyperparameters

    return int(hyperparameters(method).episodes)


def _plot_curves(path: Path, curves: dict[str, list[dict[str, Any]]]) -> None:
    if _PLAN is not None:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    maps = sorted({k.split("/")[0] for k in curves})
    fig, axes = plt.subplots(1, len(maps), figsize=(6 * len(maps), 4), squeeze=False)
    for ax, env in zip(axes[0], maps, strict=True):
        for key, pts in curves.items():
            if key.startswith(env + "/") and pts:
                ax.plot([p["episodes"] for p in pts], [p["mean_capture_time"] for p in pts], label=key.split("/")[1])
        ax.set_title(f"{env.upper()}, N = 4: training episodes' capture time")
        ax.set_xlabel("training episodes")
        ax.set_ylabel("capture time (steps)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


RUNNERS: dict[str, Callable[[Path, Budget], Path]] = {
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


def budget(
    name: str,
    quick: bool,
    train_episodes: int | None = None,
    maps: tuple[str, ...] | None = None,
    robots: tuple[int, ...] | None = None,
    train_fraction: float | None = None,
    add: bool = False,
    overwrite: bool = False,
) -> Budget:
    """The Budget of a run of experiment ``name`` (``run``'s arguments), checked: a ValueError names
    what is wrong."""
    if train_episodes is not None and train_fraction is not None:
        raise ValueError("give --train-episodes or --train-fraction, not both")
    b = (QUICK if quick else FULL).with_train(train_episodes)
    if train_fraction is not None:
        b = b.scaled(train_fraction)
    if name != "all" and name not in EXPERIMENTS:
        raise ValueError(f"experiment {name!r} is not implemented (have: {', '.join(EXPERIMENTS)}, all)")
    if add:
        if name in ("fig4", "marl"):
            raise ValueError(
                f"--add keeps rows of other maps and team sizes; {name} is not recorded by them: run it without --add"
            )
        b = replace(b, add=True)
    if overwrite:
        if name in ("fig4", "marl"):
            raise ValueError(f"--overwrite lets a run drop recorded rows of maps and team sizes; {name} has none")
        b = replace(b, overwrite=True)
    if maps is not None:
        if not maps or any(m not in PAPER_MAPS for m in maps):
            raise ValueError(f"--maps takes {' and/or '.join(PAPER_MAPS)} (comma-separated), not {','.join(maps)!r}")
        b = replace(b, maps=tuple(dict.fromkeys(maps)))
    if robots is not None:
        if not robots or any(n < 1 or n > 5 for n in robots):
            raise ValueError(f"--robots takes team sizes 1 to 5 (comma-separated), not {','.join(map(str, robots))}")
        b = replace(b, robots=tuple(sorted(set(robots))))
    return b


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
    ``overwrite`` (`--overwrite`; ``_refuse_loss``). The teams the experiment
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
    match = _label_filter(only)
    for _round in range(3):  # the teams (and the planners' cells), then the learned teams' cells
        planned = plan(name, root, b)
        if _REFUSED:
            raise ValueError(_REFUSED[0])
        jobs = [j for j in planned if match(j.label)]
        if not jobs:
            break  # what is planned now is what --only leaves
        if run_jobs(jobs, root, workers, scheduler, say=_say, until=until):  # a progress line per job, an ETA
            return None
    else:
        planned = plan(name, root, b) if only is not None else []
    if only is not None and planned:
        _say(
            f"{len(planned)} jobs of {name} left that --only {only!r} does not match "
            f"({_duration(sum(j.weight for j in planned))} on one core; --plan lists them)"
        )
        return None
    if name == "all":
        for e in EXPERIMENTS:
            if e != "fig8":
                t0 = time.perf_counter()
                _run_one(e, root, b, quick)
                _say(f"{e}: done in {time.perf_counter() - t0:.0f} s")
        return root
    return _run_one(name, root, b, quick)


def _run_one(name: str, root: Path, b: Budget, quick: bool) -> Path:
    global _CELLS
    if name == "fig4":
        return fig4(root, quick)
    _CELLS = root / "cells"
    try:
        if name == "fig8":
            return fig7(root, b).parent / "fig8"
        return RUNNERS[name](root, b)
    finally:
        _CELLS = None


def plan(name: str, root: Path, b: Budget) -> list[Job]:
    """The jobs an experiment (or ``all``) needs and the caches lack, without running anything:
    the teams to train, and the cells to evaluate whose teams exist (a cell of a team still to be
    trained comes up in the next plan); the figure functions run with placeholder cells and write
    nothing."""
    return outlook(name, root, b)[0]


def outlook(name: str, root: Path, b: Budget) -> tuple[list[Job], list[tuple[str, float]]]:
    """``plan``'s jobs, and the cells that wait for a team of those jobs: (label, estimated
    seconds on one core) each."""
    global _PLAN, _CELLS
    names = [e for e in EXPERIMENTS if e not in ("fig4", "fig8")] if name == "all" else [name]
    _PLAN, _CELLS = [], root / "cells"
    _LATER.clear()
    _REFUSED.clear()
    try:
        for e in names:
            if e in RUNNERS or e == "fig8":
                RUNNERS["fig7" if e == "fig8" else e](root, b)
        return list({j.key: j for j in _PLAN}.values()), list(_LATER.values())
    finally:
        _PLAN, _CELLS = None, None
        _LATER.clear()


def _label_filter(only: str | None) -> Callable[[str], bool]:
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
    match = _label_filter(only)
    jobs, later = outlook(name, root, b)
    refused = [f"{name}: as given, this run would be refused: {why}" for why in dict.fromkeys(_REFUSED)]
    return refused + _plan_lines(name, root, jobs, later, only, match)


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
    cells = [j for j in jobs if j.fn is _cell_job]
    teams = [j for j in jobs if j.fn is not _cell_job]
    total = sum(j.weight for j in jobs) + sum(w for _, w in later)
    matching = "" if only is None else f" (--only {only!r})"

    lines = [
        f"{name} in {root}{matching}: {len(teams)} teams to train, {len(cells)} cells to evaluate now and "
        f"{len(later)} once their teams exist; about {_duration(total)} on one core (K workers: at best that / K), "
        "estimated from this project's measured rates (shared/tools/experiments.py, TRAIN_MS_PER_EPISODE); "
        "nothing was run"
    ]
    lines += [f"  {_duration(j.weight):>7}  {j.label}" for j in sorted(jobs, key=lambda j: -j.weight)]
    lines += [f"  {_duration(w):>7}  {label}" for label, w in sorted(later, key=lambda x: -x[1])]
    return lines


# ---------------------------------------------------------------------- report
def report(root: Path, out: Path) -> Path:
    """docs/results.md from the recorded results (tables, plots, setup, a reading computed from the data)."""
    lines = [
        "# Results",
        "",
        "Generated by `mures report` from the data under `results/`; do not edit by hand.",
        "Regenerate with `mures experiment NAME [--quick]` then `mures report`.",
        "",
    ]
    rel = os.path.relpath(root, out.parent)
    f4 = root / "fig4" / "fig4.json"
    if f4.exists():
        d = json.loads(f4.read_text())
        lines += [
            "## Fig. 4: the toy (two robots, one step, A with 0.6, B with 0.4)",
            "",
            f"Setup: {len(d['rows']) // 2} seeds per beta, reward {d['reward']!r}, quick={d['quick']}; "
            f"{d['machine']['date']}.",
            "",
            "| beta | seeds | split (each robot >= 0.9 on a different node) |",
            "| --- | --- | --- |",
        ]
        for beta in (0.5, 1.0):
            rs = [r for r in d["rows"] if r["beta"] == beta]
            lines.append(f"| {beta} | {len(rs)} | {sum(r['split'] for r in rs)} |")
        lines += ["", f"![fig4]({rel}/fig4/fig4.png)", ""]
    f7 = root / "fig7" / "fig7.json"
    if f7.exists():
        d = json.loads(f7.read_text())
        rows = d["rows"]
        methods = list(dict.fromkeys(r["method"] for r in rows))
        lines += [
            f"## Fig. 7: capture time of all methods, N = {', '.join(map(str, sorted({r['robots'] for r in rows})))}",
            "",
            f"Setup: {d['episodes']} episodes per cell for random, greedy, the learned teams and oracle; "
            f"{d['planner_episodes']} for fhpe and milp, {d.get('d_milp_episodes', d['planner_episodes'])} for "
            f"d-milp, {d['fhpe_sa_episodes']} for fhpe-sa "
            f"(planners are slow; see Fig. 8); seed {d['seed']}; learned teams trained for "
            f"{_trained(d)} with EM-estimated beliefs (Gamma_hat_0 = I); horizons "
            f"{d['horizons']}, discount {d['discount']}, MILP time limit {d['milp_time_limit_s']} s per solve "
            f"(HiGHS); quick={d['quick']}; {d['machine']['cpus']} CPUs, {d['machine']['date']}; maps "
            f"{', '.join(m.upper() for m in d.get('maps', PAPER_MAPS))}, N = "
            f"{', '.join(str(n) for n in d.get('team_sizes', range(1, 6)))}; the last run, its cells cached "
            f"or not, took {d['wall_seconds']:.0f} s. "
            "MARL baselines (maddpg, masac, facmac, mambpo, mappo) trained "
            f"for {_marl_budget(d)} with EM-estimated beliefs, executed decentralised as CE-PG.",
            "",
            *_runs_lines(d),
            "The planners (fhpe, fhpe-sa, milp, d-milp) and the oracle get the true target model and see all "
            "robots' observations (centralised); pg, cepg and cepg+ robots use only their own observations "
            "and an estimated model (cepg+ robots sense N[p], a broader field of view than the others' "
            "node); c-cepg robots share all observations (collective belief); oracle robots see the target "
            "(a lower bound, exact DP, N <= 2 only). fhpe is not run for N > 3: the joint paths per decision "
            "exceed 10^6.",
            "",
            _cost_line(root, rows),
            "",
        ]

        def capture(r: dict[str, Any]) -> str:
            half = f" ± {r['ci95_halfwidth']:.1f}" if math.isfinite(r["ci95_halfwidth"]) else ""
            return f"{r['mean_capture_time']:.1f}{half} ({r['episodes']})"

        for env in maps_in(rows):
            lines += [f"### {env.upper()} (mean capture time ± 95% CI half-width, episodes)", ""]
            lines += [*_by_team_size(rows, env, methods, capture), ""]
        lines += [
            f"![fig7]({rel}/fig7/fig7.png)",
            "",
            "### Reading (computed from the table)",
            "",
            (
                "CE-PG's teams here were trained for the budget of each run above (every row states its own), "
                "the paper's 400,000 episodes or less; the MARL baselines likewise"
                if _runs(d)
                else f"CE-PG's teams here were trained for {d['training_episodes']:,} episodes, "
                f"{100 * d['training_episodes'] / 400_000:.1f}% of the paper's budget of 400,000; the MARL "
                f"baselines for {_marl_budget(d)}"
            )
            + (
                ", and the planners ran on one to four episodes: a quick run, not the paper's protocol."
                if d["quick"]
                else "."
            ),
            "",
        ]
        lines += [
            "CE-PG is compared with each method flown on the same episodes (random, greedy, the learned "
            "teams) by the paired difference, method - cepg, and its 95% CI over those episodes; with the "
            "planners, which fly fewer episodes one at a time, by non-overlapping 95% CIs.",
            "",
        ]
        lines += _training_spread(root, d)
        lines += _reading(rows)
        lines += [
            "",
            "## Fig. 8: decision time per team step",
            "",
            "Milliseconds per team step, one episode at a time (batch 1), the simulator's step included "
            "(about 0.1 ms), measured as Fig. 7's cells ran: a planner's over its cell's episodes, the "
            f"others' over extra episodes of about {TIMED_TEAM_STEPS} team steps in all (a row's "
            "timed_team_steps; rows without it were timed on three episodes, a few dozen steps at N = 5). "
            "The paper shows MUSEUM.",
        ]
        for env in maps_in(rows):
            lines += ["", f"{env.upper()}:", ""]
            lines += _by_team_size(rows, env, methods, lambda r: f"{r['decision_ms']:.3g}")
            r4 = {r["method"]: r for r in rows if r["map"] == env and r["robots"] == 4}
            if "cepg" in r4:
                ratios = [
                    f"{m} / cepg = {r4[m]['decision_ms'] / r4['cepg']['decision_ms']:.0f}x"
                    for m in ("fhpe-sa", "milp", "d-milp")
                    if m in r4
                ]
                lines += ["", f"Decision-time ratios at N = 4 on {env.upper()}: {', '.join(ratios)}."]
        lines += [
            "",
            f"HiGHS stops each MILP solve at {d['milp_time_limit_s']} s (d-milp solves once per robot), so "
            "the MILPs' times here are bounded by that limit, not by what an optimal solve would take.",
        ]
        lines += ["", f"![fig8]({rel}/fig8/fig8.png)", ""]
    ct, fa = ("mean_capture_time", "ci95_halfwidth"), ("false_alarms_per_episode", "false_alarms_ci95_halfwidth")
    tables = (  # figure, title, table rows by, columns by, value, a note on the setup
        ("fig5", "Fig. 5: beta of Eq. 9 (N = 4; beta = 1 is PG)", "method", "beta", ct, ""),
        (
            "fig6",
            "Fig. 6: CE-PG vs CE-PG+ vs C-CE-PG",
            "method",
            "robots",
            ct,
            "CE-PG+ robots sense N[p] (their own, broader field of view); C-CE-PG robots share every observation "
            "(collective belief); CE-PG robots sense their node and use their own observations.",
        ),
        (
            "fig9",
            "Fig. 9: eta_fn and CE-PG's capture time (eta_fp = 0)",
            "robots",
            "eta_fn",
            ct,
            "Each team is trained and flown with that sensor.",
        ),
        (
            "fig10",
            "Fig. 10: eta_fp and CE-PG's false alarms per episode (eta_fn = 0)",
            "robots",
            "eta_fp",
            fa,
            "False alarms: the team's total number of z = 1 readings with the target outside D(p), per episode.",
        ),
        (
            "fig11",
            "Fig. 11: all methods under eta_fn (N = 4)",
            "method",
            "eta_fn",
            ct,
            "Planners know eta_fn (their capture probability is (1 - eta_fn) per detection) and see all robots' "
            "observations; fhpe is not run at N = 4; cepg+ senses N[p].",
        ),
        ("fig12", "Fig. 12: one robot withdrawn during execution (N = 4)", "method", "withdrawn", ct, ""),
        ("fig13", "Fig. 13: a team trained for 5 robots, flown by k of them", "method", "robots", ct, ""),
    )
    for fig, title, row_key, key, (value, half), note in tables:
        f = root / fig / f"{fig}.json"
        if not f.exists():
            continue
        d = json.loads(f.read_text())
        rows = d["rows"]
        lines += [
            f"## {title}",
            "",
            f"Setup: {d['episodes']} episodes per cell, seed {d['seed']}; learned teams "
            f"trained for {_trained(d)}; "
            # fig13's methods are "maddpg trained for 5" and the like
            + (f"MARL baselines: {_marl_budget(d)}; " if any(r["method"].split()[0] in MARL for r in rows) else "")
            + f"quick={d['quick']}; {d['machine']['date']}. "
            + (
                f"Planners: {d['planner_episodes']} episodes (fhpe-sa {d['fhpe_sa_episodes']}, d-milp "
                f"{d.get('d_milp_episodes', d['planner_episodes'])}), MILP time limit "
                f"{d['milp_time_limit_s']} s per solve. "
                if "planner_episodes" in d
                else ""
            )
            + note,
            "",
            *_runs_lines(d),
            _cost_line(root, rows),
            "",
        ]
        for env in maps_in(rows):
            sel = [r for r in rows if r["map"] == env]
            groups = list(dict.fromkeys(r[key] for r in sel))
            labels = list(dict.fromkeys(r[row_key] for r in sel))
            head = "N" if row_key == "robots" else row_key
            lines += [
                f"{env.upper()} ({value.replace('_', ' ')} ± 95% CI half-width):",
                "",
                f"| {head} | " + " | ".join(f"{key} {gk}" for gk in groups) + " |",
                "| --- |" + " --- |" * len(groups),
            ]
            for lab in labels:
                cells = []
                for gk in groups:
                    r = next((x for x in sel if x[key] == gk and x[row_key] == lab), None)
                    cells.append("—" if r is None else _fmt(r[value], r[half], r["episodes"]))
                lines.append(f"| {lab} | " + " | ".join(cells) + " |")
            lines.append("")
            if fig == "fig5":
                lines += _beta_reading(sel)
            if fig == "fig6":
                lines += _variants_reading(sel, root)
            if fig in ("fig9", "fig10"):
                lines += _trend_reading(sel, key, value, half)
            if fig == "fig10":
                lines += _unmoved_reading(sel, key)
            if fig == "fig11":
                lines += _ranking_reading(sel)
            if fig == "fig12":
                lines += _withdrawal_reading(sel)
            if fig == "fig13":
                lines += _dropout_reading(sel)
        lines += [f"![{fig}]({rel}/{fig}/{fig}.png)", ""]
    lines += _marl_report(root, rel)
    missing = [e for e in EXPERIMENTS if e != "fig8" and not (root / e).exists()]
    if missing:
        lines += ["## Not recorded", "", ", ".join(missing) + ": run `mures experiment NAME` to record them.", ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, "\n".join(lines))
    return out


def _variants_reading(rows: list[dict[str, Any]], root: Path) -> list[str]:
    """fig6 on one map against the paper's claim that CE-PG+ and C-CE-PG both capture sooner
    than CE-PG: from fig7's paired difference (same episodes) where fig7 flew these very cells
    (the same teams: a recorded fig7 may predate fig6's teams), else from whether the two 95%
    CIs are disjoint."""
    f7 = root / "fig7" / "fig7.json"
    f7_rows = {
        (r["map"], r["robots"], r["method"]): r for r in (json.loads(f7.read_text())["rows"] if f7.exists() else [])
    }
    same = ("mean_capture_time", "ci95_halfwidth", "episodes", "seed", "train_episodes")

    def flown_by_fig7(r: dict[str, Any]) -> dict[str, Any] | None:
        q = f7_rows.get((r["map"], r["robots"], r["method"]))
        return q if q is not None and all(q.get(k) == r.get(k) for k in same) else None

    out = []
    for N in dict.fromkeys(r["robots"] for r in rows):
        base = next((r for r in rows if r["robots"] == N and r["method"] == "cepg"), None)
        if base is None:
            continue
        same_cepg = flown_by_fig7(base) is not None  # fig7's CE-PG row is this one
        said = []
        for m in ("cepg+", "c-cepg"):
            r = next((x for x in rows if x["robots"] == N and x["method"] == m), None)
            if r is None:
                continue
            # fig7's cell, paired with fig7's CE-PG: these teams on these episodes
            q = flown_by_fig7(r) if same_cepg else None
            if q is not None and not _paired(q, base):
                q = None
            gap, sep = _gap(q or r, base)
            if q is not None:
                how = f"fig7's paired difference {gap:+.2f} ± {sep:.2f}"
            else:
                ci = "disjoint" if abs(gap) > sep else "overlap"
                how = f"{r['mean_capture_time']:.2f} against {base['mean_capture_time']:.2f}, 95% CIs {ci}"
            verdict = (
                "captures sooner than"
                if gap < -sep
                else "captures later than"
                if gap > sep
                else "is not separated from"
            )
            said.append(f"{m} {verdict} CE-PG ({how})")
        if said:
            out.append(f"at N = {N}, " + "; ".join(said))
    if out:
        out = ["The paper: CE-PG+ and C-CE-PG both capture sooner than CE-PG. Here, " + "; ".join(out) + ".", ""]
    return out


def _trend_reading(rows: list[dict[str, Any]], key: str, value: str, half: str) -> list[str]:
    """fig9 / fig10 on one map against the paper's claim that the value (capture time, false
    alarms) grows with the sensor's error rate ``key``: per team size, each step up in the rate
    and whether the two cells' 95% CIs are disjoint."""
    what = value.replace("_", " ")
    out = []
    for N in dict.fromkeys(r["robots"] for r in rows):
        sel = sorted((r for r in rows if r["robots"] == N), key=lambda r: r[key])
        steps = []
        for a, b in itertools.pairwise(sel):
            d, h = _gap(b, a, value, half)
            word = "rises" if d > h else "falls" if d < -h else "the 95% CIs overlap"
            steps.append(f"{a[key]} -> {b[key]}: {word} ({a[value]:.2f} to {b[value]:.2f})")
        if steps:
            out.append(f"at N = {N}, " + "; ".join(steps))
    if not out:
        return []
    return [f"The paper: the {what} rises with {key}. Here, " + "; ".join(out) + ".", ""]


def _unmoved_reading(rows: list[dict[str, Any]], key: str) -> list[str]:
    """fig10 on one map against the paper's other claim there: eta_fp (``key``) raises the false
    alarms but not the capture time. Per team size, the capture time at the lowest and the highest
    rate and whether their 95% CIs are disjoint."""
    out = []
    for N in dict.fromkeys(r["robots"] for r in rows):
        sel = sorted((r for r in rows if r["robots"] == N), key=lambda r: r[key])
        if len(sel) < 2:
            continue
        lo, hi = sel[0], sel[-1]
        d, h = _gap(hi, lo)
        word = (
            "it rises (95% CIs disjoint)" if d > h else "it falls (95% CIs disjoint)" if d < -h else "95% CIs overlap"
        )
        out.append(
            f"at N = {N}, {key} {lo[key]} -> {hi[key]}: "
            f"{_fmt(lo['mean_capture_time'], lo['ci95_halfwidth'], lo['episodes'])} to "
            f"{_fmt(hi['mean_capture_time'], hi['ci95_halfwidth'], hi['episodes'])}, {word}"
        )
    if not out:
        return []
    return [f"The paper: {key} does not change the capture time. Here, " + "; ".join(out) + ".", ""]


def _rank(rows: list[dict[str, Any]], key: str, base_method: str, label: str = "", say: str = "") -> list[str]:
    """Per value of ``key``: ``base_method``'s rank by mean capture time among ``rows`` (cells of
    one episode, which have no CI, left out) and the rows that capture sooner, separated from it
    (``_gap``: by the paired difference's 95% CI where the row flew CE-PG's episodes, else by
    disjoint CIs),
    as "SAY V: LABEL ranks R of M (mean ± h); sooner ..." phrases (SAY: ``say`` or the key)."""
    out = []
    for v in dict.fromkeys(r[key] for r in rows):
        sel = [r for r in rows if r[key] == v and r["episodes"] >= 2 and math.isfinite(r["ci95_halfwidth"])]
        base = next((r for r in sel if r["method"] == base_method), None)
        if base is None or len(sel) < 2:
            continue
        ranked = sorted(sel, key=lambda r: r["mean_capture_time"])
        rank = 1 + ranked.index(base)
        sooner = []
        for r in ranked[: rank - 1]:
            gap, sep = _gap(r, base)
            if gap < -sep:
                how = f"paired {gap:+.2f} ± {sep:.2f}" if _paired(r, base) else "CIs disjoint"
                sooner.append(f"{r['method']} {r['mean_capture_time']:.2f} ± {r['ci95_halfwidth']:.2f} ({how})")
        out.append(
            f"{say or key} {v}: {label or base_method} ranks {rank} of {len(ranked)} "
            f"({base['mean_capture_time']:.2f} ± {base['ci95_halfwidth']:.2f}); "
            + (f"sooner, separated: {', '.join(sooner)}" if sooner else "none is sooner and separated")
        )
    return out


def _ranking_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig11 on one map against the paper's claim that CE-PG is among the three best methods at
    every eta_fn (MILP or D-MILP sometimes ahead of it): per eta_fn, CE-PG's rank among the
    methods that sense as it does (CE-PG+ senses N[p] and is left out) and those that capture
    sooner, separated from it (``_rank``)."""
    out = _rank([r for r in rows if r["method"] != "cepg+"], "eta_fn", "cepg")
    if not out:
        return []
    return [
        "The paper: CE-PG is among the three best methods at every eta_fn (MILP or D-MILP sometimes ahead). "
        "Here (cepg+, with its broader sensor, left out): " + "; ".join(out) + ".",
        "",
    ]


def _dropout_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig13 on one map against the paper's claim that CE-PG does best of the MARL methods when
    robots of a 5-robot team drop out: per k flown, the 5-robot teams ranked (CE-PG's rank, and the
    teams that capture sooner, separated from it: ``_rank``). The teams trained for k are the table's
    reference, not part of the ranking."""
    five = [{**r, "method": r["method"].removesuffix(" trained for 5")} for r in rows if r["method"].endswith(" for 5")]
    out = _rank([r for r in five if r["robots"] < 5], "robots", "cepg", "cepg trained for 5", "k =")
    if not out:
        return []
    return [
        "The paper: CE-PG does best of the MARL methods when robots of a 5-robot team drop out. Here, of the "
        "teams trained for 5: " + "; ".join(out) + ".",
        "",
    ]


def _withdrawal_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig12 on one map against the paper's claim that CE-PG does best of the learned methods
    when a robot is withdrawn: the lowest capture time and the runner-up (are their 95% CIs
    disjoint?), and how much each learned method's capture time rises over its intact team's."""
    intact = {r["method"]: r for r in rows if r["withdrawn"] == "none"}
    out = []
    for label in dict.fromkeys(r["withdrawn"] for r in rows if r["withdrawn"] != "none"):
        learned = sorted(
            (r for r in rows if r["withdrawn"] == label and r["method"] not in ("random", "greedy")),
            key=lambda r: r["mean_capture_time"],
        )
        if len(learned) < 2:
            continue
        best, second = learned[:2]
        gap, sep = _gap(second, best)  # rows of one withdrawal: none carries a paired difference
        apart = gap > sep
        rises = ", ".join(
            f"{r['method']} {r['mean_capture_time'] - intact[r['method']]['mean_capture_time']:+.2f}"
            for r in learned
            if r["method"] in intact
        )
        out.append(
            f"With {label} withdrawn, {best['method']} captures soonest of the learned methods "
            f"({best['mean_capture_time']:.2f} ± {best['ci95_halfwidth']:.2f}), then {second['method']} "
            f"({second['mean_capture_time']:.2f} ± {second['ci95_halfwidth']:.2f}; 95% CIs "
            f"{'disjoint' if apart else 'overlap'}). Rise over the intact team: {rises}."
        )
    if not out:
        return []
    return ["The paper: CE-PG does best of the learned methods when a robot is withdrawn. " + " ".join(out), ""]


def _training_spread(root: Path, d: dict[str, Any]) -> list[str]:
    """fig7 flies one team per method and the CI is over episodes; how far a team moves with its
    training run, from fig5's recorded training seeds (beta 0.5 against PG, seed for seed)."""
    f5 = root / "fig5" / "fig5.json"
    if d["quick"] or not f5.exists():
        return []
    spans = []
    for r in json.loads(f5.read_text())["rows"]:
        per = r.get("diff_to_pg_per_seed") or []
        if r.get("beta") == 0.5 and len(per) > 1:
            spans.append(f"{r['map'].upper()} {min(per):+.2f} to {max(per):+.2f} over seeds {r['training_seeds']}")
    if not spans:
        return []
    seeds = sorted({s for r in d["rows"] for s in r.get("training_seeds") or []})
    return [
        f"Each method here is one team (training seed {', '.join(map(str, seeds))}), so a paired CI says "
        "that these teams differ, "
        "not that the methods do: another training run moves a team. In Fig. 5 (N = 4) CE-PG's (beta 0.5) "
        f"paired difference to PG ranges {'; '.join(spans)}; a difference here within that spread "
        "of zero may change sign with another training run.",
        "",
    ]


def _beta_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig5's paired differences to beta = 1 on one map, and what they say."""
    diffs = [r for r in rows if "diff_to_pg" in r]
    if not diffs:
        return []
    seeds = diffs[0].get("training_seeds", [0])
    out = [
        f"Paired difference to beta = 1 (PG) of the same training seed (negative: CE-PG captures sooner), "
        f"training seeds {seeds}, each team on the same {diffs[0]['episodes']} episodes; 95% CI over the "
        "pooled episodes, and over the training seeds (Student t):",
        "",
        "| beta | difference | CI (episodes) | CI (seeds) | per seed |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in diffs:
        out.append(
            f"| {r['beta']} | {r['diff_to_pg']:+.2f} | ± {r['diff_to_pg_ci95_episodes']:.2f} | "
            f"± {r['diff_to_pg_ci95_seeds']:.2f} | {', '.join(f'{x:+.2f}' for x in r['diff_to_pg_per_seed'])} |"
        )
    sig = [r["beta"] for r in diffs if r["diff_to_pg"] + r["diff_to_pg_ci95_seeds"] < 0]
    worse = [r["beta"] for r in diffs if r["diff_to_pg"] - r["diff_to_pg_ci95_seeds"] > 0]
    if len(seeds) > 1:
        out += [
            "",
            "Across training seeds (a difference counts when its 95% CI over the seeds excludes 0): "
            + (f"beta in {sig} captures sooner than PG" if sig else "no beta < 1 captures sooner than PG")
            + (f"; beta in {worse} captures later" if worse else "")
            + ".",
        ]
    # the pooled-episode CI holds the teams fixed: it says these teams differ, not that training
    # with that beta does; reported too, so that a reader sees both
    ep_sooner = [r["beta"] for r in diffs if r["diff_to_pg"] + r["diff_to_pg_ci95_episodes"] < 0]
    ep_later = [r["beta"] for r in diffs if r["diff_to_pg"] - r["diff_to_pg_ci95_episodes"] > 0]
    if ep_sooner or ep_later:
        out += [
            "",
            "Over the pooled episodes (these teams, not the training's variation): "
            + "; ".join(
                x
                for x in (
                    f"beta in {ep_sooner} captures sooner than PG" if ep_sooner else "",
                    f"beta in {ep_later} captures later" if ep_later else "",
                )
                if x
            )
            + (
                f". With {len(seeds)} training seeds per beta that is not separated from the seed-to-seed spread."
                if len(seeds) > 1 and not (set(ep_sooner) & set(sig) or set(ep_later) & set(worse))
                else "."
            ),
        ]
    return [*out, ""]


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


def _runs(setup: dict[str, Any]) -> list[dict[str, Any]]:
    """The runs a figure's rows come from, when more than one (`--add`; ``_merge``), else []."""
    parts = setup.get("parts") or []
    return parts if len(parts) > 1 else []


def _cost_line(root: Path, rows: list[dict[str, Any]]) -> str:
    """What a figure cost on the machines that made it: its cells' evaluation and the training of the
    teams its rows name (each team once, from its snapshot's wall time in ``root``'s cache)."""
    said = f"evaluating the cells of its {len(rows)} rows {_duration(sum(r.get('wall_seconds', 0.0) for r in rows))}"
    teams = {t for r in rows for t in (r.get("teams") or [r.get("team")]) if t}
    snaps = [root / "snapshots" / t for t in sorted(teams)]
    walls = [float(_summary(d).get("wall_seconds", 0.0)) for d in snaps if (d / "policy.json").exists()]
    if teams:
        cached = "" if len(walls) == len(teams) else f" ({len(walls)} of them in the cache)"
        said += f"; training the {len(teams)} teams its rows name{cached} {_duration(sum(walls))}"
    unnamed = sum(1 for r in rows if r.get("train_episodes") is not None and not ({"team", "teams"} & r.keys()))
    if unnamed:
        said += f"; {unnamed} learned rows were recorded before rows named their team, their training not counted"
    return f"Cost (wall time, one core a job, often beside another job): {said}."


def _duration(seconds: float) -> str:
    """A duration as a reader takes it in: seconds, minutes or hours."""
    if seconds >= 360:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.0f} min" if seconds >= 60 else f"{seconds:.0f} s"


def _trained(setup: dict[str, Any]) -> str:
    """The learned teams' training budget as a setup states it."""
    return "the budget of each run below" if _runs(setup) else f"{setup['training_episodes']:,} episodes"


def _runs_lines(setup: dict[str, Any]) -> list[str]:
    """A figure recorded in several runs: what each covers and at which budgets."""
    runs = _runs(setup)
    if not runs:
        return []
    said = []
    for p in runs:
        where = _pairs(p["covers"])
        planners = (
            f", planners {p['planner_episodes']} (fhpe-sa {p['fhpe_sa_episodes']}, d-milp "
            f"{p.get('d_milp_episodes', p['planner_episodes'])})"
            if "planner_episodes" in p
            else ""
        )
        said.append(
            f"{where}: learned teams trained for {p['training_episodes']:,} episodes, MARL baselines "
            f"{_marl_budget(p)}; {p['episodes']} episodes per cell{planners}; quick={p['quick']}; "
            f"{p['machine']['date']}"
        )
    return [
        f"Recorded in {len(runs)} runs (`--add`), each row with its own training budget (train_episodes in the "
        "data): " + "; and ".join(said) + ".",
        "",
    ]


def _marl_budget(setup: dict[str, Any]) -> str:
    """The MARL baselines' training budget as a setup states it (older results have none)."""
    if _runs(setup):
        return "the budget of each run below"
    given = setup.get("marl_training_episodes")
    if given is None:
        return "(not recorded)"
    by = setup.get("marl_training_episodes_by_method") or {}
    if isinstance(given, int):
        said = f"{given:,} episodes"
    elif given == MARL_OWN:
        said = "each method's own budget"
    elif by:
        said = "each method's default budget"
    else:  # files from before the setup listed the defaults: they were other budgets then
        said = "each method's default budget when recorded (each row's training episodes)"
    return said + (" (" + ", ".join(f"{m.upper()} {e:,}" for m, e in by.items()) + ")" if by else "")


def _marl_report(root: Path, rel: str) -> list[str]:
    """The MARL baselines' section: budgets, capture times against random and CE-PG, the sweep."""
    f = root / "marl" / "marl.json"
    if not f.exists():
        return []
    d = json.loads(f.read_text())
    rows, lines = d["rows"], []
    budget = _marl_budget(d)
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
                f"| {env.upper()} | {r['method']} | {_fmt(r['mean_capture_time'], r['ci95_halfwidth'], r['episodes'])} "
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
            f"| {_fmt(r['mean_capture_time'], r['ci95_halfwidth'], r['episodes'])} |"
        )
    return [*lines, "", *_plateau_report(root)]


def _by_team_size(
    rows: list[dict[str, Any]], env: str, methods: list[str], cell: Callable[[dict[str, Any]], str]
) -> list[str]:
    """A markdown table of one map's rows: a line per method, a column per team size N, ``cell(row)``
    in each (— where the method has no row at that N)."""
    Ns = sorted({r["robots"] for r in rows if r["map"] == env})
    out = ["| method | " + " | ".join(f"N={n}" for n in Ns) + " |", "| --- |" + " --- |" * len(Ns)]
    for m in methods:
        at: dict[int, dict[str, Any]] = {}
        for r in rows:
            if r["map"] == env and r["method"] == m:
                at.setdefault(r["robots"], r)  # the first row of a size, as the figure's own order
        out.append(f"| {m} | " + " | ".join(cell(at[n]) if n in at else "—" for n in Ns) + " |")
    return out


def _plateau_report(root: Path) -> list[str]:
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
        f"{ref['train_episodes']:,} episodes ({_fmt(ref['mean_capture_time'], ref['ci95_halfwidth'], d['episodes'])}); "
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
            f"| {_fmt(r['mean_capture_time'], r['ci95_halfwidth'], d['episodes'])} | {paired} | {shorter} "
            f"| {said(r.get('curve_at_half'))} -> {said(r.get('curve_at_end'))} |"
        )
    return [*lines, ""]


def _fmt(mean: float, half: float, episodes: int) -> str:
    """mean ± CI half-width; a cell of fewer than 2 episodes has no CI and says how many it had."""
    if episodes < 2 or not math.isfinite(half):
        return f"{mean:.2f} ({episodes} ep.)"
    return f"{mean:.2f} ± {half:.2f}"


def _gap(
    r: dict[str, Any], base: dict[str, Any], value: str = "mean_capture_time", half: str = "ci95_halfwidth"
) -> tuple[float, float]:
    """(r - base, the margin it must exceed to count): CE-PG's paired difference and its CI
    half-width when ``r`` carries one (it flew CE-PG's episodes, and ``base`` is CE-PG's row), else
    the difference of the two values and the sum of their CI half-widths (the CIs must not overlap)."""
    if _paired(r, base, value):
        return r["diff_to_cepg"], r["diff_to_cepg_ci95"]
    return r[value] - base[value], r[half] + base[half]


def _paired(r: dict[str, Any], base: dict[str, Any], value: str = "mean_capture_time") -> bool:
    """Whether ``_gap`` compares ``r`` with ``base`` by CE-PG's paired difference."""
    return "diff_to_cepg" in r and base.get("method") == "cepg" and value == "mean_capture_time"


def _reading(rows: list[dict[str, Any]]) -> list[str]:
    out = []
    for env in maps_in(rows):
        for n in sorted({r["robots"] for r in rows if r["map"] == env}):
            cell = {r["method"]: r for r in rows if r["map"] == env and r["robots"] == n}
            if "cepg" not in cell:
                continue
            c = cell["cepg"]
            better: list[str] = []
            worse: list[str] = []
            tied: list[str] = []
            few: list[str] = []
            same: list[str] = []
            for m, r in cell.items():
                if m in ("cepg", "oracle"):
                    continue
                if r["episodes"] < 2 or not math.isfinite(r["ci95_halfwidth"]):
                    few.append(f"{m} {r['mean_capture_time']:.1f}")
                    continue
                if r.get("diff_to_cepg") == 0 and r.get("diff_to_cepg_ci95") == 0:
                    same.append(m)  # every paired difference 0: C-CE-PG at N = 1 is CE-PG
                    continue
                gap, sep = _gap(r, c)
                text = f"{m} {r['mean_capture_time']:.1f}" + (
                    f" (paired {gap:+.2f} ± {sep:.2f})" if "diff_to_cepg" in r else ""
                )
                (better if gap > sep else worse if gap < -sep else tied).append(text)
            line = f"- {env.upper()} N={n}: cepg {c['mean_capture_time']:.1f}"
            if better:
                line += f"; sooner than {', '.join(better)}"
            if worse:
                line += f"; later than {', '.join(worse)}"
            if tied:
                line += f"; not separated from {', '.join(tied)}"
            if same:
                line += f"; the same capture time as CE-PG in every episode: {', '.join(same)}"
            if few:
                line += f"; one episode only, not compared: {', '.join(few)}"
            if "oracle" in cell:
                line += f"; oracle bound {cell['oracle']['mean_capture_time']:.1f}"
            out.append(line + ".")
    return out

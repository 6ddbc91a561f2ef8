"""`mures train`: a team trained in simulation, CE-PG (Algorithm 2) or a MARL baseline, written
as a policy snapshot; Ctrl-C stops after the current update and still writes it."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from shared.core.choices import TEAM_SEARCHERS
from shared.learning import config as train_config
from shared.learning.config import CHECKPOINT_EVERY_S, positive_int, seconds
from shared.learning.team_snapshot import load_snapshot, save_snapshot
from shared.tools.cli_args import CliError, add_world_args, device_of, world_of
from shared.tools.map_commands import large_graph_warning


class _Progress:
    """A one-line progress bar on a terminal; a line every 10% otherwise (logs)."""

    def __init__(self, stream: Any = sys.stderr) -> None:
        self.stream = stream
        self.tty = stream.isatty()
        self.next_pct = 10

    def __call__(self, p: dict[str, Any]) -> None:
        frac = min(1.0, p["episodes"] / p["total"])
        rate = p["episodes_per_second"]
        eta = (p["total"] - p["episodes"]) / max(rate, 1e-9)
        text = (
            f"{p['episodes']:>9,}/{p['total']:,} episodes  {rate:7.0f} eps/s  "
            f"capture time {p['mean_capture_time']:6.2f}{' ticks' if p.get('time_unit') == 'ticks' else ''}  "
            + (f"CE {p['cross_entropy']:.2f}  " if "cross_entropy" in p else "")
            + f"ETA {max(eta, 0):4.0f} s"
        )
        if self.tty:
            bar = "#" * int(24 * frac)
            self.stream.write(f"\r[{bar:<24}] {text}")
            self.stream.flush()
        elif frac * 100 >= self.next_pct or frac >= 1.0:
            self.next_pct = int(frac * 10) * 10 + 10
            print(text, file=self.stream, flush=True)

    def close(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


def _init_distributed(device: torch.device) -> int:
    """Join the torchrun process group when launched by torchrun; returns this process's rank."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return 0
    import torch.distributed as dist

    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    dist.init_process_group(backend=backend)
    return dist.get_rank()


def cmd_train(args: argparse.Namespace) -> int:
    from shared.learning.train import leave_process_group

    detection = "neighbourhood" if args.variant == "cepg+" else None  # None: the map's default
    if args.variant == "cepg+" and args.detection == "node":
        raise CliError("cepg+ trains with a sensing range: use --detection neighbourhood or custom, or leave it out")
    graph, target, sensor = world_of(args, detection)
    warning = None if _general_init(args) else large_graph_warning(graph.n)  # it is about per-map teams
    if warning:
        print(f"mures train: {graph.name}: {warning}", file=sys.stderr, flush=True)
    device = device_of(args.device)
    out = Path(args.out)
    if out.exists() and not (out / "policy.json").is_file():
        raise CliError(f"--out {out} exists and is not a policy snapshot; refusing to replace it")
    init_model = None
    if args.model:
        from shared.core.models import load_model_file

        init_model = load_model_file(graph, args.model)
    elif _general_init(args):  # its beliefs start on the model it was trained with, not Gamma_hat_0 = I
        from shared.core.models import uniform_walk

        init_model = uniform_walk(graph)
    init_policy = _init_policy(args, graph, target, sensor) if args.init else None
    cfg, hyper = _checked_config(args, device, graph.n)
    clock_text = _clock_text(graph, cfg)
    torch.set_num_threads(args.threads)
    if hyper is not None and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise CliError(f"{cfg.algorithm} runs in one process; torchrun data parallelism is CE-PG's")
    rank = _init_distributed(device)
    if rank == 0:
        model_text = "true model" if cfg.belief == "true" else "EM-estimated model"
        what = (
            f"{cfg.algorithm} on {graph.name} (n={graph.n}), N={args.robots}, {hyper.episodes:,} episodes, "
            f"{model_text}{clock_text}; hyperparameters {hyper.to_dict()}"
            if hyper is not None
            else f"{args.variant} on {graph.name} (n={graph.n}), N={args.robots}, beta={cfg.beta}, lr={cfg.lr}, "
            f"{cfg.episodes:,} episodes, {model_text}{clock_text}"
        )
        print(f"training {what}", file=sys.stderr)
    res = _fit(args, cfg, hyper, (graph, target, sensor), init_model, init_policy, rank == 0 and not args.quiet)
    if rank == 0:
        _write_snapshot(args, out, cfg, hyper, graph, target, sensor, res)
    code = 130 if res.interrupted else 0
    leave_process_group(code)  # under torchrun: ends this process with ``code``
    return code


def _general_init(args: argparse.Namespace) -> bool:
    """--init names the general policy (``general`` or ``general:DIR``)."""
    return bool(args.init) and (args.init == "general" or args.init.startswith("general:"))


def _init_policy(args: argparse.Namespace, graph: Any, target: Any, sensor: Any) -> Any:
    """--init's snapshot, or the general policy (``general``: the shipped one, ``general:DIR``)
    bound to this map and --robots, to fine-tune."""
    if _general_init(args):
        from shared.core.snapshot_format import load_general, shipped_general_path
        from shared.learning.team_snapshot import general_snapshot

        if args.algorithm != "cepg":
            raise CliError(f"--init {args.init}: the general policy fine-tunes with cepg, not {args.algorithm}")
        where = shipped_general_path() if args.init == "general" else args.init.removeprefix("general:")
        return general_snapshot(load_general(where), graph, args.robots, target, sensor)
    return load_snapshot(args.init, graph)


def _clock_text(graph: Any, cfg: Any) -> str:
    """With --speed, what the run's travel times are (for its first line); a CliError for a graph
    without edge lengths or --tick without --speed."""
    from shared.learning.train import clock_of

    if cfg.speed is None:
        if cfg.tick != train_config.default("tick"):
            raise CliError("--tick sets the clock of --speed's travel times: give --speed too")
        return ""
    try:
        clock = clock_of(graph, cfg)
    except ValueError as exc:
        raise CliError(f"--speed: {exc}") from None
    assert clock is not None
    moves = clock.ticks[graph.edges[:, 0], graph.edges[:, 1]]
    return (
        f"; on the clock at {cfg.speed:g} m/s: moves of {int(moves.min())}-{int(moves.max())} ticks of "
        f"{cfg.tick:g} s (a step of the model {clock.ticks_per_step:.1f} ticks), capture times in ticks"
    )


def _checked_config(args: argparse.Namespace, device: Any, graph_n: int) -> tuple[Any, Any]:
    """The run's TrainConfig and, for a MARL baseline, its hyperparameters (None for CE-PG), with
    every flag checked against the algorithm before anything trains."""
    cfg = train_config.from_flags(args, robots=args.robots, seed=args.seed, device=str(device))
    if _general_init(args):  # a fine-tune of the general policy: its own defaults for what is not given
        tuned = train_config.fine_tune_defaults(graph_n)
        cfg = replace(cfg, **{k: v for k, v in tuned.items() if getattr(args, k) is None})
    marl = cfg.algorithm != "cepg"
    if not _general_init(args) and cfg.node_bias != train_config.default("node_bias"):
        raise CliError("--node-bias is for a fine-tune of the general policy (--init general)")
    try:
        cfg.check()
        cfg.per_robot(cfg.beta, "--beta")
        cfg.per_robot(cfg.lr, "--lr")
        if args.hp and not marl:
            raise ValueError("--hp sets a MARL baseline's hyperparameters; CE-PG takes its own flags")
        if marl and args.init:
            raise ValueError(f"--init warm-starts CE-PG only; {cfg.algorithm} trains from scratch")
        if args.checkpoint and not marl:
            raise ValueError("--checkpoint makes a MARL baseline's run resumable; CE-PG runs are not checkpointed")
        if not marl:
            return cfg, None
        from shared.learning.marl import hyperparameters

        lr = None if args.lr is None else cfg.lr[0]
        return cfg, hyperparameters(cfg.algorithm, args.hp, episodes=args.episodes, envs=args.batch, lr=lr)
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _fit(
    args: argparse.Namespace,
    cfg: Any,
    hyper: Any,
    world: tuple[Any, Any, Any],
    init_model: Any,
    init_policy: Any,
    progress: bool,
) -> Any:
    """Train in ``world`` (graph, target, sensor; ``hyper``: a MARL baseline, else CE-PG) until
    done or a first Ctrl-C; a second Ctrl-C aborts without a snapshot."""
    from shared.learning.train import train

    graph, target, sensor = world
    stop = {"requested": False}

    def on_sigint(_sig: int, _frame: Any) -> None:
        if stop["requested"]:
            raise KeyboardInterrupt
        stop["requested"] = True
        print("\nmures: stopping after the current update (Ctrl-C again to abort without a snapshot)", file=sys.stderr)

    old_handler = signal.signal(signal.SIGINT, on_sigint)
    bar = _Progress() if progress else None
    try:
        if hyper is None:
            return train(
                graph,
                target,
                sensor,
                cfg,
                init_model=init_model,
                init_policy=init_policy,
                progress=bar,
                should_stop=lambda: stop["requested"],
            )
        from shared.learning.marl import train_marl

        try:
            return train_marl(
                cfg.algorithm,
                graph,
                target,
                sensor,
                cfg,
                hyper,
                init_model=init_model,
                progress=bar,
                should_stop=lambda: stop["requested"],
                checkpoint=args.checkpoint,
                checkpoint_every=args.checkpoint_every,
            )
        except ValueError as exc:  # a checkpoint directory of another run, or not one at all
            if not args.checkpoint:
                raise
            raise CliError(str(exc)) from None
    finally:
        signal.signal(signal.SIGINT, old_handler)
        if bar:
            bar.close()


def _write_snapshot(
    args: argparse.Namespace, out: Path, cfg: Any, hyper: Any, graph: Any, target: Any, sensor: Any, res: Any
) -> None:
    """Save the trained team at ``out`` with its training configuration, and say what was done."""
    config = {**cfg.to_dict(), "target": target.kind, "map": graph.name}
    if hyper is not None:
        config.update(episodes=hyper.episodes, batch=hyper.envs, lr=[hyper.lr], hyperparameters=hyper.to_dict())
    save_snapshot(
        out,
        res.policy,
        graph,
        res.model,
        sensor,
        args.variant,
        [] if hyper is not None else cfg.per_robot(cfg.beta, "beta"),
        config,
        res.summary,
        algorithm=cfg.algorithm,
        team_searcher=args.team_searcher,
    )
    s = res.summary
    resumed = f" (resumed at {s['resumed'][-1]['episodes']:,})" if s.get("resumed") else ""
    clock = s.get("clock")
    # CE-PG's rollout steps only the ticks where some robot decides; a MARL environment every tick
    unit = "steps" if not clock else ("ticks" if hyper is not None else "ticks when some robot decided")
    last = f"{s['final_mean_capture_time']:.2f}"
    if clock:
        last += f" ticks ({s['final_mean_capture_time'] * clock['tick_s']:.1f} s)"
    print(
        f"{'interrupted: ' if res.interrupted else ''}{s['episodes']:,} episodes{resumed} ({s['env_steps']:,} team "
        f"{unit}) in {s['wall_seconds']:.1f} s, {s['episodes_per_second']:.0f} episodes/s; "
        f"last capture time {last}; wrote {out}"
    )
    if args.checkpoint and res.interrupted:
        print(f"checkpoint in {args.checkpoint}: the same command continues the run from it")
    elif args.checkpoint:
        from shared.learning.marl import remove_checkpoint

        remove_checkpoint(args.checkpoint)


def add_train_command(sub: Any) -> None:
    """`mures train` and its parser."""
    p = sub.add_parser(
        "train", help="train a team in simulation (CE-PG or a MARL baseline) and write a policy snapshot"
    )
    add_world_args(p)
    p.add_argument("--out", required=True, metavar="DIR", help="snapshot directory to write")
    train_config.add_flags(p)  # one flag per TrainConfig field, its defaults
    p.add_argument("--true-model", dest="belief", action="store_const", const="true", help="the same as --belief true")
    p.add_argument(
        "--team-searcher",
        choices=(*TEAM_SEARCHERS, "none"),
        help="what the snapshot's robots fly together when their links allow (default: c-cepg for a c-cepg team, "
        "else none; the training server decides for its own versions)",
    )
    p.add_argument(
        "--model",
        metavar="model.json",
        help="Gamma_hat_0 and b0 for the beliefs (default I, uniform; the uniform walk for --init general)",
    )
    p.add_argument(
        "--init",
        metavar="DIR",
        help="start from this snapshot's weights (CE-PG); `general` fine-tunes the shipped general policy on this "
        "map (`general:DIR` another one), its snapshot flown by any number of robots; the flags a fine-tune takes "
        "its own defaults for say so (docs/general-policy.md)",
    )
    p.add_argument(
        "--hp",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a MARL baseline's hyperparameter (repeatable; docs/SPEC.md section 11 lists them)",
    )
    p.add_argument(
        "--threads",
        type=positive_int,
        default=train_config.TORCH_THREADS,
        help=f"torch CPU threads (default {train_config.TORCH_THREADS}: a team's tensors are small, more threads "
        "gain little and lose much on a shared machine; torchrun or `mures experiment --workers` use the other cores)",
    )
    p.add_argument(
        "--checkpoint",
        metavar="DIR",
        help="a MARL baseline's run saves its whole state in DIR as it goes and when stopped, and the same command "
        "continues from it after a kill or Ctrl-C, ending as an uninterrupted run would; DIR is removed when done",
    )
    p.add_argument(
        "--checkpoint-every",
        type=seconds,
        default=CHECKPOINT_EVERY_S,
        metavar="SECONDS",
        help=f"seconds of training between checkpoints (default {CHECKPOINT_EVERY_S:.0f})",
    )
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_train)

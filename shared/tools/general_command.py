"""`mures train-general`: the general policy trained with CE-PG on many generated buildings
(shared/learning/general.py), written as a general policy directory; progress on stderr, a
checkpoint in the output directory that the same command goes on from after a kill or Ctrl-C.
With --dask-scheduler (or --workers K, a local cluster) the rollouts run on Dask workers, with the
same numbers as in one process."""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
import tempfile
from dataclasses import fields
from pathlib import Path
from typing import Any

import torch

from shared.learning.config import positive_int, whole_number
from shared.tools.cli_args import CliError, device_of


def cmd_train_general(args: argparse.Namespace) -> int:
    from shared.learning.general import GeneralConfig, train_general

    cfg = GeneralConfig(**{f.name: getattr(args, f.name) for f in fields(GeneralConfig)})
    try:
        cfg.check()
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if args.workers and args.dask_scheduler:
        raise CliError("train-general: --workers starts a local cluster; give it or --dask-scheduler, not both")
    device = device_of(args.device)
    if device.type != "cpu" and (args.workers or args.dask_scheduler):
        raise CliError(f"train-general: --device {args.device} goes without --workers and --dask-scheduler "
                       "(rollouts on Dask workers run on their CPUs)")  # fmt: skip
    if (args.workers or args.dask_scheduler) and cfg.floors_per_update == 1:
        print(
            "note: with --floors-per-update 1 each update flies one floor, so one worker at a time is busy "
            "after the imitation phase",
            file=sys.stderr,
        )
    torch.set_num_threads(args.threads)
    print(
        f"training the general policy: {cfg.episodes:,} episodes on {cfg.pool} generated floors of "
        f"{cfg.min_nodes}-{cfg.max_nodes} nodes, teams of 1-{cfg.max_robots}, into {args.out}"
        + ("" if device.type == "cpu" else f", on {device}"),
        file=sys.stderr,
        flush=True,
    )

    def progress(p: dict[str, Any]) -> None:
        rate = p["episodes"] / max(p["wall_seconds"], 1e-9)
        eta = (p["total"] - p["episodes"]) / max(rate, 1e-9)
        print(
            f"{p['episodes']:>9,}/{p['total']:,} episodes  {rate:5.0f} eps/s  capture time / n "
            f"{p['capture_time_per_node']:.3f}  ETA {max(eta, 0):5.0f} s",
            file=sys.stderr,
            flush=True,
        )

    command = "mures " + shlex.join(sys.argv[1:])
    with contextlib.ExitStack() as stack:
        scheduler = args.dask_scheduler
        if args.workers:
            from shared.tools.runner import local_dask_cluster

            work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="mures-train-general-")))
            project = Path(__file__).resolve().parents[2]  # the checkout the workers import from
            scheduler = stack.enter_context(local_dask_cluster(args.workers, work, project))
        try:
            summary = train_general(
                cfg,
                args.out,
                None if args.quiet else progress,
                command=command,
                say=(lambda _t: None) if args.quiet else (lambda t: print(t, file=sys.stderr, flush=True)),
                scheduler=scheduler,
                device=device,
            )
        except ValueError as exc:
            raise CliError(str(exc)) from None
    print(f"wrote {args.out} ({summary['episodes']:,} episodes, {summary['wall_seconds']:.0f} s)", file=sys.stderr)
    return 0


def add_general_command(sub: Any) -> None:
    """`mures train-general` and its parser: one flag per GeneralConfig field."""
    from shared.learning.general import GeneralConfig

    p = sub.add_parser(
        "train-general",
        help="train the general policy (any building, any team size) on generated floors",
        description=__doc__,
    )
    p.add_argument("--out", required=True, metavar="DIR", help="general policy directory to write (and checkpoint in)")
    helps = {
        "episodes": "training episodes in all",
        "min_nodes": "smallest generated floor",
        "max_nodes": "largest generated floor",
        "max_robots": "teams of 1 to this many robots",
        "pool": "generated floors in the training pool",
        "batch_elements": "episodes per update: this over the floor's n (16 to 256)",
        "lr": "Adam's learning rate",
        "lr_final": "the learning rate decays linearly to this share of --lr",
        "beta": "Eq. 9's weight of J against the cross-entropy term",
        "eps": "smoothing of pi_i inside the cross entropy",
        "hidden": "hidden units of each of the network's two layers",
        "imitation_episodes": "episodes FHPE-SA flies on each pool building for the imitation phase (0: none)",
        "imitation_epochs": "epochs of fitting the network to FHPE-SA's moves",
        "seed": "random seed",
        "checkpoint_every": "seconds between checkpoints",
        "init": "a general policy directory to go on from (its weights, no imitation phase)",
        "floors_per_update": "pool floors flown per update, their gradients averaged (side by side on Dask workers)",
    }
    for f in fields(GeneralConfig):
        counts = ("seed", "imitation_episodes", "imitation_epochs")  # may be 0
        kind: Any = (whole_number if f.name in counts else positive_int) if f.type in ("int", int) else float
        if f.name == "init":
            kind = str
        p.add_argument(
            "--" + f.name.replace("_", "-"), dest=f.name, type=kind, default=f.default,
            help=f"{helps[f.name]} (default {f.default})",
        )  # fmt: skip
    p.add_argument("--threads", type=positive_int, default=1, help="torch CPU threads (default 1; workers use as many)")
    p.add_argument(
        "--dask-scheduler",
        metavar="ADDRESS",
        help="fly the imitation phase's planner and each update's rollouts on this Dask cluster (the cluster extra)",
    )
    p.add_argument(
        "--workers",
        type=whole_number,
        default=0,
        metavar="K",
        help="start a local Dask cluster of K one-thread workers for them (default 0: this process)",
    )
    p.add_argument(
        "--device",
        default="cpu",
        help="torch device of the rollouts and the network (default cpu; cuda: a GPU, without --workers; the "
        "imitation phase's planner stays on the CPU, and a run's numbers are reproducible on the device it ran on)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_train_general)

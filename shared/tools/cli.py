"""The `mures` command line (docs/SPEC.md section 7).

    mures evaluate  (--env office|museum | --graph FILE) --robots N --searcher NAME ...
    mures simulate  (--env | --graph) --robots N --missions M --out FILE.jsonl ...
    mures estimate  (--env | --graph) --episodes FILE.jsonl --out model.json ...
    mures train     (--env | --graph) --robots N --out DIR [--beta 0.5] [--episodes 400000] ...
    mures map       (--env | --graph)

Bad arguments and bad input files end with one line ``mures: error: ...`` and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shared.core.choices import ESTIMATORS
from shared.core.files import atomic_write
from shared.core.graph import Graph, GraphError
from shared.core.models import ModelError, Sensor, TargetModel, parse_target
from shared.core.records import read_jsonl
from shared.core.snapshot import SnapshotError
from shared.engine.estimate import EMWorkerError, collect_missions, em, eq8, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate
from shared.engine.searchers import Searcher
from shared.learning import config as train_config
from shared.learning.config import CHECKPOINT_EVERY_S, positive_int, seconds
from shared.learning.snapshot import load_snapshot, save_snapshot
from shared.registry import searcher_factory
from shared.tools.cli_args import (
    CliError,
    add_map_args,
    add_world_args,
    graph_of,
    world_of,
)
from shared.tools.experiment_commands import add_experiment_commands
from shared.tools.fleet_commands import add_fleet_commands


def _device(name: str) -> torch.device:
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise CliError(f"unknown device {name!r} (expected cpu or cuda)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CliError("--device cuda asked for, but no CUDA device is available")
    return dev


# ---------------------------------------------------------------------- evaluate
def _searcher_factory(
    args: argparse.Namespace, graph: Graph, target: TargetModel, sensor: Sensor, device: torch.device
) -> Callable[[int], Searcher]:
    """seed -> searcher for evaluate(); checks the name (and loads a snapshot) once, before any simulation."""
    try:
        return searcher_factory(
            args.searcher,
            graph,
            target,
            sensor,
            args.robots,
            device,
            note=lambda text: print(f"mures: note: {text}", file=sys.stderr),
        )
    except SnapshotError:
        raise
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _snapshot_detection(args: argparse.Namespace) -> str:
    """A policy is evaluated with the detection it was trained for unless --detection says otherwise."""
    if args.searcher.startswith("policy:") and args.detection is None:
        meta = Path(args.searcher.removeprefix("policy:")) / "policy.json"
        try:
            return str(json.loads(meta.read_text(encoding="utf-8"))["sensor"]["detection"])
        except (OSError, ValueError, KeyError, TypeError):
            return "node"  # load_snapshot reports the problem
    return "node"


def cmd_evaluate(args: argparse.Namespace) -> int:
    graph, target, sensor = world_of(args, _snapshot_detection(args))
    device = _device(args.device)
    factory = _searcher_factory(args, graph, target, sensor, device)
    res = evaluate(graph, target, sensor, args.robots, factory, episodes=args.episodes, seed=args.seed, device=device)
    summary: dict[str, Any] = {
        "map": graph.name,
        "graph_id": graph.graph_id,
        "robots": args.robots,
        "searcher": args.searcher,
        "target": target.kind,
        "sensor": sensor.to_json(),
        **res.summary(),
        "wall_seconds": round(res.wall_seconds, 3),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        lo, hi = summary["ci95"]
        print(
            f"{graph.name}, N={args.robots}, searcher={args.searcher}, "
            f"{summary['episodes']} episodes, seed {args.seed}\n"
            f"  mean_capture_time         {summary['mean_capture_time']:.2f}  (95% CI {lo:.2f} .. {hi:.2f})\n"
            f"  median                    {summary['median']:.1f}\n"
            f"  censored_fraction         {summary['censored_fraction']:.4f}  (T_max = {3 * graph.n})\n"
            f"  false_alarms_per_episode  {summary['false_alarms_per_episode']:.3f}\n"
            f"  wall_seconds              {summary['wall_seconds']:.2f}"
        )
    return 0


# ---------------------------------------------------------------------- simulate
def cmd_simulate(args: argparse.Namespace) -> int:
    graph, target, sensor = world_of(args)
    device = _device(args.device)
    factory = _searcher_factory(args, graph, target, sensor, device)
    res = evaluate(
        graph, target, sensor, args.robots, factory, episodes=args.missions, seed=args.seed, device=device, record=True
    )
    out = Path(args.out)
    lines = [
        json.dumps(rec, separators=(",", ":")) + "\n"
        for rec in episode_records(graph, res, sensor, fleet=args.fleet, mission_prefix=f"sim-{args.seed}")
    ]
    atomic_write(out, "".join(lines))
    written = len(lines)
    if args.truth:
        atomic_write(args.truth, json.dumps({**target.to_json(graph), "kind": target.kind}) + "\n")
    s = res.summary()
    print(
        f"wrote {written} records of {args.missions} missions to {out} "
        f"(mean capture time {s['mean_capture_time']:.2f}, censored {s['censored_fraction']:.3f})"
    )
    return 0


# ---------------------------------------------------------------------- estimate
def cmd_estimate(args: argparse.Namespace) -> int:
    # EM on 1000 WARD missions (benchmarks/bench_estimate.py): 13.7-14.4 s in one process, 8.7-8.9 s
    # shared by two on this 2-core machine, quiet; torch's own threads gained little (18.5 s on two:
    # each small operation waits for the other thread at its end), and lost much under load
    torch.set_num_threads(1)
    graph = graph_of(args)
    if not Path(args.episodes).is_file():
        raise CliError(f"episode file {args.episodes!r} does not exist")
    t0 = time.perf_counter()
    data = collect_missions(read_jsonl(args.episodes), graph, capture_aware=args.method == "em")
    skipped = sum(data.skipped.values())
    reasons = ", ".join(f"{k}: {v}" for k, v in sorted(data.skipped.items())) or "none"
    print(
        f"read {data.used_records} records in {len(data.length)} missions; skipped {skipped} ({reasons})",
        file=sys.stderr,
    )
    if data.impossible:
        shown = ", ".join(data.impossible[:10]) + (
            f" and {len(data.impossible) - 10} more" if len(data.impossible) > 10 else ""
        )
        print(
            f"set aside {len(data.impossible)} missions that no path of the target explains "
            f"under their sensor: {shown}",
            file=sys.stderr,
        )
    if len(data.length) == 0:
        raise CliError("no usable episode records: nothing estimated, nothing written")
    last = [0.0]

    def progress(it: int, ll: float) -> None:
        now = time.perf_counter()
        if now - last[0] > 2.0:
            last[0] = now
            print(f"  EM pass {it}: log-likelihood {ll:.3f}", file=sys.stderr)

    if args.method == "em":
        est = em(
            graph,
            data,
            max_iter=args.max_iter,
            tol=args.tol,
            pseudo_count=args.pseudo_count,
            b0_pseudo_count=args.b0_pseudo_count,
            progress=progress,
            workers=args.threads,
        )
    else:
        est = eq8(graph, data, rounds=args.rounds)
    out = est.to_json(graph, data)
    if args.truth:
        truth = parse_target(graph, args.truth)
        out["mean_row_tv_to_truth"] = mean_row_tv(est.model, truth)
    path = atomic_write(args.out, json.dumps(out) + "\n")
    msg = (
        f"{args.method}: {est.iterations} passes, converged={est.converged}, "
        f"{time.perf_counter() - t0:.1f} s; wrote {path}"
    )
    if est.log_likelihood:
        msg += f"; log-likelihood {est.log_likelihood[-1]:.3f}"
    if args.truth:
        msg += f"; mean row TV to truth {out['mean_row_tv_to_truth']:.4f}"
    print(msg)
    return 0


# ---------------------------------------------------------------------- train
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
            f"capture time {p['mean_capture_time']:6.2f}  "
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
    from shared.learning.train import leave_process_group, train

    detection = "neighbourhood" if args.variant == "cepg+" else "node"
    if args.variant == "cepg+" and args.detection == "node":
        raise CliError("cepg+ trains with a sensing range: use --detection neighbourhood or custom, or leave it out")
    graph, target, sensor = world_of(args, detection)
    device = _device(args.device)
    out = Path(args.out)
    if out.exists() and not (out / "policy.json").is_file():
        raise CliError(f"--out {out} exists and is not a policy snapshot; refusing to replace it")
    init_model = None
    if args.model:
        from shared.core.models import load_model_file

        init_model = load_model_file(graph, args.model)
    init_policy = load_snapshot(args.init, graph) if args.init else None
    cfg = train_config.from_flags(args, robots=args.robots, seed=args.seed, device=str(device))
    marl = cfg.algorithm != "cepg"
    try:
        cfg.check()
        cfg.per_robot(cfg.beta, "--beta")
        cfg.per_robot(cfg.lr, "--lr")
        if args.hp and not marl:
            raise ValueError("--hp sets a MARL baseline's hyperparameters; CE-PG takes its own flags")
        if marl and init_policy is not None:
            raise ValueError(f"--init warm-starts CE-PG only; {cfg.algorithm} trains from scratch")
        if args.checkpoint and not marl:
            raise ValueError("--checkpoint makes a MARL baseline's run resumable; CE-PG runs are not checkpointed")
        hyper = None
        if marl:
            from shared.learning.marl import hyperparameters

            lr = None if args.lr is None else cfg.lr[0]
            hyper = hyperparameters(cfg.algorithm, args.hp, episodes=args.episodes, envs=args.batch, lr=lr)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    torch.set_num_threads(args.threads)
    if marl and int(os.environ.get("WORLD_SIZE", "1")) > 1:
        raise CliError(f"{cfg.algorithm} runs in one process; torchrun data parallelism is CE-PG's")
    rank = _init_distributed(device)
    stop = {"requested": False}

    def on_sigint(_sig: int, _frame: Any) -> None:
        if stop["requested"]:
            raise KeyboardInterrupt
        stop["requested"] = True
        print("\nmures: stopping after the current update (Ctrl-C again to abort without a snapshot)", file=sys.stderr)

    old_handler = signal.signal(signal.SIGINT, on_sigint)
    bar = _Progress() if rank == 0 and not args.quiet else None
    model_text = "true model" if cfg.belief == "true" else "EM-estimated model"
    if rank == 0 and hyper is not None:
        print(
            f"training {cfg.algorithm} on {graph.name} (n={graph.n}), N={args.robots}, {hyper.episodes:,} episodes, "
            f"{model_text}; hyperparameters {hyper.to_dict()}",
            file=sys.stderr,
        )
    elif rank == 0:
        print(
            f"training {args.variant} on {graph.name} (n={graph.n}), N={args.robots}, beta={args.beta}, "
            f"{cfg.episodes:,} episodes, {model_text}",
            file=sys.stderr,
        )
    try:
        if hyper is not None:
            from shared.learning.marl import train_marl

            try:
                res = train_marl(
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
        else:
            res = train(
                graph,
                target,
                sensor,
                cfg,
                init_model=init_model,
                init_policy=init_policy,
                progress=bar,
                should_stop=lambda: stop["requested"],
            )
    finally:
        signal.signal(signal.SIGINT, old_handler)
        if bar:
            bar.close()
    if rank == 0:
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
            [] if marl else cfg.per_robot(cfg.beta, "beta"),
            config,
            res.summary,
            algorithm=cfg.algorithm,
        )
        s = res.summary
        resumed = f" (resumed at {s['resumed'][-1]['episodes']:,})" if s.get("resumed") else ""
        print(
            f"{'interrupted: ' if res.interrupted else ''}{s['episodes']:,} episodes{resumed} ({s['env_steps']:,} team "
            f"steps) in {s['wall_seconds']:.1f} s, {s['episodes_per_second']:.0f} episodes/s; "
            f"last capture time {s['final_mean_capture_time']:.2f}; wrote {out}"
        )
        if args.checkpoint and res.interrupted:
            print(f"checkpoint in {args.checkpoint}: the same command continues the run from it")
        elif args.checkpoint:
            from shared.learning.marl import remove_checkpoint

            remove_checkpoint(args.checkpoint)
    code = 130 if res.interrupted else 0
    leave_process_group(code)  # under torchrun: ends this process with ``code``
    return code


# ---------------------------------------------------------------------- snapshot convert
def cmd_snapshot_convert(args: argparse.Namespace) -> int:
    from shared.learning.snapshot import convert_snapshot

    for d in args.dirs:
        done = convert_snapshot(d)
        print(f"{d}: {'converted to weights.safetensors' if done else 'already in the numpy-readable format'}")
    return 0


# ---------------------------------------------------------------------- map
def cmd_map(args: argparse.Namespace) -> int:
    g = graph_of(args)
    deg = g.deg_closed - 1
    info = {
        "name": g.name,
        "nodes": g.n,
        "edges": g.m,
        "start_node": int(g.labels[g.start]),
        "max_degree": int(deg.max()),
        "mean_degree": float(np.mean(deg)),
        "graph_id": g.graph_id,
    }
    print(json.dumps(info, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mures", description="MuRES fleet: multirobot search for a moving target")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("evaluate", help="evaluate a searcher in simulation and print capture-time statistics")
    add_world_args(p)
    p.add_argument(
        "--searcher", required=True, help="random, greedy, fhpe, fhpe-sa, milp, d-milp, oracle, or policy:DIR"
    )
    p.add_argument("--episodes", type=positive_int, default=1500, help="episodes (default 1500)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("simulate", help="simulate missions and write their episode records (JSON Lines)")
    add_world_args(p)
    p.add_argument("--searcher", default="random", help="searcher that drives the robots (default random)")
    p.add_argument("--missions", type=positive_int, required=True, help="number of missions")
    p.add_argument("--fleet", default="default", help="fleet name written into the records")
    p.add_argument("--out", required=True, metavar="FILE.jsonl", help="output records")
    p.add_argument("--truth", metavar="FILE", help="also write the true target model as model.json")
    p.set_defaults(func=cmd_simulate)

    p = sub.add_parser("estimate", help="estimate Gamma_hat and b0 from episode records")
    add_map_args(p)
    p.add_argument("--episodes", required=True, metavar="FILE.jsonl", help="episode records (JSON Lines)")
    p.add_argument("--out", required=True, metavar="model.json")
    p.add_argument("--method", choices=ESTIMATORS, default="em", help="EM (default) or the paper's Eq. 8")
    p.add_argument("--max-iter", type=positive_int, default=1000, help="EM forward-backward passes at most")
    p.add_argument("--tol", type=float, default=1e-6, help="EM relative log-likelihood tolerance")
    p.add_argument(
        "--pseudo-count",
        type=float,
        default=0.0,
        help="Dirichlet prior: expected transitions added to each entry of Gamma_hat's support (default 0: "
        "maximum likelihood; the training server uses 1)",
    )
    p.add_argument(
        "--b0-pseudo-count",
        type=float,
        default=0.0,
        help="Dirichlet prior: expected starts added to every node of b0 (default 0; the training server uses 1)",
    )
    p.add_argument("--rounds", type=positive_int, default=1, help="Eq. 8 rounds (filter <-> Eq. 8)")
    p.add_argument("--truth", metavar="MODEL", help="a known model (lazy:STAY, uniform, or .json): report the TV")
    p.add_argument(
        "--threads",
        type=positive_int,
        default=1,
        help="cores EM runs on: its missions shared by that many processes, each on one torch thread "
        "(default 1; the estimate differs only by rounding, about 1e-9)",
    )
    p.set_defaults(func=cmd_estimate)

    p = sub.add_parser(
        "train", help="train a team in simulation (CE-PG or a MARL baseline) and write a policy snapshot"
    )
    add_world_args(p)
    p.add_argument("--out", required=True, metavar="DIR", help="snapshot directory to write")
    train_config.add_flags(p)  # one flag per TrainConfig field, its defaults
    p.add_argument("--true-model", dest="belief", action="store_const", const="true", help="the same as --belief true")
    p.add_argument("--model", metavar="model.json", help="Gamma_hat_0 and b0 for the beliefs (default I, uniform)")
    p.add_argument("--init", metavar="DIR", help="start from this snapshot's weights (CE-PG)")
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

    add_fleet_commands(sub)

    add_experiment_commands(sub)

    p = sub.add_parser("map", help="print a map's size and graph_id")
    add_map_args(p)
    p.set_defaults(func=cmd_map)

    p = sub.add_parser("snapshot", help="policy snapshot tools")
    snap_sub = p.add_subparsers(dest="snapshot_command", required=True, metavar="ACTION")
    c = snap_sub.add_parser(
        "convert", help="rewrite an older snapshot's weights.pt as weights.safetensors (the same values)"
    )
    c.add_argument("dirs", nargs="+", metavar="DIR", help="snapshot directories")
    c.set_defaults(func=cmd_snapshot_convert)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (CliError, GraphError, ModelError, SnapshotError) as exc:
        print(f"mures: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"mures: error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except EMWorkerError as exc:  # not the input's fault: a worker process was killed
        print(f"mures: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("mures: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

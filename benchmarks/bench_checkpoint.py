"""What a resumable MARL run's checkpoint costs (`mures train --checkpoint`, the experiments'
MARL teams): its size on disk and the seconds to write and to read it, for a MUSEUM team whose
replay buffer is full (the largest checkpoint the protocol makes).

Run: python benchmarks/bench_checkpoint.py [--map museum] [--robots 4] [--algorithm masac] [--buffer 200000]

Collects with the untrained actors until the buffer is full (no gradient steps: ``warmup`` is
set beyond the run), stops (which saves a checkpoint), then resumes from it once (which reads it
and, after one more batch and the stop, saves again). Prints the checkpoint's size and each
save's and load's seconds, and the share of a team's training time that saving every 10 minutes
takes at that cost.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.learning.config import CHECKPOINT_EVERY_S, TrainConfig
from shared.learning.marl import hyperparameters, train_marl
from shared.learning.marl.checkpoint import Checkpointer

TIMES: dict[str, list[float]] = {"save": [], "load": []}


def _timed(name: str, fn):  # type: ignore[no-untyped-def]
    def wrapper(self, *a, **k):  # type: ignore[no-untyped-def]
        t = time.perf_counter()
        out = fn(self, *a, **k)
        TIMES[name].append(time.perf_counter() - t)
        return out

    return wrapper


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--map", default="museum")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--algorithm", default="masac", choices=["maddpg", "masac", "facmac", "mambpo"])
    ap.add_argument("--buffer", type=int, default=200_000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    Checkpointer.save = _timed("save", Checkpointer.save)  # type: ignore[method-assign]
    Checkpointer.load = _timed("load", Checkpointer.load)  # type: ignore[method-assign]
    g = builtin_graph(args.map)
    hyper = hyperparameters(args.algorithm, [f"buffer={args.buffer}", "warmup=1000000000", "episodes=1000000000"])
    cfg = TrainConfig(robots=args.robots, algorithm=args.algorithm, seed=0, em_first=10**9)
    batches = -(-args.buffer // (hyper.envs * hyper.collect))  # until the buffer is full
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as tmp:
        ckpt = Path(tmp) / "ckpt"
        calls = iter(range(10**9))
        t0 = time.perf_counter()
        train_marl(
            args.algorithm,
            g,
            uniform_walk(g),
            Sensor(),
            cfg,
            hyper,
            should_stop=lambda: next(calls) + 1 >= batches,
            checkpoint=ckpt,
        )
        fill = time.perf_counter() - t0 - sum(TIMES["save"])
        size = sum(p.stat().st_size for p in ckpt.rglob("*") if p.is_file())
        train_marl(args.algorithm, g, uniform_walk(g), Sensor(), cfg, hyper, should_stop=lambda: True, checkpoint=ckpt)
    save, load = TIMES["save"], TIMES["load"]
    print(
        f"{args.map.upper()} N={args.robots} {args.algorithm}, buffer {args.buffer:,} transitions (filled in {fill:.0f} s): "
        f"checkpoint {size / 1e9:.2f} GB; save {', '.join(f'{s:.1f}' for s in save)} s; load {', '.join(f'{s:.1f}' for s in load)} s; "
        f"every {CHECKPOINT_EVERY_S:.0f} s of training that is {100 * max(save) / CHECKPOINT_EVERY_S:.1f} % at most"
    )


if __name__ == "__main__":
    main()

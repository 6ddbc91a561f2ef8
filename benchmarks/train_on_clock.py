"""A team trained on travel times against the same team trained in steps, both flown on travel
times: what training on the clock (`mures train --speed`) buys a robot's own policy.

    python benchmarks/train_on_clock.py [--robots 2 4] [--episodes 20000] [--eval-episodes 1000]
                                        [--algorithm cepg|maddpg|masac|facmac|mambpo|mappo]
                                        [--speed 0.5] [--offices 2] [--maps depot,bookstore,...]
                                        [--workdir DIR] [--json results/train_on_clock/train_on_clock.json]

Per map (imported with `mures map import`'s defaults; Nav2's and AWS's maps, generated office
floors) and team size N:
1. `mures train --graph G --robots N --episodes E --seed 0 --out STEPS` (the paper's model: every
   move one step) and the same with `--speed S` (each move its travel time in ticks of 1 s, EM per
   tick): CE-PG (or ``--algorithm``'s MARL baseline) with each robot on its own belief, the model
   learned by EM, as the trainer does by default;
2. both teams, greedy and random evaluated on travel times (`mures evaluate --clock --speed S`'s
   engine), on the same episodes (seed 1: the simulator draws the target's path and every reading
   from its own generator, the same for every searcher while an episode runs), so the clock team's
   capture times are paired with the step team's: the difference's mean and 95 % CI.
Prints a row per map and N (capture times in seconds) and writes them as JSON.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from fleet_in_time import maps  # benchmarks/fleet_in_time.py, beside this script
from shipped_maps import imported, write_rows

from shared.core.clock import TravelTimes
from shared.core.models import Sensor, uniform_walk
from shared.engine.evaluate import evaluate, mean_ci95
from shared.registry import searcher_factory

MURES = [sys.executable, "-m", "shared.tools.cli"]


def train(graph_file: Path, robots: int, episodes: int, out: Path, *extra: str) -> float | None:
    """`mures train` into ``out`` unless it is there; the seconds it took (None when it was there)."""
    if out.exists():
        return None
    t0 = time.perf_counter()
    args = ["train", "--graph", str(graph_file), "--robots", str(robots), "--episodes", str(episodes), "--seed", "0",
            "--out", str(out), "--quiet", *extra]  # fmt: skip
    r = subprocess.run([*MURES, *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"mures {' '.join(args)} failed:\n{r.stderr[-2000:]}")
    return time.perf_counter() - t0


def cell(figures: dict[str, float]) -> str:
    """A capture time's mean ± 95 % CI half-width, in seconds."""
    return f"{figures['mean_capture_time_s']:7.1f} ± {figures['ci95_halfwidth_s']:5.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--episodes", type=int, default=20_000, help="training episodes of each team (default 20000)")
    ap.add_argument("--eval-episodes", type=int, default=1000, help="evaluation episodes (default 1000)")
    ap.add_argument("--algorithm", default="cepg", help="the method both teams train with (default cepg)")
    ap.add_argument("--speed", type=float, default=0.5, help="robots' speed, m/s (default 0.5)")
    ap.add_argument("--offices", type=int, default=2, help="generated office floors, seeds 1..K (default 2)")
    ap.add_argument("--maps", type=lambda s: s.split(","), default=None, help="only these (default: all here)")
    ap.add_argument("--workdir", help="keep graphs and teams here (default: a temporary folder)")
    ap.add_argument("--json", default="results/train_on_clock/train_on_clock.json")
    args = ap.parse_args()
    tmp = None if args.workdir else tempfile.TemporaryDirectory(prefix="mures-train-on-clock-")
    work = Path(args.workdir or tmp.name)  # type: ignore[union-attr]
    work.mkdir(parents=True, exist_ok=True)
    sensor = Sensor()
    rows = []
    print(f"{'map':<12} {'n':>4} {'N':>2} {'step team s':>16} {'clock team s':>16} {'clock - step':>20} "
          f"{'greedy s':>16} {'random s':>9}")  # fmt: skip
    for name, yaml_path in maps(args.maps, args.offices, work):
        graph = imported(yaml_path, work)
        graph_file = work / f"{yaml_path.stem}.json"
        clock = TravelTimes.of(graph, args.speed)
        target = clock.model(uniform_walk(graph))
        for robots in args.robots:
            tag = "" if args.algorithm == "cepg" else f"{args.algorithm}-"
            steps_team, clock_team = work / f"steps-{tag}{name}-N{robots}", work / f"clock-{tag}{name}-N{robots}"
            method = ("--algorithm", args.algorithm)
            wall = {
                "steps": train(graph_file, robots, args.episodes, steps_team, *method),
                "clock": train(graph_file, robots, args.episodes, clock_team, *method, "--speed", str(args.speed)),
            }
            times = {}
            for key, searcher in (("steps", f"policy:{steps_team}"), ("clock", f"policy:{clock_team}"),
                                  ("greedy", "greedy"), ("random", "random")):  # fmt: skip
                factory = searcher_factory(searcher, graph, target, sensor, robots, clock=clock)
                res = evaluate(graph, target, sensor, robots, factory, episodes=args.eval_episodes, seed=1, clock=clock)
                times[key] = res.capture_time.astype(np.float64) * clock.tick_s
            diff = times["clock"] - times["steps"]
            row = {"map": name, "nodes": graph.n, "robots": robots, "algorithm": args.algorithm,
                   "episodes": args.eval_episodes}  # fmt: skip
            for key, ct in times.items():
                mean, half = mean_ci95(ct)
                row[key] = {"mean_capture_time_s": mean, "ci95_halfwidth_s": half}
            d_mean, d_half = mean_ci95(diff)
            row["clock_minus_steps_s"] = {"mean": d_mean, "ci95_halfwidth": d_half}
            row["training_wall_s"] = {k: None if v is None else round(v, 1) for k, v in wall.items()}
            rows.append(row)

            print(f"{name:<12} {graph.n:>4} {robots:>2} {cell(row['steps']):>16} {cell(row['clock']):>16} "
                  f"{d_mean:+8.1f} ± {d_half:4.1f} ({d_mean / row['steps']['mean_capture_time_s']:+.0%}) "
                  f"{cell(row['greedy']):>16} {row['random']['mean_capture_time_s']:9.1f}", flush=True)  # fmt: skip
    out = write_rows(args.json, {k: v for k, v in vars(args).items() if k != "workdir"}, rows)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""Batched simulator throughput: random searcher, OFFICE, N = 4, auto-reset (training mode).

Run: python benchmarks/bench_sim.py [--batch B] [--seconds S]
Prints finished episodes per second and team steps (env steps) per second.
"""

import argparse
import time

import torch

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.engine.searchers import GreedySearcher, RandomSearcher
from shared.engine.sim import SearchSim


def run(searcher_name: str, batch: int, seconds: float) -> None:
    g = builtin_graph("office")
    model, sensor = uniform_walk(g), Sensor()
    sim = SearchSim(g, model, sensor, n_robots=4, batch=batch, seed=0)
    searcher = RandomSearcher(g, seed=1) if searcher_name == "random" else GreedySearcher(g, model, sensor, seed=1)
    obs = sim.reset()
    with torch.no_grad():
        for _ in range(50):  # warm-up
            obs, _ = sim.step(searcher.act(obs))
        episodes, steps, total_t = 0, 0, 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            obs, res = sim.step(searcher.act(obs))
            done = int(res.done.sum())
            episodes += done
            total_t += int(res.capture_time[res.done].sum())
            steps += batch
        dt = time.perf_counter() - t0
    print(
        f"simulator  OFFICE N=4 {searcher_name:<6} B={batch:<6} threads={torch.get_num_threads()}  "
        f"{episodes / dt:10.0f} episodes/s  {steps / dt:12.0f} team-steps/s  "
        f"(mean capture time of finished episodes {total_t / max(episodes, 1):.1f})"
    )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, nargs="*", default=[1024, 8192, 32768])
    ap.add_argument("--seconds", type=float, default=3.0)
    args = ap.parse_args()
    for b in args.batch:
        run("random", b, args.seconds)
    run("greedy", 8192, args.seconds)


if __name__ == "__main__":
    main()

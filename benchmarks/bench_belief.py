"""One robot's belief update (Theorem 1) with the O(n + m) filter: median time per step.

Run: python benchmarks/bench_belief.py
"""

import statistics
import time

import numpy as np

from shared.core.belief_filter import BeliefFilter
from shared.core.graph import builtin_graph, grid_graph
from shared.core.models import Sensor, uniform_walk


def bench(graph, steps: int) -> tuple[float, float]:
    f = BeliefFilter(graph, uniform_walk(graph), Sensor(eta_fn=0.1, eta_fp=0.01))
    rng = np.random.default_rng(0)
    p = graph.start
    f.reset(p, 0)
    times = []
    for _ in range(steps):
        p = int(rng.choice(graph.closed(p)))
        z = int(rng.random() < 0.05)
        t0 = time.perf_counter()
        f.update(p, z)
        times.append(time.perf_counter() - t0)
    times.sort()
    return statistics.median(times) * 1e6, times[int(0.99 * len(times))] * 1e6


def main() -> None:
    for graph, steps in ((builtin_graph("museum"), 20000), (grid_graph(100, 100), 2000)):
        med, p99 = bench(graph, steps)
        print(f"belief update  {graph.name:<12} n={graph.n:<6} m={graph.m:<6} median {med:8.1f} us   p99 {p99:8.1f} us")


if __name__ == "__main__":
    main()

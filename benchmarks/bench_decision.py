"""One robot's decision step as the agent runs it (Algorithm 1, lines 3 and 7): the belief update
(Theorem 1) plus the policy network and the action draw, in numpy. Median and p99 per step.

Run: python benchmarks/bench_decision.py [SNAPSHOT_DIR]   (MUSEUM, n = 70, unless a snapshot says otherwise)

Without a snapshot the network has freshly initialised weights and the belief uses the uniform
walk: the cost does not depend on the weights' values or on Gamma_hat's (fixed) support.
"""

import statistics
import sys
import time

import numpy as np
import torch

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.core.snapshot_format import PolicyAgent, read_snapshot
from shared.learning.policy import TeamPolicy
from shared.learning.team_snapshot import Snapshot


def main() -> None:
    g = builtin_graph("museum")
    if len(sys.argv) > 1:
        snap = read_snapshot(sys.argv[1], g)
    else:
        policy = TeamPolicy(g.n, 4, torch.as_tensor(g.adjacency()))
        snap = Snapshot(
            meta={"variant": "cepg", "robots": 4}, policy=policy, model=uniform_walk(g), sensor=Sensor()
        ).to_data()
    agent = PolicyAgent(snap, g, robot=0, seed=0)
    rng = np.random.default_rng(0)
    p = g.start
    agent.reset(p, 0)
    times = []
    for _ in range(20_000):
        z = int(rng.random() < 0.02)
        t0 = time.perf_counter()
        agent.observe(p, z)
        p = agent.act(p)
        times.append(time.perf_counter() - t0)
    times.sort()
    med, p99 = statistics.median(times) * 1e6, times[int(0.99 * len(times))] * 1e6
    print(f"decision step (belief update + policy + draw), {g.name} n={g.n}: median {med:.1f} us, p99 {p99:.1f} us")


if __name__ == "__main__":
    main()

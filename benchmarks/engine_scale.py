"""The engine's cost against the building's size: the batched simulator with greedy robots (their
beliefs predicted and updated every step) on generated office floors of 100-10,000 nodes, dense
(Gamma_hat an (n, n) matrix, the engine below 512 nodes) and sparse (its n + 2m entries, above).

    python benchmarks/engine_scale.py [--nodes 100 300 1000 3000 10000] [--batch 64] [--robots 4]
                                      [--steps 200] [--json results/engine_scale/engine_scale.json]

Each (size, representation) runs in a fresh process (its peak memory is that process's, read from
getrusage): B episodes of N greedy robots (shared/engine/searchers.py) on `office_graph(n)`
(shared/core/graph.py: two corridors joined every tenth node, rooms off them), ``--steps`` steps
after 10 of warm-up, one torch thread. Prints milliseconds a step (B N beliefs each) and the peak
resident memory; dense is skipped where its (n, n) tables would not fit the engine's limit.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

from shipped_maps import write_rows  # benchmarks/shipped_maps.py, beside this script


def measure(n: int, sparse: bool, batch: int, robots: int, steps: int) -> dict:
    """One configuration, in this process: ms a step and peak memory."""
    import torch

    from shared.core.graph import office_graph
    from shared.core.models import Sensor, uniform_walk
    from shared.engine.batched_belief import BatchedBelief
    from shared.engine.searchers import GreedySearcher
    from shared.engine.sim import SearchSim

    torch.set_num_threads(1)
    graph = office_graph(n, seed=0)
    model, sensor = uniform_walk(graph), Sensor()
    sim = SearchSim(graph, model, sensor, robots, batch, seed=0, auto_reset=True)
    greedy = GreedySearcher(graph, model, sensor, seed=1)
    greedy.beliefs.belief = BatchedBelief(graph, model, sensor, sparse=sparse)
    obs = sim.reset()
    with torch.no_grad():
        for _ in range(10):
            obs, _ = sim.step(greedy.act(obs))
        t0 = time.perf_counter()
        for _ in range(steps):
            obs, _ = sim.step(greedy.act(obs))
        wall = time.perf_counter() - t0
    return {
        "nodes": n,
        "edges": graph.m,
        "sparse": sparse,
        "ms_per_step": 1000 * wall / steps,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nodes", type=int, nargs="+", default=[100, 300, 1000, 3000, 10000])
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--json", default="results/engine_scale/engine_scale.json")
    ap.add_argument("--one", nargs=2, metavar=("N", "SPARSE"), help=argparse.SUPPRESS)  # a child's configuration
    args = ap.parse_args()
    if args.one:
        n, sparse = int(args.one[0]), args.one[1] == "1"
        print(json.dumps(measure(n, sparse, args.batch, args.robots, args.steps)))
        return
    from shared.core.graph import DENSE_MAX_NODES

    rows = []
    print(f"{'nodes':>6} {'edges':>6} {'dense ms/step':>14} {'dense MB':>9} {'sparse ms/step':>15} {'sparse MB':>10}")
    for n in args.nodes:
        row: dict = {}
        for sparse in (False, True):
            if not sparse and n > DENSE_MAX_NODES:
                continue
            cmd = [sys.executable, __file__, "--one", str(n), "1" if sparse else "0", "--batch", str(args.batch),
                   "--robots", str(args.robots), "--steps", str(args.steps)]  # fmt: skip
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            row["sparse" if sparse else "dense"] = json.loads(out)
        rows.append(row)
        d, s = row.get("dense"), row["sparse"]
        dense = f"{d['ms_per_step']:14.2f} {d['peak_rss_mb']:9.0f}" if d else f"{'-':>14} {'-':>9}"
        print(f"{n:>6} {s['edges']:>6} {dense} {s['ms_per_step']:15.2f} {s['peak_rss_mb']:10.0f}", flush=True)
    out = write_rows(args.json, {k: v for k, v in vars(args).items() if k != "one"}, rows)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

"""Does an estimated target model rule out where the target really is? Maximum-likelihood EM (what
the trainer's Algorithm 2 runs) against EM with the training server's Dirichlet prior (1 expected
transition per supported entry of Gamma_hat, 1 expected start per node), on the same records.

For each map: M missions of N random robots under the true target (the uniform walk), node
sensor without noise, as episode records; both estimates from them; then E fresh episodes of the
same kind in which every robot filters its own belief with each estimated model (Eq. 1). Printed
per model: the share of episodes whose true start node has b0 = 0, the share of robot-steps whose
belief gives the target's true node probability 0, the filter's restarts (its mass vanished)
per episode, and the mean row total-variation distance of Gamma_hat to the truth.

Run: python benchmarks/model_support.py [--maps office museum] [--missions 512] [--robots 4]
         [--episodes 150] [--seed 1]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from shared.core.belief_filter import BeliefFilter
from shared.core.graph import builtin_graph
from shared.core.models import Sensor, TargetModel, uniform_walk
from shared.engine.estimate import collect_missions, em, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate
from shared.engine.searchers import RandomSearcher

ZERO = 1e-12  # a probability below this counts as ruled out


def rules_out(graph, truth: TargetModel, model: TargetModel, robots: int, episodes: int, seed: int) -> dict:
    """Fly ``episodes`` random-robot episodes under ``truth`` and filter each robot's belief with
    ``model``; count where the model gives the truth probability zero."""
    rng = np.random.default_rng(seed)
    sensor = Sensor()
    gamma = np.cumsum(truth.dense(), axis=1)
    b0 = np.cumsum(truth.b0)
    start_ruled_out, steps, zero_steps, restarts = 0, 0, 0, 0
    for _ in range(episodes):
        e = int(np.searchsorted(b0, rng.random() * b0[-1], side="right"))
        start_ruled_out += model.b0[e] < ZERO
        pos = [graph.start] * robots
        filters = [BeliefFilter(graph, model, sensor) for _ in range(robots)]
        for t in range(3 * graph.n + 1):
            if t:
                e = int(np.searchsorted(gamma[e], rng.random() * gamma[e, -1], side="right"))
                pos = [int(rng.choice(graph.closed(p))) for p in pos]
            caught = False
            for i, f in enumerate(filters):
                z = int(pos[i] == e)
                b = f.reset(pos[i], z) if t == 0 else f.update(pos[i], z)
                steps += 1
                zero_steps += b[e] < ZERO
                caught |= bool(z)
            if caught:
                break
        restarts += sum(f.restarts for f in filters)
    return {
        "start_ruled_out": start_ruled_out / episodes,
        "steps_ruled_out": zero_steps / steps,
        "restarts_per_episode": restarts / episodes,
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--maps", nargs="+", default=["office", "museum"])
    ap.add_argument("--missions", type=int, default=512)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=150)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(
        f"{args.missions} missions of {args.robots} random robots (seed {args.seed}) -> EM; "
        f"{args.episodes} fresh episodes (seed {args.seed + 1}) filtered with each estimate"
    )
    print("map     model                     start ruled out  robot-steps ruled out  restarts/episode  row TV  EM s")
    for name in args.maps:
        graph = builtin_graph(name)
        truth = uniform_walk(graph)
        res = evaluate(
            graph,
            truth,
            Sensor(),
            args.robots,
            lambda s, graph=graph: RandomSearcher(graph, seed=s),
            args.missions,
            args.seed,
            record=True,
        )
        data = collect_missions(enumerate(episode_records(graph, res, Sensor())), graph)
        for label, prior in (("maximum likelihood", 0.0), ("prior 1, 1 (the server's)", 1.0)):
            t0 = time.perf_counter()
            est = em(graph, data, max_iter=1000, tol=1e-6, pseudo_count=prior, b0_pseudo_count=prior)
            secs = time.perf_counter() - t0
            r = rules_out(graph, truth, est.model, args.robots, args.episodes, args.seed + 1)
            print(
                f"{name:7s} {label:25s} {r['start_ruled_out']:15.1%}  {r['steps_ruled_out']:21.2%}  "
                f"{r['restarts_per_episode']:16.2f}  {mean_row_tv(est.model, truth):6.3f}  {secs:4.1f}"
            )


if __name__ == "__main__":
    main()

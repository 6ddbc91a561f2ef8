"""The trainer's speed and the trained team's quality (its acceptance figures: 4x10^5 episodes on
OFFICE, N = 4, within 120 s; the team against the reference searchers).

Run: python benchmarks/bench_train.py [--env office] [--graph FILE] [--robots 4] [--episodes 400000]
                                      [--beta 0.5] [--seed 0] [--eval 1500] [--out DIR]

Trains CE-PG (Algorithm 2: EM-estimated beliefs, starting from Gamma_hat_0 = I) for the given
budget, writes the snapshot, then evaluates it and the reference searchers on the same seed
with the engine's evaluator and prints wall time, episodes/s and capture times (mean, 95% CI).
"""

import argparse
import time

import torch

from shared.core.graph import builtin_graph, load_graph_file
from shared.core.models import Sensor, uniform_walk
from shared.engine.evaluate import evaluate
from shared.learning.config import TrainConfig
from shared.learning.team_snapshot import PolicySearcher, load_snapshot, save_snapshot
from shared.learning.train import train
from shared.registry import make_searcher


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--env", default="office")
    ap.add_argument("--graph")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=400_000)
    ap.add_argument("--beta", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--eval", type=int, default=1500)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    g = load_graph_file(a.graph) if a.graph else builtin_graph(a.env)
    m, s = uniform_walk(g), Sensor()
    cfg = TrainConfig(robots=a.robots, episodes=a.episodes, beta=[a.beta], seed=a.seed)
    t0 = time.perf_counter()
    res = train(g, m, s, cfg)
    wall = time.perf_counter() - t0
    out = a.out or f"out/bench/{g.name.lower()}-N{a.robots}-beta{a.beta:g}-seed{a.seed}"
    save_snapshot(out, res.policy, g, res.model, s, "cepg", [a.beta] * a.robots, cfg.to_dict(), res.summary)
    sm = res.summary
    print(
        f"train {g.name} n={g.n} N={a.robots} beta={a.beta:g} seed={a.seed}: {sm['episodes']:,} episodes, "
        f"{sm['env_steps']:,} team steps in {wall:.1f} s ({sm['episodes_per_second']:.0f} episodes/s, "
        f"{sm['env_steps_per_second']:.0f} team steps/s, {a.threads} threads); "
        f"EM updates {[(u['episodes'], u['mean_row_tv_to_true'], u['seconds']) for u in sm['em_updates']]}"
    )
    snap = load_snapshot(out, g)
    rows = [("cepg", lambda sd: PolicySearcher(snap, g, s, a.robots, seed=sd))]
    rows += [(name, lambda sd, name=name: make_searcher(name, g, m, s, seed=sd)) for name in ("random", "greedy")]
    best_ref = None
    for name, factory in rows:
        r = evaluate(g, m, s, a.robots, factory, episodes=a.eval, seed=a.seed + 1).summary()
        lo, hi = r["ci95"]
        print(
            f"  {name:7s} {r['mean_capture_time']:7.2f}  (95% CI {lo:.2f} .. {hi:.2f}, {a.eval} episodes, "
            f"seed {a.seed + 1})"
        )
        if name == "cepg":
            learned = r["mean_capture_time"]
        else:
            best_ref = min(best_ref or 1e9, r["mean_capture_time"])
    print(f"  cepg captures {100 * (1 - learned / best_ref):.1f}% sooner than the better reference searcher")
    print(f"  snapshot: {out}")


if __name__ == "__main__":
    main()

"""CE-PG (beta = 0.5) against vanilla PG (beta = 1): same maps, team sizes, seeds and budget.

Run: python benchmarks/compare_beta.py [--env office] [--robots 2,3,4] [--seeds 0,1,2]
                                       [--episodes 30000] [--belief em|true] [--eval 1500]
                                       [--ce-states shared,all]

CE-PG is trained once per --ce-states value (the states the cross entropy counts at, shared/learning/cepg.py).

For every (N, seed) both betas train from the same initial weights and simulator seed; each final
team is evaluated on 1500 episodes (seed 1000 + seed). Printed per run: the final capture time
(mean, 95% CI) and the mean capture time over all training episodes (the area under the
learning curve: lower = learned sooner); then, per N, both averaged over seeds with the paired
difference PG - CE-PG (mean and 95% CI over seeds, t distribution).
"""

import argparse
import math
import statistics

import torch

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.engine.evaluate import evaluate
from shared.learning.config import TrainConfig
from shared.learning.team_snapshot import PolicySearcher, Snapshot
from shared.learning.train import train

T95 = {1: 12.71, 2: 4.30, 3: 3.18, 4: 2.78, 5: 2.57, 6: 2.45, 7: 2.36, 8: 2.31, 9: 2.26}


def ci(xs: list[float]) -> tuple[float, float]:
    m = statistics.fmean(xs)
    if len(xs) < 2:
        return m, float("nan")
    return m, T95.get(len(xs) - 1, 1.96) * statistics.stdev(xs) / math.sqrt(len(xs))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--env", default="office")
    ap.add_argument("--robots", default="2,3,4")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--episodes", type=int, default=30_000)
    ap.add_argument("--belief", default="em", choices=("em", "true"))
    ap.add_argument("--eval", type=int, default=1500)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--ce-states", default="shared", help="comma-separated: shared, all")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    g = builtin_graph(a.env)
    m, s = uniform_walk(g), Sensor()
    print(f"{g.name}, {a.episodes:,} training episodes per run, beliefs: {a.belief}, eval {a.eval} episodes")
    arms = [(f"CE-PG ({c})", 0.5, c) for c in a.ce_states.split(",")] + [("PG", 1.0, "shared")]
    for N in (int(x) for x in a.robots.split(",")):
        final: dict[str, list[float]] = {name: [] for name, _, _ in arms}
        auc: dict[str, list[float]] = {name: [] for name, _, _ in arms}
        for seed in (int(x) for x in a.seeds.split(",")):
            for name, beta, states in arms:
                cfg = TrainConfig(
                    robots=N, episodes=a.episodes, beta=[beta], belief=a.belief, seed=seed, ce_states=states
                )
                res = train(g, m, s, cfg)
                snap = Snapshot(meta={"variant": "cepg", "robots": N}, policy=res.policy, model=res.model, sensor=s)
                ev = evaluate(
                    g,
                    m,
                    s,
                    N,
                    lambda sd, snap=snap, N=N: PolicySearcher(snap, g, s, N, seed=sd),
                    episodes=a.eval,
                    seed=1000 + seed,
                ).summary()
                curve = res.summary["learning_curve"]
                area = sum(p["mean_capture_time"] for p in curve) / len(curve)
                final[name].append(ev["mean_capture_time"])
                auc[name].append(area)
                print(
                    f"  N={N} seed={seed} {name}: final {ev['mean_capture_time']:6.2f} "
                    f"+- {ev['ci95_halfwidth']:.2f}   training mean {area:6.2f}   "
                    f"({res.summary['wall_seconds']:.0f} s)",
                    flush=True,
                )
        for label, d in (("final capture time", final), ("training mean (AUC)", auc)):
            mp, hp = ci(d["PG"])
            for name, _, _ in arms[:-1]:
                diff = [p - c for p, c in zip(d["PG"], d[name], strict=True)]
                (mc, hc), (md, hd) = ci(d[name]), ci(diff)
                print(
                    f"N={N} {label}: {name} {mc:.2f} +- {hc:.2f}, PG {mp:.2f} +- {hp:.2f}, "
                    f"PG - {name} {md:+.2f} +- {hd:.2f} over {len(diff)} seeds"
                )


if __name__ == "__main__":
    main()

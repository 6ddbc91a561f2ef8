"""EM acceptance run: a lazy target (stay 0.9) on our WAREHOUSE map (or --map ward, 36 nodes), 3
random robots, eta_fn = 0.1, 1000 missions; mean row total-variation distance of the estimate to the
truth, and wall time.

Run: python benchmarks/bench_estimate.py [--map warehouse|ward|GRAPH.json] [--missions 1000] [--seed 1] [--threads T]
    [--pseudo-count C [C ...]]

--threads T: the cores EM runs on (`em(..., workers=T)`: T processes share the missions, each on one
torch thread; `mures estimate --threads T`); each run is timed.

--pseudo-count runs EM once per value C (a Dirichlet prior of C expected transitions added to
every supported entry, `em(..., pseudo_count=C)`; 0 is maximum likelihood) and prints each
estimate's distance to the truth: does a prior help where the likelihood is flat?
"""

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from shared.core.graph import builtin_graph, load_graph_file
from shared.core.models import Sensor, lazy_walk, uniform_walk
from shared.engine.estimate import collect_missions, em, eq8, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate
from shared.engine.searchers import RandomSearcher

MAP = Path(__file__).resolve().parents[1] / "examples" / "maps" / "warehouse.json"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--missions", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--map", default="warehouse")
    ap.add_argument("--threads", type=int, nargs="+", default=[1], metavar="T")
    ap.add_argument("--pseudo-count", type=float, nargs="+", default=[0.0], metavar="C")
    args = ap.parse_args()
    torch.set_num_threads(1)
    g = (
        load_graph_file(MAP if args.map == "warehouse" else args.map)
        if args.map.endswith(".json") or args.map == "warehouse"
        else builtin_graph(args.map)
    )
    truth, sensor, N = lazy_walk(g, 0.9), Sensor(eta_fn=0.1), 3
    res = evaluate(g, truth, sensor, N, lambda s: RandomSearcher(g, seed=s), args.missions, args.seed, record=True)
    recs = list(episode_records(g, res, sensor))
    t0 = time.perf_counter()
    data = collect_missions(enumerate(recs), g)
    t_collect = time.perf_counter() - t0
    print(
        f"{g.name} n={g.n}, lazy target stay 0.9, N=3 random robots, eta_fn=0.1, {args.missions} missions, "
        f"seed {args.seed}; records -> emission likelihoods {t_collect:.1f} s"
    )
    for c in args.pseudo_count:
        for workers in args.threads:
            t0 = time.perf_counter()
            est = em(g, data, pseudo_count=c, workers=workers)
            t_em = time.perf_counter() - t0
            print(
                f"  EM{'' if c == 0 else f' pseudo-count {c:g}'}  mean row TV {mean_row_tv(est.model, truth):.4f}  "
                f"({est.iterations} passes, converged={est.converged}, log-likelihood {est.log_likelihood[-1]:.2f}, "
                f"{t_em:.1f} s on {workers} core{'s' if workers > 1 else ''})"
            )
    e8 = eq8(g, collect_missions(enumerate(recs), g, capture_aware=False))
    print(f"  Eq. 8  mean row TV {mean_row_tv(e8.model, truth):.4f}  ({e8.wall_seconds:.1f} s)")
    print(
        f"  uniform-walk guess  {mean_row_tv(uniform_walk(g), truth):.4f};  identity guess {mean_row_tv(np.eye(g.n), truth):.4f}"
    )


if __name__ == "__main__":
    main()

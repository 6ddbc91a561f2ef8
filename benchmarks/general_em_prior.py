"""What EM's Dirichlet prior does to the general policy's captures on a large floor: the
measurement behind the fine-tune's default pseudo-counts (shared/learning/config.py
``em_prior``: 1 below 100 nodes, n / 15 up to 20 above).

    python benchmarks/general_em_prior.py [--sizes 300,1000] [--robots 4] [--episodes 400]
                                          [--pseudo-counts 1,5,20,default] [--targets uniform,lazy:0.6]
                                          [--json results/general_policy/em_prior.json]

Per generated office floor (``office_graph(n, seed=1)``) and target (the uniform walk, a lazy walk):
1. the shipped general policy, its beliefs on the uniform walk (where a fine-tune starts), flies
   the fine-tune's number of EM missions (``fine_tune_defaults(n)["em_missions"]``, seed 7) and
   they become episode records, as the fine-tune's model update makes them;
2. EM fits Gamma_hat and b0 from them with each pseudo-count (on Gamma_hat's entries and on b0;
   "default" is the fine-tune's);
3. the policy flies the same ``--episodes`` episodes (seed 11, the target on its true walk) with
   its beliefs on the true model, on the true model with other action draws (how far two runs of
   the same beliefs lie apart), on the uniform walk (for a lazy target) and on each EM estimate.
Prints mean capture time ± 95 % CI and the paired difference to the true model's run, with each
estimate's mean row total variation to the true walk.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from shared.core.graph import office_graph
from shared.core.models import Sensor, TargetModel, parse_target, uniform_walk
from shared.core.snapshot_format import load_general, shipped_general_path
from shared.engine.estimate import collect_missions, em, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate, mean_ci95
from shared.learning.config import fine_tune_defaults
from shared.learning.general import GeneralSearcher

ROOT = Path(__file__).resolve().parent.parent


def fly(policy, graph, true, model, robots, episodes, seed, offset=0, record=False):  # type: ignore[no-untyped-def]
    """``episodes`` episodes (seed ``seed``, the target on ``true``) of the general policy with its
    beliefs on ``model``, its action draws seeded ``offset`` from the episodes'."""
    sensor = Sensor()
    return evaluate(graph, true, sensor, robots,
                    lambda s: GeneralSearcher(policy, graph, model, sensor, robots, seed=s + offset),
                    episodes=episodes, seed=seed, record=record)  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="300,1000")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=400)
    ap.add_argument("--pseudo-counts", default="1,5,20,default")
    ap.add_argument("--targets", default="uniform,lazy:0.6")
    ap.add_argument("--json", default=str(ROOT / "results" / "general_policy" / "em_prior.json"))
    args = ap.parse_args()
    policy, sensor, N = load_general(shipped_general_path()), Sensor(), args.robots
    rows = []
    for n in (int(x) for x in args.sizes.split(",")):
        graph = office_graph(n, seed=1)
        defaults = fine_tune_defaults(n)
        counts = sorted({defaults["em_pseudo_count"] if c == "default" else float(c)
                         for c in args.pseudo_counts.split(",")})  # fmt: skip
        for target_name in args.targets.split(","):
            true = parse_target(graph, target_name)

            def times(model: TargetModel, offset: int = 0) -> np.ndarray:
                """(episodes,) capture times of the policy with its beliefs on ``model``."""
                res = fly(policy, graph, true, model, N, args.episodes, 11, offset)  # noqa: B023 - used at once
                return res.capture_time.astype(np.float64)

            flown = fly(policy, graph, true, uniform_walk(graph), N, defaults["em_missions"], 7, record=True)
            data = collect_missions(((0, r) for r in episode_records(graph, flown, sensor, mission_prefix="m")), graph)
            runs: list[tuple[str, dict, np.ndarray]] = [("true model", {}, times(true))]
            runs.append(("true model, other draws", {}, times(true, offset=17)))
            if target_name != "uniform":
                runs.append(("uniform walk", {"mean_row_tv_to_true": mean_row_tv(uniform_walk(graph), true)},
                             times(uniform_walk(graph))))  # fmt: skip
            for c in counts:
                t0 = time.perf_counter()
                est = em(graph, data, max_iter=60, tol=1e-5, pseudo_count=c, b0_pseudo_count=c)
                info = {"pseudo_count": c, "em_seconds": round(time.perf_counter() - t0, 1),
                        "em_passes": est.iterations, "mean_row_tv_to_true": round(mean_row_tv(est.model, true), 4)}  # fmt: skip
                runs.append((f"EM, pseudo-count {c:g}", info, times(est.model)))
            base = runs[0][2]
            for name, info, ct in runs:
                mean, half = mean_ci95(ct)
                d_mean, d_half = mean_ci95(ct - base)
                row = {"nodes": n, "robots": N, "target": target_name, "missions": len(data.length), "beliefs": name,
                       **info, "episodes": args.episodes, "mean_capture_time": round(mean, 2),
                       "ci95_halfwidth": round(half, 2), "minus_true_model": round(d_mean, 2),
                       "minus_true_model_ci95": round(d_half, 2)}  # fmt: skip
                rows.append(row)
                tv = f"TV {info['mean_row_tv_to_true']:.3f}" if "mean_row_tv_to_true" in info else ""
                print(f"n={n} {target_name:9s} {name:26s}{tv:12s} {mean:7.1f} ± {half:5.1f}   "
                      f"minus the true model's {d_mean:+7.1f} ± {d_half:5.1f}", flush=True)  # fmt: skip
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(
        json.dumps({"settings": {k: v for k, v in vars(args).items() if k != "json"}, "rows": rows}, indent=1) + "\n",
        encoding="utf-8",
    )
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()

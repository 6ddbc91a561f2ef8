"""How good a model the team's plan needs: FHPE-SA teams planning on models the fleet estimated by
EM from its own missions, against the model's error.

    python benchmarks/model_error.py --map office [--target lazy:0.6] [--missions 100 500 2000 10000] [--pseudo-counts 0 1]

Under the target --target (the paper's uniform walk, or lazy:STAY: stay with probability STAY, else
move to a uniformly chosen neighbour; its rows are not the uniform prior's), the protocol's CE-PG
team (N = 4) flies M missions alone (each robot on its own policy, as a fleet does before it
searches together); EM estimates (Gamma_hat, b0) from their records with Dirichlet pseudo-counts c
(transitions and starts alike; 1 is the training server's default, 0 maximum likelihood), for every
M of --missions and c of --pseudo-counts. For each model: the mean row TV of Gamma_hat to the
truth, the TV of b0, and the capture time of the team's FHPE-SA plan on it (links up) on the same
--episodes episodes as CE-PG alone and the fully informed FHPE-SA (true model), paired. Writes
results/coordination/model-error-<map>-<target>.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
from coordination import fleet_model  # benchmarks/coordination.py, beside this script

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, lazy_walk, uniform_walk
from shared.core.snapshot_format import read_snapshot
from shared.engine.evaluate import evaluate, mean_ci95
from shared.engine.linked_team import LinkedTeamSearcher
from shared.learning.team_snapshot import torch_weights
from shared.planners import make_baseline


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="office")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--target", default="lazy:0.6", help="uniform, or lazy:STAY")
    ap.add_argument("--episodes", type=int, default=400)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--missions", type=int, nargs="+", default=[100, 500, 2000, 10000])
    ap.add_argument("--pseudo-counts", type=float, nargs="+", default=[0.0, 1.0])
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--out", type=Path, default=Path("results/coordination"))
    args = ap.parse_args()
    graph, sensor, N, E = builtin_graph(args.map), Sensor(), args.robots, args.episodes
    truth = uniform_walk(graph) if args.target == "uniform" else lazy_walk(graph, float(args.target.split(":")[1]))
    snap_dir = args.results / "snapshots" / f"{args.map}-N{N}-beta0.5-400000-s0"
    snap = read_snapshot(snap_dir, graph, legacy=torch_weights)
    t_start = time.perf_counter()

    def fly(label: str, make, **extra) -> dict:
        t0 = time.perf_counter()
        ct = np.asarray(evaluate(graph, truth, sensor, N, make, episodes=E, seed=args.seed).capture_time, float)
        m, h = mean_ci95(ct)
        row = {"searcher": label, **extra, "mean_capture_time": round(m, 3), "ci95_halfwidth": round(h, 3)}
        row["wall_seconds"] = round(time.perf_counter() - t0, 1)
        print(f"{args.map} {args.target} {label} {extra}: {m:.2f} ± {h:.2f} ({row['wall_seconds']} s)", file=sys.stderr)
        return {**row, "capture_times": ct}

    rows = [
        fly("fhpe-sa fully informed", lambda s: make_baseline("fhpe-sa", graph, truth, sensor, N, seed=s)),
        fly("cepg alone", lambda s: LinkedTeamSearcher(snap, graph, N, s, None)),
    ]
    for M in args.missions:
        for c in args.pseudo_counts:
            model, tv, _ = fleet_model(snap_dir, graph, M, seed=1000 + M, truth=truth, pseudo_count=c)
            b0_tv = 0.5 * float(np.abs(model.b0 - truth.b0).sum())
            rows.append(
                fly(
                    "team fhpe-sa",
                    lambda s, model=model: LinkedTeamSearcher(snap, graph, N, s, "fhpe-sa", team_model=model),
                    fleet_missions=M,
                    pseudo_count=c,
                    gamma_row_tv=round(tv, 4),
                    b0_tv=round(b0_tv, 4),
                )
            )
    informed, alone = rows[0]["capture_times"], rows[1]["capture_times"]
    for r in rows:
        for name, base in (("cepg_alone", alone), ("fhpe_sa_informed", informed)):
            d, h = mean_ci95(r["capture_times"] - base)
            r[f"diff_to_{name}"], r[f"diff_to_{name}_ci95"] = round(d, 3), round(h, 3)
    record = {
        "map": args.map,
        "robots": N,
        "target": args.target,
        "episodes": E,
        "seed": args.seed,
        "team": snap_dir.name,
        "command": "python benchmarks/model_error.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "wall_seconds": round(time.perf_counter() - t_start, 1),
        "rows": [{k: v for k, v in r.items() if k != "capture_times"} for r in rows],
    }
    out = args.out / f"model-error-{args.map}-{args.target.replace(':', '')}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(
        "| searcher | fleet missions | pseudo-count | Gamma_hat row TV | b0 TV | capture time | vs CE-PG alone | vs FHPE-SA informed |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in record["rows"]:
        print(
            f"| {r['searcher']} | {r.get('fleet_missions', '—')} | {r.get('pseudo_count', '—')} "
            f"| {r.get('gamma_row_tv', '—')} | {r.get('b0_tv', '—')} "
            f"| {r['mean_capture_time']:.2f} ± {r['ci95_halfwidth']:.2f} "
            f"| {r['diff_to_cepg_alone']:+.2f} ± {r['diff_to_cepg_alone_ci95']:.2f} "
            f"| {r['diff_to_fhpe_sa_informed']:+.2f} ± {r['diff_to_fhpe_sa_informed_ci95']:.2f} |"
        )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

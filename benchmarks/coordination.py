"""Searching together against searching alone: a CE-PG team of the recorded protocol flown as
robot agents fly it (shared/core/team.py), every robot on its own policy, or on the team's
FHPE-SA plan over the collective belief, over links that lose or delay observation messages.

    python benchmarks/coordination.py --map office [--robots 4] [--episodes 300] [--missions 100 500 2000]

For one map and team size, with the protocol's CE-PG team (results/snapshots/<map>-N<N>-beta0.5-400000-s0):
1. the fleet's model: the team flies M missions (each robot on its own policy, as a fleet does
   before it searches together), their records are estimated by EM with the training server's
   priors (pseudo-counts 1 and 1), for each M of --missions; the row TV of Gamma_hat to the truth;
2. every searcher flies the same --episodes episodes (seed --seed: the target's paths do not
   depend on the robots), so each difference to CE-PG alone and to the fully informed FHPE-SA
   (true model, every robot's observations) is paired episode by episode: CE-PG alone; the team's
   plan on each fleet model, links up; on the largest model with each message lost with
   probability P (--losses), and delayed by K steps (--delays).
Writes results/coordination/<map>-N<N>.json (every row with mean, 95% CI, the paired
differences, the share of robot-steps flown on the team's plan, the machine) and prints a table.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.core.snapshot_format import read_snapshot
from shared.engine.estimate import collect_missions, em, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate, mean_ci95
from shared.engine.linked_team import LinkedTeamSearcher
from shared.learning.team_snapshot import PolicySearcher, load_snapshot, torch_weights
from shared.planners import make_baseline


def fleet_model(snap_dir: Path, graph, missions: int, seed: int):
    """(Gamma_hat, b0) by EM with the server's priors from ``missions`` missions the team flew alone."""
    snap = load_snapshot(snap_dir, graph)
    truth, sensor = uniform_walk(graph), Sensor()
    res = evaluate(
        graph,
        truth,
        sensor,
        snap.robots,
        lambda s: PolicySearcher(snap, graph, sensor, snap.robots, seed=s),
        episodes=missions,
        seed=seed,
        record=True,
    )
    data = collect_missions(((0, r) for r in episode_records(graph, res, sensor, mission_prefix="fleet")), graph)
    est = em(graph, data, init=uniform_walk(graph), max_iter=300, tol=1e-5, pseudo_count=1.0, b0_pseudo_count=1.0)
    return est.model, mean_row_tv(est.model, truth)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="office")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=300)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--missions", type=int, nargs="+", default=[100, 500, 2000])
    ap.add_argument("--losses", type=float, nargs="+", default=[0.1, 0.3, 0.5, 0.9, 1.0])
    ap.add_argument("--delays", type=int, nargs="+", default=[1, 3])
    ap.add_argument("--results", type=Path, default=Path("results"), help="where the protocol's snapshots are")
    ap.add_argument("--out", type=Path, default=Path("results/coordination"))
    args = ap.parse_args()
    graph, truth, sensor = builtin_graph(args.map), uniform_walk(builtin_graph(args.map)), Sensor()
    snap_dir = args.results / "snapshots" / f"{args.map}-N{args.robots}-beta0.5-400000-s0"
    snap = read_snapshot(snap_dir, graph, legacy=torch_weights)
    N, E = args.robots, args.episodes
    t_start = time.perf_counter()

    def fly(label: str, make, **extra) -> dict:
        t0 = time.perf_counter()
        res = evaluate(graph, truth, sensor, N, make, episodes=E, seed=args.seed)
        ct = np.asarray(res.capture_time, dtype=np.float64)
        m, h = mean_ci95(ct)
        row = {"searcher": label, **extra, "mean_capture_time": round(m, 3), "ci95_halfwidth": round(h, 3)}
        row["wall_seconds"] = round(time.perf_counter() - t0, 1)
        print(f"{args.map} N={N} {label} {extra}: {m:.2f} ± {h:.2f} ({row['wall_seconds']} s)", file=sys.stderr)
        return {**row, "capture_times": ct}

    def team(label: str, model, searcher="fhpe-sa", loss=0.0, delay=0, **extra) -> dict:
        counter = {"team": 0, "partial": 0, "own": 0}

        def make(s: int) -> LinkedTeamSearcher:
            return LinkedTeamSearcher(snap, graph, N, s, searcher, loss, delay, counter=counter, team_model=model)

        row = fly(label, make, link_loss=loss, link_delay=delay, **extra)
        flown = sum(counter.values())
        share = {k: round(v / flown, 4) if flown else None for k, v in counter.items()}
        return {**row, "share_complete": share["team"], "share_partial": share["partial"], "share_own": share["own"]}

    rows = [
        fly("fhpe-sa fully informed", lambda s: make_baseline("fhpe-sa", graph, truth, sensor, N, seed=s)),
        team("cepg alone", None, searcher=None),
    ]
    models = {}
    for M in args.missions:
        model, tv = fleet_model(snap_dir, graph, M, seed=1000 + M)
        models[M] = model
        rows.append(team("team fhpe-sa", model, fleet_missions=M, gamma_row_tv=round(tv, 4)))
    best = models[max(models)]
    for P in args.losses:
        rows.append(team("team fhpe-sa", best, loss=P, fleet_missions=max(models)))
    for K in args.delays:
        rows.append(team("team fhpe-sa", best, delay=K, fleet_missions=max(models)))
    alone, informed = rows[1]["capture_times"], rows[0]["capture_times"]
    for r in rows:
        for name, base in (("cepg_alone", alone), ("fhpe_sa_informed", informed)):
            d, h = mean_ci95(r["capture_times"] - base)
            r[f"diff_to_{name}"], r[f"diff_to_{name}_ci95"] = round(d, 3), round(h, 3)
    out = args.out / f"{args.map}-N{N}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "map": args.map,
        "robots": N,
        "episodes": E,
        "seed": args.seed,
        "team": snap_dir.name,
        "command": "python benchmarks/coordination.py " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "wall_seconds": round(time.perf_counter() - t_start, 1),
        "rows": [{k: v for k, v in r.items() if k != "capture_times"} for r in rows],
    }
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(
        "| searcher | fleet missions | link loss | delay | capture time | vs CE-PG alone | vs FHPE-SA informed | robot-steps complete / partial / own |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in record["rows"]:
        print(
            f"| {r['searcher']} | {r.get('fleet_missions', '—')} | {r.get('link_loss', '—')} | {r.get('link_delay', '—')} "
            f"| {r['mean_capture_time']:.2f} ± {r['ci95_halfwidth']:.2f} "
            f"| {r['diff_to_cepg_alone']:+.2f} ± {r['diff_to_cepg_alone_ci95']:.2f} "
            f"| {r['diff_to_fhpe_sa_informed']:+.2f} ± {r['diff_to_fhpe_sa_informed_ci95']:.2f} "
            f"| {r.get('share_complete', '—')} / {r.get('share_partial', '—')} / {r.get('share_own', '—')} |"
        )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()

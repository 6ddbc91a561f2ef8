"""Searching together against searching alone: the protocol's CE-PG teams flown as robot agents
fly them (shared/core/team.py), every robot on its own policy, or on the team's FHPE-SA plan over
the collective belief, over links that lose or delay observation messages.

    python benchmarks/coordination.py --map office [--robots 4] [--episodes 400] [--missions 100 500 2000 10000]

For one map and team size N, with the protocol's CE-PG team (results/snapshots/<map>-N<N>-beta0.5-400000-s0):
1. the fleet's model: the team flies M missions (each robot on its own policy, as a fleet does
   before it searches together), their records are estimated by EM with the training server's
   priors (pseudo-counts 1 and 1), for each M of --missions; the mean row TV of Gamma_hat to the
   truth, and the b0 mass on the target's true start nodes;
2. every searcher flies the same --episodes episodes (seed --seed: the target's paths do not
   depend on the robots), so each difference to CE-PG alone and to the fully informed FHPE-SA
   (true model, every robot's observations) is paired episode by episode: CE-PG alone; the best
   decentralised learners of the protocol alone (--learners); the team's plan on each fleet
   model, links up; on the largest model with each message lost with probability P (--losses),
   and delayed by K steps (--delays); with robot N withdrawn at step --withdraw-at (Fig. 12's
   setting, beside CE-PG alone withdrawn alike); with --fewer, the team flown by k = 1..N-1 of its
   robots (Fig. 13's setting) against the teams built for k, CE-PG alone and as a team;
3. CE-PG alone again on --policy-episodes episodes (its mean with the protocol's precision).
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
from coordination_tables import table  # benchmarks/coordination_tables.py, beside this script

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.core.snapshot_format import read_snapshot
from shared.engine.estimate import collect_missions, em, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate, mean_ci95
from shared.engine.linked_team import LinkedTeamSearcher
from shared.learning.team_snapshot import PolicySearcher, load_snapshot, torch_weights
from shared.planners import make_baseline


def fleet_model(snap_dir: Path, graph, missions: int, seed: int, truth=None, pseudo_count: float = 1.0):
    """(Gamma_hat, b0) by EM with the server's priors (``pseudo_count`` for both) from ``missions``
    missions the team flew alone under the target ``truth`` (default the uniform walk), its mean
    row TV to the truth, and b0's mass on the truth's start nodes."""
    snap = load_snapshot(snap_dir, graph)
    truth, sensor = truth or uniform_walk(graph), Sensor()
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
    est = em(
        graph,
        data,
        init=uniform_walk(graph),
        max_iter=300,
        tol=1e-5,
        pseudo_count=pseudo_count,
        b0_pseudo_count=pseudo_count,
    )
    b0_on_start = float(est.model.b0[truth.b0 > 0].sum())
    return est.model, mean_row_tv(est.model, truth), b0_on_start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="office")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=400, help="paired episodes of every searcher")
    ap.add_argument("--policy-episodes", type=int, default=1500, help="episodes of CE-PG alone's own row")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--missions", type=int, nargs="+", default=[100, 500, 2000, 10000])
    ap.add_argument("--losses", type=float, nargs="*", default=[0.1, 0.3, 0.5, 0.9, 1.0])
    ap.add_argument("--delays", type=int, nargs="*", default=[1, 3])
    ap.add_argument("--learners", nargs="*", default=["masac-300000-s0", "beta1.0-400000-s0"])
    ap.add_argument("--withdraw-at", type=int, default=5, help="step robot N is withdrawn at (0: no such rows)")
    ap.add_argument("--fewer", action="store_true", help="fly the team with k = 1..N-1 of its robots")
    ap.add_argument(
        "--merge",
        action="store_true",
        help="replace the rows this run measures in the map's existing record, keeping the others",
    )
    ap.add_argument("--results", type=Path, default=Path("results"), help="where the protocol's snapshots are")
    ap.add_argument("--out", type=Path, default=Path("results/coordination"))
    args = ap.parse_args()
    graph, truth, sensor = builtin_graph(args.map), uniform_walk(builtin_graph(args.map)), Sensor()
    N, E = args.robots, args.episodes

    def team_dir(k: int, kind: str = "beta0.5-400000-s0") -> Path:
        return args.results / "snapshots" / f"{args.map}-N{k}-{kind}"

    snaps = {k: read_snapshot(team_dir(k), graph, legacy=torch_weights) for k in range(1, N + 1)}
    t_start = time.perf_counter()

    def fly(label: str, make, robots: int = N, episodes: int = E, withdraw=None, **extra) -> dict:
        t0 = time.perf_counter()
        res = evaluate(graph, truth, sensor, robots, make, episodes=episodes, seed=args.seed, withdraw_at=withdraw)
        ct = np.asarray(res.capture_time, dtype=np.float64)
        m, h = mean_ci95(ct)
        row = {"searcher": label, "robots": robots, "episodes": episodes, **extra}
        row |= {"mean_capture_time": round(m, 3), "ci95_halfwidth": round(h, 3)}
        row["wall_seconds"] = round(time.perf_counter() - t0, 1)
        print(f"{args.map} N={robots} {label} {extra}: {m:.2f} ± {h:.2f} ({row['wall_seconds']} s)", file=sys.stderr)
        return {**row, "capture_times": ct}

    def team(label: str, model, searcher="fhpe-sa", loss=0.0, delay=0, snap=None, robots=N, **extra) -> dict:
        counter = {"team": 0, "partial": 0, "own": 0}
        snap = snap or snaps[N]

        def make(s: int) -> LinkedTeamSearcher:
            return LinkedTeamSearcher(snap, graph, robots, s, searcher, loss, delay, counter=counter, team_model=model)

        row = fly(label, make, robots=robots, link_loss=loss, link_delay=delay, **extra)
        flown = sum(counter.values())
        share = {k: round(v / flown, 4) if flown else None for k, v in counter.items()}
        return {**row, "share_complete": share["team"], "share_partial": share["partial"], "share_own": share["own"]}

    rows = [
        fly("fhpe-sa fully informed", lambda s: make_baseline("fhpe-sa", graph, truth, sensor, N, seed=s)),
        team("cepg alone", None, searcher=None),
    ]
    for kind in args.learners:
        if team_dir(N, kind).is_dir():
            learner = read_snapshot(team_dir(N, kind), graph, legacy=torch_weights)
            rows.append(team(f"{kind.split('-')[0]} alone", None, searcher=None, snap=learner))
    models = {}
    for M in args.missions:
        model, tv, b0_mass = fleet_model(team_dir(N), graph, M, seed=1000 + M)
        models[M] = model
        rows.append(
            team("team fhpe-sa", model, fleet_missions=M, gamma_row_tv=round(tv, 4), b0_on_start=round(b0_mass, 4))
        )
    best, most = models[max(models)], max(models)
    for P in args.losses:
        rows.append(team("team fhpe-sa", best, loss=P, fleet_missions=most))
    for K in args.delays:
        rows.append(team("team fhpe-sa", best, delay=K, fleet_missions=most))
    later: list[dict] = []  # rows not paired with the N-robot episodes
    if args.withdraw_at and N > 1:
        gone = [None] * (N - 1) + [args.withdraw_at]
        withdrawn = {"withdrawn": f"r{N}@t{args.withdraw_at}"}
        alone = fly("cepg alone", lambda s: LinkedTeamSearcher(snaps[N], graph, N, s, None), withdraw=gone, **withdrawn)

        def make_team(s: int) -> LinkedTeamSearcher:
            return LinkedTeamSearcher(snaps[N], graph, N, s, "fhpe-sa", team_model=best)

        together = fly("team fhpe-sa", make_team, withdraw=gone, fleet_missions=most, **withdrawn)
        later += _paired([alone, together], alone)
    if args.fewer:
        for k in range(1, N):
            group = [
                team("cepg alone", None, searcher=None, robots=k, trained_for=N),
                team("cepg alone", None, searcher=None, snap=snaps[k], robots=k, trained_for=k),
                team("team fhpe-sa", best, robots=k, trained_for=N, fleet_missions=most),
                team("team fhpe-sa", best, snap=snaps[k], robots=k, trained_for=k, fleet_missions=most),
            ]
            later += _paired(group, group[1])
    if args.policy_episodes > E:  # CE-PG alone on more episodes (not paired with the others)
        make_alone = lambda s: LinkedTeamSearcher(snaps[N], graph, N, s, None)  # noqa: E731
        later.append(fly("cepg alone", make_alone, episodes=args.policy_episodes, own_row=True))
    rows = _paired(rows, rows[1], informed=rows[0]) + later
    out = args.out / f"{args.map}-N{N}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    command = "python benchmarks/coordination.py " + " ".join(sys.argv[1:])
    kept = [r for r in rows if r is not rows[0] and r is not rows[1]] if args.merge else rows
    if args.merge:  # the measured rows replace their namesakes; the others stay as recorded
        old = json.loads(out.read_text())
        new = {_key(r): r for r in kept}
        merged = [new.pop(_key(r), r) for r in old["rows"]]
        rows = merged + list(new.values())
        commands = [*old.get("commands", [old["command"]]), command]
        t_start -= old["wall_seconds"]  # the record's wall time: every run's
    else:
        commands = [command]
    record = {
        "map": args.map,
        "robots": N,
        "episodes": E,
        "seed": args.seed,
        "team": team_dir(N).name,
        "command": commands[0],
        "commands": commands,
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "wall_seconds": round(time.perf_counter() - t_start, 1),
        "rows": [{k: v for k, v in r.items() if k != "capture_times"} for r in rows],
    }
    out.write_text(json.dumps(record, indent=1) + "\n")
    table(record)
    print(f"wrote {out}")


def _key(row: dict) -> tuple:
    """What a row measured: its searcher and setting."""
    return tuple(
        row.get(k)
        for k in (
            "searcher",
            "robots",
            "link_loss",
            "link_delay",
            "fleet_missions",
            "withdrawn",
            "trained_for",
            "own_row",
        )
    )


def _paired(rows: list[dict], alone: dict, informed: dict | None = None) -> list[dict]:
    """``rows`` with each one's paired difference to ``alone`` (and ``informed``): the same episodes."""
    for r in rows:
        for name, base in (("cepg_alone", alone), ("fhpe_sa_informed", informed)):
            if base is not None:
                d, h = mean_ci95(r["capture_times"] - base["capture_times"])
                r[f"diff_to_{name}"], r[f"diff_to_{name}_ci95"] = round(d, 3), round(h, 3)
    return rows


if __name__ == "__main__":
    main()

"""The best policy for a fleet, measured end to end: a simulated fleet of N robot-agent processes
(`mures fleet-sim`'s server, world and agents on loopback) started from the untrained policy,
--missions missions of records, then one `algorithm: "best"` training run over HTTP as an operator
starts it, then --after missions flown by what it published and, on the same mission seeds, by
the CE-PG team a `cepg` run trains from the same records (same seed, same EM, same warm start).

    python benchmarks/best_policy.py --map office [--robots 4] [--missions 200] [--after 200]
        [--candidates cepg pg masac mappo] [--budget-fraction 1.0] [--gate-episodes 1500]

The runs fly with team_searcher "none": each robot flies the trained policy on its own belief,
the method compared (a team's plan would hide it). Writes results/best_policy/<map>-N<N>.json
and prints what was published, every candidate's capture time on the run's gate (the held-out
missions' model), each team's training wall time (one core), the fleet's capture times after,
and the recorded protocol's figures for the same map and N (results/fig7) beside them.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.engine.evaluate import mean_ci95
from shared.tools.fleetsim import launch, wait_until

OUT = Path("results/best_policy")


def say(text: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {text}", file=sys.stderr, flush=True)


def fly(fleet: Any, robots: list[str], seeds: range) -> list[dict[str, Any]]:
    out = []
    for seed in seeds:
        m = fleet.fly(robots, seed=seed, timeout=300)
        ct = m["outcome"]["capture_time"]
        out.append(
            {
                "seed": seed,
                "capture_time": ct if ct is not None else m["params"]["max_steps"],
                "captured": ct is not None,
                "policy_version": (m["outcome"].get("policy_versions") or [None])[0],
            }
        )
    return out


def follow(fleet: Any, params: dict[str, Any]) -> dict[str, Any]:
    """A training run over HTTP, followed to its end with its progress printed."""
    run = fleet.api.post("/api/v1/training-runs", params)
    last = [""]

    def done() -> dict[str, Any] | None:
        r = fleet.api.get(f"/api/v1/training-runs/{run['id']}")
        p = r.get("progress") or {}
        line = p.get("message") or ""
        if p.get("phase") == "train" and p.get("total"):
            pct = int(10 * p.get("episodes", 0) / p["total"]) * 10
            line = f"{p.get('method')} for {p.get('robots')} robots: {pct} %"
        if line and line != last[0]:
            last[0] = line
            say(f"  {p.get('phase')}: {line}")
        return r if r["status"] not in ("queued", "running") else None

    return wait_until(done, 6 * 3600, f"training run {run['id']}", every=1.0)


def fig7(map_name: str, robots: int) -> dict[str, dict[str, float]]:
    rows = {}
    with open("results/fig7/fig7.csv", newline="") as f:
        for row in csv.DictReader(f):
            if row["map"] == map_name and int(row["robots"]) == robots:
                rows[row["method"]] = {"mean": float(row["mean_capture_time"]), "ci95": float(row["ci95_halfwidth"])}
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", choices=("office", "museum"), required=True)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--missions", type=int, default=200, help="missions of records before the run")
    ap.add_argument("--after", type=int, default=200, help="missions flown by each version after the run")
    ap.add_argument("--candidates", nargs="+", default=["cepg", "pg", "masac", "mappo"])
    ap.add_argument("--budget-fraction", type=float, default=1.0)
    ap.add_argument("--gate-episodes", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    graph = builtin_graph(args.map)
    target = uniform_walk(graph)  # the paper's target, as in fig7
    robots = [f"r{i + 1}" for i in range(args.robots)]
    t0 = time.perf_counter()
    path = OUT / f"{args.map}-N{args.robots}.json"
    out: dict[str, Any] = {
        "map": graph.name,
        "robots": args.robots,
        "missions_before": args.missions,
        "missions_after": args.after,
        "candidates": args.candidates,
        "budget_fraction": args.budget_fraction,
        "gate_episodes": args.gate_episodes,
        "seed": args.seed,
        "fig7": fig7(args.map, args.robots),
    }

    def save(**part: Any) -> None:  # after each phase: a run cut short keeps what it measured
        out.update(part, wall_seconds=round(time.perf_counter() - t0, 1))
        path.write_text(json.dumps(out, indent=1) + "\n")

    common = {
        "seed": args.seed,
        "gate_episodes": args.gate_episodes,
        "canary_pairs": 0,
        "team_searcher": "none",
        "budget_fraction": args.budget_fraction,
        "min_missions": 1,
    }
    keys = ("id", "status", "version", "error", "metrics")
    with tempfile.TemporaryDirectory(prefix="mures-best-") as workdir:
        fleet = launch(graph, ["--env", args.map], target, Sensor(), args.robots, Path(workdir), step_timeout=10.0)
        try:
            say(f"{args.map} N={args.robots}: flying {args.missions} missions of the untrained policy")
            save(before=fly(fleet, robots, range(args.missions)))
            say("a cepg run on the same records, kept beside the current version (promote false)")
            cepg = follow(fleet, {**common, "algorithm": "cepg", "promote": False, "gate": False})
            say(f"  {cepg['status']}: version {cepg['version']}")
            save(cepg_run={k: cepg[k] for k in keys})
            say(f"the best run: candidates {', '.join(args.candidates)}")
            best = follow(fleet, {**common, "algorithm": "best", "candidates": args.candidates})
            say(f"  {best['status']}: version {best['version']} ({(best.get('metrics') or {}).get('chosen')})")
            save(best_run={k: best[k] for k in keys})
            after_seeds = range(100_000, 100_000 + args.after)
            save(after_best=fly(fleet, robots, after_seeds))
            fleet.api.post("/api/v1/policies/current", {"version": cepg["version"]})
            save(after_cepg=fly(fleet, robots, after_seeds))
        finally:
            fleet.close()
    report(out)
    print(f"wrote {path}")


def report(out: dict[str, Any]) -> None:
    m = out["best_run"]["metrics"] or {}
    print(f"{out['map']} N={out['robots']}: best run {out['best_run']['status']}, published {m.get('chosen')}")
    print("| team | capture time on the gate (95% CI) | vs current | training episodes | wall s |")
    print("| --- | --- | --- | --- | --- |")
    for c in m.get("candidates", []):
        t = c.get("training") or {}
        vs = f"{c['paired_difference']:+.2f} ± {c['paired_ci95']:.2f}" if "paired_difference" in c else ""
        lo, hi = c["ci95"]
        print(
            f"| {c['method']} | {c['mean_capture_time']:.2f} ({lo:.2f}-{hi:.2f}) | {vs} "
            f"| {t.get('episodes', '')} | {t.get('wall_seconds') or ''} |"
        )
    published = (
        f"published {m.get('chosen')}" if out["best_run"]["status"] == "succeeded" else "current (none published)"
    )
    for name, key in ((published, "after_best"), ("cepg", "after_cepg")):
        mean, half = mean_ci95([r["capture_time"] for r in out[key]])
        print(f"fleet, {len(out[key])} missions after the run, {name}: {mean:.2f} ± {half:.2f}")
    diff, half = mean_ci95(
        [a["capture_time"] - b["capture_time"] for a, b in zip(out["after_best"], out["after_cepg"], strict=True)]
    )
    print(f"paired difference (after the best run) - cepg: {diff:+.2f} ± {half:.2f}")
    print(
        "fig7 (true model, 1500 episodes): "
        + ", ".join(f"{k} {v['mean']:.2f} ± {v['ci95']:.2f}" for k, v in out["fig7"].items())
    )


if __name__ == "__main__":
    main()

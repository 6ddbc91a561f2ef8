"""The general policy (shared/core/graph_policy.py, trained by `mures train-general`) on buildings
it never saw: the paper's maps against their own CE-PG teams, and generated floors of 100-1,000
nodes against greedy, random and FHPE-SA (true model, every observation), with its decision time.

    python benchmarks/general_policy.py [--policy DIR] [--parts maps,generated,withdrawals,decision]
                                        [--episodes 1500] [--generated-episodes 300] [--fhpe-episodes 10]
                                        [--json results/general_policy/general_policy.json]

maps: OFFICE and MUSEUM, N = 2-5, ``--episodes`` episodes with seed 1 (the protocol of results/fig7,
whose CE-PG teams were trained on each map and team size; their rows are read from
results/fig7/fig7.csv). The general policy and greedy fly with the true model, as greedy does in
fig7; "untrained" is the network before training (its skip connection alone: move toward the most
likely node), to show what training added.
generated: ``office_graph(n, seed=1)`` (the training pool uses seeds from 10,000), N = 2, 4, 8; every
searcher on the same episodes (seed 1: the same target walks), paired differences to greedy;
FHPE-SA on the first ``--fhpe-episodes`` of them (a third as many at 1,000 nodes).
withdrawals: N = 5 on OFFICE and MUSEUM with robots withdrawn at fixed steps, the schedules and
episodes of results/team_switching/<map>-N5-simulated.json (`benchmarks/team_switching.py
--simulated`): the general policy against that benchmark's per-map teams (switching, keeping the
5-robot team, the team built for the robots left).
decision: milliseconds one robot's numpy decision takes (``GeneralAgent.act``, one thread, three teammates) at
2,000 nodes, with the hop-distance table built once and row by row (cold).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from shared.core.graph import builtin_graph, office_graph
from shared.core.graph_policy import Distances, GeneralAgent
from shared.core.models import Sensor, uniform_walk
from shared.core.snapshot_format import load_general, save_general, shipped_general_path
from shared.engine.evaluate import evaluate, mean_ci95
from shared.learning.general import GeneralNet
from shared.registry import searcher_factory

ROOT = Path(__file__).resolve().parent.parent


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def run(graph, robots: int, name: str, episodes: int, seed: int = 1, withdraw_at: list | None = None) -> dict:
    target, sensor = uniform_walk(graph), Sensor()
    t0 = time.perf_counter()
    factory = searcher_factory(name, graph, target, sensor, robots)
    res = evaluate(graph, target, sensor, robots, factory, episodes, seed, withdraw_at=withdraw_at)
    s = res.summary()
    return {
        "searcher": name.split(":")[0],
        "episodes": episodes,
        "mean_capture_time": round(s["mean_capture_time"], 3),
        "ci95_halfwidth": round(s["ci95_halfwidth"], 3),
        "censored_fraction": s["censored_fraction"],
        "wall_seconds": round(time.perf_counter() - t0, 1),
        "_times": res.capture_time.astype(float),
    }


def paired(a: dict, b: dict) -> dict:
    """a - b on the same episodes: mean and 95 % half-width, and the ratio of the means."""
    m, h = mean_ci95(a["_times"] - b["_times"])
    return {
        "diff": round(m, 3),
        "diff_ci95": round(h, 3),
        "ratio": round(a["mean_capture_time"] / b["mean_capture_time"], 3),
    }


def fig7_rows() -> dict:
    out = {}
    with open(ROOT / "results" / "fig7" / "fig7.csv", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            out[(r["map"], int(r["robots"]), r["method"])] = (float(r["mean_capture_time"]), float(r["ci95_halfwidth"]))
    return out


def part_maps(policy: str, untrained: str, episodes: int) -> list[dict]:
    ref = fig7_rows()
    rows = []
    for name in ("office", "museum"):
        graph = builtin_graph(name)
        for N in (2, 3, 4, 5):
            gen = run(graph, N, f"general:{policy}", episodes)
            raw = run(graph, N, f"general:{untrained}", episodes)
            cepg, cepg_h = ref[(name, N, "cepg")]
            greedy, _greedy_h = ref[(name, N, "greedy")]
            row = {
                "map": name,
                "robots": N,
                "general": gen["mean_capture_time"],
                "general_ci95": gen["ci95_halfwidth"],
                "untrained": raw["mean_capture_time"],
                "untrained_ci95": raw["ci95_halfwidth"],
                "cepg_fig7": cepg,
                "cepg_fig7_ci95": cepg_h,
                "greedy_fig7": greedy,
                "ratio_to_cepg": round(gen["mean_capture_time"] / cepg, 3),
            }
            say(f"  {name} N={N}: general {gen['mean_capture_time']:.2f} ± {gen['ci95_halfwidth']:.2f}, untrained "
                f"{raw['mean_capture_time']:.2f}, fig7 CE-PG {cepg:.2f} ± {cepg_h:.2f}, greedy {greedy:.2f}")  # fmt: skip
            rows.append(row)
    return rows


def part_generated(policy: str, untrained: str, episodes: int, fhpe_episodes: int, sizes: list[int]) -> list[dict]:
    rows = []
    for n in sizes:
        graph = office_graph(n, seed=1)
        for N in (2, 4, 8):
            res = {
                "general": run(graph, N, f"general:{policy}", episodes),
                "untrained": run(graph, N, f"general:{untrained}", episodes),
                "greedy": run(graph, N, "greedy", episodes),
                "random": run(graph, N, "random", episodes),
            }
            row = {"nodes": n, "robots": N, "episodes": episodes}
            for k, r in res.items():
                row[k] = r["mean_capture_time"]
                row[f"{k}_ci95"] = r["ci95_halfwidth"]
                row[f"{k}_censored"] = r["censored_fraction"]
            row["general_vs_greedy"] = paired(res["general"], res["greedy"])
            row["general_vs_untrained"] = paired(res["general"], res["untrained"])
            k = fhpe_episodes if n < 1000 else max(1, fhpe_episodes // 3)  # its plans take long on 1,000 nodes
            if k:
                f = run(graph, N, "fhpe-sa", k)
                row["fhpe_sa"], row["fhpe_sa_ci95"], row["fhpe_sa_episodes"] = (
                    f["mean_capture_time"],
                    f["ci95_halfwidth"],
                    k,
                )
                row["fhpe_sa_wall_seconds"] = f["wall_seconds"]
            say(f"  n={n} N={N}: " + ", ".join(f"{k} {row[k]:.1f}" for k in ("general", "untrained", "greedy", "random"))
                + (f", fhpe-sa {row['fhpe_sa']:.1f} ({k} eps)" if k else "")
                + f"; general/greedy {row['general_vs_greedy']['ratio']:.2f}")  # fmt: skip
            rows.append(row)
    return rows


def part_withdrawals(policy: str, episodes: int) -> list[dict]:
    """Robots withdrawn mid-mission (results/team_switching/<map>-N5-simulated.json's schedules, the
    same episodes): the general policy's robots left keep the one network as a team of the robots
    left, against that benchmark's per-map teams switching to the team built for them, keeping the
    5-robot team, and the team built for k flown by k robots from the start."""
    rows = []
    for name in ("office", "museum"):
        ref = json.loads((ROOT / "results" / "team_switching" / f"{name}-N5-simulated.json").read_text())
        graph = builtin_graph(name)
        by_schedule: dict = {}
        for r in ref["rows"]:
            by_schedule.setdefault(tuple(r["withdrawn_at"]), {})[r["setting"].split(",")[0]] = r["mean_capture_time"]
        for schedule, settings in by_schedule.items():
            gen = run(graph, 5, f"general:{policy}", episodes, withdraw_at=list(schedule))
            left = sum(x is None for x in schedule)
            row = {
                "map": name,
                "withdrawn_at": list(schedule),
                "robots_left": left,
                "general": gen["mean_capture_time"],
                "general_ci95": gen["ci95_halfwidth"],
                "switching": settings.get("switching"),
                "five_robot_team": settings.get("the 5-robot team"),
                "built_for_k_from_the_start": settings.get(f"the team built for {left}"),
            }
            say(f"  {name}, {left} left: general {row['general']:.2f} ± {row['general_ci95']:.2f}, switching "
                f"{row['switching']}, keeping the 5-robot team {row['five_robot_team']}")  # fmt: skip
            rows.append(row)
    return rows


def part_decision(policy: str, nodes: int = 2000, decisions: int = 200) -> dict:
    torch.set_num_threads(1)
    graph = office_graph(nodes, seed=1)
    pol = load_general(policy)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    table = Distances(graph)
    build = time.perf_counter() - t0
    out = {"nodes": nodes, "edges": graph.m, "table_build_s": round(build, 2)}
    # row by row, cold: the path buildings above ALL_PAIRS_MAX take
    for label, dist in (("table", table), ("rows", Distances(graph, all_pairs=False))):
        agent = GeneralAgent(pol.weights, graph, 0, 4, distances=dist)
        p, times = graph.start, []
        for _ in range(decisions):
            b = rng.dirichlet(np.ones(graph.n) * 0.1)
            mates = rng.integers(0, graph.n, size=3)  # robot 0's three teammates, last heard there
            t = time.perf_counter()
            p = agent.act(p, b, mates)
            times.append(1000 * (time.perf_counter() - t))
        out[f"ms_{label}_mean"] = round(float(np.mean(times)), 2)
        out[f"ms_{label}_p95"] = round(float(np.percentile(times, 95)), 2)
    say(f"  decision at n={nodes}: {out}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--policy", default=str(shipped_general_path()))
    ap.add_argument("--parts", default="maps,generated,withdrawals,decision")
    ap.add_argument("--episodes", type=int, default=1500)
    ap.add_argument("--generated-episodes", type=int, default=300)
    ap.add_argument("--fhpe-episodes", type=int, default=10)
    ap.add_argument("--sizes", default="100,300,1000")
    ap.add_argument("--json", default=str(ROOT / "results" / "general_policy" / "general_policy.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    parts = args.parts.split(",")
    meta = load_general(args.policy).meta
    out: dict = {"policy": os.path.relpath(args.policy, ROOT), "training": meta.get("training", {}).get("command")}
    with tempfile.TemporaryDirectory() as tmp:
        torch.manual_seed(meta["training"]["config"]["seed"])
        untrained = save_general(Path(tmp) / "untrained", GeneralNet(meta["hidden"]).numpy_weights(), {})
        if "maps" in parts:
            say("OFFICE and MUSEUM (never trained on):")
            out["maps"] = part_maps(args.policy, str(untrained), args.episodes)
        if "generated" in parts:
            say("generated floors (never trained on):")
            sizes = [int(x) for x in args.sizes.split(",")]
            rows = part_generated(args.policy, str(untrained), args.generated_episodes, args.fhpe_episodes, sizes)
            out["generated"] = rows
        if "withdrawals" in parts:
            say("robots withdrawn mid-mission:")
            out["withdrawals"] = part_withdrawals(args.policy, args.episodes)
    if "decision" in parts:
        out["decision"] = part_decision(args.policy)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    say(f"wrote {args.json}")


if __name__ == "__main__":
    main()

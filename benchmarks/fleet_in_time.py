"""Today's fleet flown in the continuous world: robot-agent processes with a trained CE-PG team and
its team searcher (FHPE-SA), each move taking its travel time, on Nav2's and AWS's maps and on
generated office floors; capture time in seconds and how often the robots decide on the team's
plan, beside the same fleet in the step world.

    python benchmarks/fleet_in_time.py [--robots 2 4] [--missions 30] [--episodes 20000] [--seed 1]
                                       [--offices 2] [--maps depot,bookstore,...] [--workdir DIR]
                                       [--team-clock steps|seconds] [--step-limit 3] [--belief em|true]
                                       [--train-speed M_PER_S] [--em-pseudo-count C] [--general]
                                       [--detection node|custom] [--against BEFORE.json]
                                       [--json results/fleet_in_time/before.json]

Per map (imported with `mures map import`'s defaults) and team size N:
1. `mures train --graph G --robots N --episodes E --team-searcher fhpe-sa --seed 0 --belief B --out
   TEAM` (with --general none: TEAM is the shipped general policy, zero shot; B em: the model the team's beliefs and plan use learned by EM, as the trainer does by
   default; true: the true model, the uniform walk); with --train-speed S also `--speed S`: the team
   trained on the map's travel times (its model per tick, EM per tick), which the agents fly on
   the mission clock; with --em-pseudo-count C also `--em-pseudo-count C --em-b0-pseudo-count C`:
   EM with the Dirichlet prior a training server's retraining uses (C = 1 there);
2. `mures fleet-sim --graph G --world MAP.yaml --robots N --missions K --seed S --init-policy TEAM
   --json`: the agents in the continuous world (docs/continuous-world.md: 0.5 m/s, 4 m range in
   line of sight, a target walking at 0.5 m/s and dwelling 10 s on average);
   with --team-clock seconds, the agents match their teammates' observations by the mission clock
   (shared/core/timed_team.py) instead of by step index; each mission's step limit is --step-limit
   times n (a robot on the clock that stays spends a step a second), or with --step-limit 0
   fleet-sim's own limit: in the continuous world a time limit of 3 n moves of the median edge;
3. (--team-clock steps) the same fleet-sim without --world (the step world: every step together),
   for the share of decisions on the team's plan when steps are simultaneous;
4. `mures evaluate --graph G --world MAP.yaml --robots N --searcher sweep --episodes 500` (the
   batched continuous world; other missions than 2's, so a reference, not a paired comparison);
5. (--team-clock seconds) the team's plan given the true model and every observation at once (the
   batched world's ``fhpe-sa``) on 2's missions (each target walking by its mission's seed), so the
   fleet's capture times are paired with the plan's mission by mission.
With --detection custom every map is imported with `--sensor-range 4` (the world's range) and the
teams, the fleet and the plan of 5 take D(p) from that sensing table (what each node's robot sees
in line of sight) instead of {p}.
Prints a row per map and N and writes every run's summary as JSON. With --against, an earlier
run's JSON on the same seeds (so the same missions: the continuous world draws the target's path
from the mission seed alone), each row adds the paired difference of the capture times in seconds
(this run minus that one, mean and 95 % CI half-width over the missions).
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from shipped_maps import MAPS, imported, map_yaml  # benchmarks/shipped_maps.py, beside this script

from shared.core.models import Sensor
from shared.engine.evaluate import mean_ci95
from shared.floorplan.occupancy import read_map
from shared.tools.fleetsim import fleet_mission_seed
from shared.world.continuous import building, fly

RANGE_M = 4.0  # the world's sensor range, fleet-sim's and evaluate's default

MURES = [sys.executable, "-m", "shared.tools.cli"]


def run(*args: str) -> dict:
    """A `mures` command's --json output (or, without --json, nothing); exits on failure."""
    r = subprocess.run([*MURES, *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"mures {' '.join(args)} failed:\n{r.stderr[-2000:]}")
    return json.loads(r.stdout) if "--json" in args else {}


def maps(names: list[str] | None, offices: int, workdir: Path) -> list[tuple[str, Path]]:
    """(name, map YAML) of the shipped maps that are here and ``offices`` generated office floors."""
    out = [(name, path) for name, path in MAPS.items() if path.exists() and (not names or name in names)]
    for seed in range(1, offices + 1):
        name = f"office-{seed}"
        if not names or name in names:
            out.append((name, map_yaml(name, workdir)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--missions", type=int, default=30, help="fleet-sim missions per map and N (default 30)")
    ap.add_argument("--episodes", type=int, default=20_000, help="training episodes of each team (default 20000)")
    ap.add_argument("--seed", type=int, default=1, help="fleet-sim's seed (its missions' seeds follow from it)")
    ap.add_argument("--offices", type=int, default=2, help="generated office floors, seeds 1..K (default 2)")
    ap.add_argument("--maps", type=lambda s: s.split(","), default=None, help="only these (default: all here)")
    ap.add_argument("--workdir", help="keep graphs, teams and maps here (default: a temporary folder)")
    ap.add_argument("--team-clock", choices=("steps", "seconds"), default="steps")
    ap.add_argument("--belief", choices=("em", "true"), default="em", help="the teams' model: mures train --belief")
    ap.add_argument("--train-speed", type=float, metavar="M_PER_S", help="train the teams on travel times at it")
    ap.add_argument("--em-pseudo-count", type=float, metavar="C", help="train the teams with EM's prior of C")
    ap.add_argument(
        "--general",
        action="store_true",
        help="fly the shipped general policy (fleet-sim --init-policy general) instead of a team trained per map",
    )
    ap.add_argument(
        "--step-limit",
        type=int,
        default=3,
        metavar="K",
        help="each mission's step limit, K n (the server's: 3); 0: none given, so fleet-sim's default limits "
        "(in the continuous world a time limit of 3 n moves of the median edge)",
    )
    ap.add_argument(
        "--detection",
        choices=("node", "custom"),
        default="node",
        help="D(p) of the teams, the fleet and the plan: {p}, or the sensing table of each map imported with "
        "--sensor-range 4 (default node)",
    )
    ap.add_argument("--against", help="an earlier run's JSON on the same settings: paired differences")
    ap.add_argument("--json", default="results/fleet_in_time/before.json")
    args = ap.parse_args()
    tmp = None if args.workdir else tempfile.TemporaryDirectory(prefix="mures-fleet-in-time-")
    work = Path(args.workdir or tmp.name)  # type: ignore[union-attr]
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    earlier = (
        {(r["map"], r["robots"]): r for r in json.loads(Path(args.against).read_text())["rows"]} if args.against else {}
    )
    print(f"{'map':<12} {'n':>4} {'N':>2} {'capture s (in time)':>20} {'captured':>8} {'team plan':>9} "
          f"{'team plan (steps)':>17} {'sweep s':>14}")  # fmt: skip
    for name, yaml_path in maps(args.maps, args.offices, work):
        graph = imported(yaml_path, work, RANGE_M if args.detection == "custom" else None)
        world = None  # the batched world, for the plan on the fleet's missions (built once a map)
        graph_file = work / f"{yaml_path.stem}.json"
        for robots in args.robots:
            t0 = time.perf_counter()
            team = work / f"team-{name}-N{robots}" if args.belief == "em" else work / f"team-{name}-N{robots}-true"
            train_extra = [] if args.train_speed is None else ["--speed", str(args.train_speed)]
            if args.train_speed is not None:
                team = team.with_name(f"{team.name}-clock")
            if args.detection != "node":
                train_extra += ["--detection", args.detection]
                team = team.with_name(f"{team.name}-{args.detection}")
            if args.em_pseudo_count is not None:
                c = str(args.em_pseudo_count)
                train_extra += ["--em-pseudo-count", c, "--em-b0-pseudo-count", c]
                team = team.with_name(f"{team.name}-prior{args.em_pseudo_count:g}")
            if not args.general and not team.exists():
                run("train", "--graph", str(graph_file), "--robots", str(robots), "--episodes", str(args.episodes),
                    "--team-searcher", "fhpe-sa", "--seed", "0", "--belief", args.belief, "--out", str(team),
                    "--quiet", *train_extra)  # fmt: skip
            init = "general" if args.general else str(team)  # general: the server's own first version
            common = ["--graph", str(graph_file), "--robots", str(robots), "--missions", str(args.missions),
                      "--seed", str(args.seed), "--init-policy", init, "--detection", args.detection,
                      "--json"]  # fmt: skip
            if args.step_limit:
                common += ["--max-steps", str(args.step_limit * graph.n)]
            in_time = run("fleet-sim", *common, "--world", str(yaml_path), "--team-clock", args.team_clock)
            in_steps = run("fleet-sim", *common) if args.team_clock == "steps" else {"coordinated_share": None}
            sweep = run("evaluate", "--graph", str(graph_file), "--world", str(yaml_path), "--robots", str(robots),
                        "--searcher", "sweep", "--episodes", "500", "--seed", "0", "--json")  # fmt: skip
            row = {
                "map": name,
                "nodes": graph.n,
                "robots": robots,
                "missions": in_time["missions"],
                "mean_capture_time_s": in_time["mean_capture_time_s"],
                "ci95_halfwidth_s": in_time["ci95_halfwidth_s"],
                "captured": 1 - in_time["censored_fraction"],
                "team_plan_share": in_time["coordinated_share"],
                "team_plan_share_in_steps": in_steps["coordinated_share"],
                "mean_capture_time_steps_in_step_world": in_steps.get("mean_capture_time"),
                "sweep_mean_capture_time_s": sweep["mean_capture_time_s"],
                "sweep_ci95_halfwidth_s": sweep["ci95_halfwidth_s"],
                "wall_s": round(time.perf_counter() - t0, 1),
                "fleet_sim_in_time": {k: v for k, v in in_time.items() if k != "results"},
                "capture_time_s": [r["capture_time_s"] for r in in_time["results"]],
            }
            if args.team_clock == "seconds":  # the plan with the true model and every observation, same missions
                seeds = [fleet_mission_seed(args.seed, k) for k in range(in_time["missions"])]
                if world is None:
                    world = building(read_map(yaml_path), graph, RANGE_M)
                plan = fly(world, "fhpe-sa", robots, len(seeds), mission_seeds=seeds,
                           sensor=Sensor(detection=args.detection)).capture_s  # fmt: skip
                row["plan_capture_time_s"] = plan.tolist()
                row["plan_mean_capture_time_s"], row["plan_ci95_halfwidth_s"] = mean_ci95(plan)
                diff = np.subtract(row["capture_time_s"], plan)
                row["fleet_minus_plan_s"], row["fleet_minus_plan_ci95_s"] = mean_ci95(diff)
                row["fleet_over_plan"] = float(np.mean(row["capture_time_s"]) / max(np.mean(plan), 1e-9))
            before = earlier.get((name, robots))
            if before is not None and len(before["capture_time_s"]) == len(row["capture_time_s"]):
                diff = np.subtract(row["capture_time_s"], before["capture_time_s"])
                mean, half = mean_ci95(diff)
                row["paired_difference_s"], row["paired_ci95_s"] = mean, half
                row["relative_to_earlier"] = float(np.mean(row["capture_time_s"]) / np.mean(before["capture_time_s"]))
            rows.append(row)
            share = lambda x: "-" if x is None else f"{100 * x:.1f}%"  # noqa: E731
            print(
                f"{name:<12} {graph.n:>4} {robots:>2} {row['mean_capture_time_s']:>11.1f} ± {row['ci95_halfwidth_s']:>5.1f} s "
                f"{100 * row['captured']:>7.0f}% {share(row['team_plan_share']):>9} "
                f"{share(row['team_plan_share_in_steps']):>17} "
                f"{row['sweep_mean_capture_time_s']:>7.1f} ± {row['sweep_ci95_halfwidth_s']:>4.1f}"
                + (
                    f"   paired vs earlier {row['paired_difference_s']:+.1f} ± {row['paired_ci95_s']:.1f} s "
                    f"({100 * (row['relative_to_earlier'] - 1):+.0f}%)"
                    if "paired_difference_s" in row
                    else ""
                )
                + (
                    f"   plan {row['plan_mean_capture_time_s']:.1f} s, fleet - plan "
                    f"{row['fleet_minus_plan_s']:+.1f} ± {row['fleet_minus_plan_ci95_s']:.1f} s "
                    f"(fleet / plan {row['fleet_over_plan']:.2f})"
                    if "plan_mean_capture_time_s" in row
                    else ""
                ),
                flush=True,
            )
            out = Path(args.json)
            out.parent.mkdir(parents=True, exist_ok=True)
            settings = {k: v for k, v in vars(args).items() if k != "workdir"}
            out.write_text(json.dumps({"settings": settings, "machine": platform.machine(), "rows": rows}, indent=1))
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()

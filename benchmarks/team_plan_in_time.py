"""The team's plan on the mission clock given every observation at once (the continuous world's
``fhpe-sa`` searcher, shared/world/continuous.py), beside sweep: its walks taking time as the
paper's do (a move a step), with their detections discounted by when they happen, or with the
target also propagated over each move's travel time; and with D(p) = {p} or the sensing table of
what each node's robot sees (`mures map import --sensor-range`, --detection custom).

    python benchmarks/team_plan_in_time.py [--maps depot] [--robots 2 4] [--missions 200] [--seed 3]
                                           [--variants all|plan] [--offices K]
                                           [--json results/fleet_in_time/team_plan_in_time.json]

Maps: those of benchmarks/shipped_maps.py named by --maps ("all": every one here) and K generated
office floors (as benchmarks/fleet_in_time.py makes them), imported with default flags and
--sensor-range 4 (the world's range). --variants plan flies the plan alone (D(p) = {p}, discount by
move: what robot-agent --team-clock seconds flies), the reference the fleet on the clock is
measured against. Mean capture time in seconds with its 95 % CI half-width; all
variants on one seed (the same target draws until the robots' decisions part them).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from shipped_maps import MAPS, map_yaml  # benchmarks/shipped_maps.py, beside this script

from shared.core.graph import load_graph_file
from shared.core.models import Sensor
from shared.engine.evaluate import mean_ci95
from shared.floorplan.occupancy import read_map
from shared.tools.cli import main as mures_main
from shared.world.continuous import building, fly

PLAN = ("fhpe-sa", "node", "move")
VARIANTS = [  # (searcher, detection, how the plan's walks take time: shared/world/continuous.py PLAN_TIMES)
    ("sweep", "node", "move"),
    PLAN,
    ("fhpe-sa", "node", "discount"),
    ("fhpe-sa", "node", "travel"),
    ("fhpe-sa", "custom", "move"),
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--maps", type=lambda s: s.split(","), default=["depot"])
    ap.add_argument("--robots", type=int, nargs="+", default=[2, 4])
    ap.add_argument("--missions", type=int, default=200)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--variants", choices=("all", "plan"), default="all")
    ap.add_argument("--offices", type=int, default=0, help="generated office floors, seeds 1..K (default 0)")
    ap.add_argument("--json", default="results/fleet_in_time/team_plan_in_time.json")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        names = [n for n in MAPS if MAPS[n].exists()] if args.maps == ["all"] else args.maps
        names += [f"office-{k}" for k in range(1, args.offices + 1)]
        maps = [(name, map_yaml(name, Path(tmp))) for name in names]
        for name, yaml_path in maps:
            out = Path(tmp) / f"{name}.json"
            if mures_main(["map", "import", str(yaml_path), "--out", str(out), "--sensor-range", "4", "--quiet"]):
                raise SystemExit(f"importing {name} failed")
            world = building(read_map(yaml_path), load_graph_file(out), 4.0)
            for robots in args.robots:
                for searcher, detection, plan_time in VARIANTS if args.variants == "all" else [PLAN]:
                    f = fly(world, searcher, robots, args.missions, sensor=Sensor(detection=detection),
                            seed=args.seed, plan_time=plan_time)  # fmt: skip
                    mean, half = mean_ci95(f.capture_s)
                    rows.append({"map": name, "robots": robots, "searcher": searcher, "detection": detection,
                                 "plan_time": plan_time, "mean_capture_time_s": mean, "ci95_halfwidth_s": half,
                                 "captured": float(f.captured.mean()), "wall_s": round(f.wall_s, 1)})  # fmt: skip
                    print(f"{name:<10} N={robots} {searcher:<8} D(p) {detection:<6} plan time {plan_time:<8} "
                          f"{mean:6.1f} ± {half:4.1f} s  ({f.wall_s:.0f} s)", flush=True)  # fmt: skip
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"settings": vars(args), "rows": rows}, indent=1))


if __name__ == "__main__":
    main()

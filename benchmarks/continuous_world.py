"""Capture time in seconds in the continuous world (shared/world/continuous.py), per map, searcher
and team size, and how fast the world runs.

    python benchmarks/continuous_world.py [--missions 500] [--robots 2 4] [--range 4.0] [--seed 0]
                                          [--json results/continuous_world/continuous_world.json]

Maps: Nav2's depot and warehouse (examples/maps/nav2) and AWS's bookstore and small house
(shared/reference/maps/aws, when present), each imported with `mures map import`'s defaults. Robots
drive at 0.5 m/s and take 1 s to stay; the target walks at 0.5 m/s and dwells 10 s on average; a
robot sees 4 m in line of sight; eta_fn = eta_fp = 0; missions end at 1800 s. Searchers: random,
greedy (each robot's own belief on the step model, flown on its own clock) and sweep (a shortest
tour cut into one arc a robot). Prints the mean capture
time with its 95 % CI half-width over the missions, the share captured, the decisions a mission, and
the world's speed: ticks of 0.1 s a wall second, each advancing all --missions missions at once (a
mission captured early still ticks along until the slowest one ends).
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

from shipped_maps import shipped_graphs  # benchmarks/shipped_maps.py, beside this script

from shared.engine.evaluate import mean_ci95
from shared.floorplan.occupancy import read_map
from shared.world.continuous import SEARCHERS, building, fly


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--missions", type=int, default=500)
    p.add_argument("--robots", type=int, nargs="+", default=[2, 4])
    p.add_argument("--range", type=float, default=4.0, help="sensor range in metres")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="FILE")
    args = p.parse_args()
    rows = []
    print(
        f"map          n    N  searcher  capture time (s)   captured  decisions/mission  ticks/s ({args.missions} missions)"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for name, path, graph in shipped_graphs(Path(tmp)):
            t0 = time.perf_counter()
            world = building(read_map(path), graph, args.range)
            built_s = time.perf_counter() - t0
            for robots in args.robots:
                for searcher in SEARCHERS:
                    f = fly(world, searcher, robots, args.missions, seed=args.seed)
                    mean, half = mean_ci95(f.capture_s)
                    row = {
                        "map": name,
                        "nodes": world.graph.n,
                        "robots": robots,
                        "searcher": searcher,
                        "mean_capture_time_s": mean,
                        "ci95_halfwidth_s": half,
                        "captured": float(f.captured.mean()),
                        "decisions_per_mission": f.decisions / args.missions,
                        "ticks_per_s": f.ticks / f.wall_s,
                        "wall_s": f.wall_s,
                        "building_s": built_s,
                    }
                    rows.append(row)
                    print(
                        f"{name:<12} {world.graph.n:<4} {robots:<2} {searcher:<9} {mean:7.1f} ± {half:5.1f}    "
                        f"{100 * row['captured']:5.1f} %   {row['decisions_per_mission']:8.1f}          "
                        f"{row['ticks_per_s']:8.0f}"
                    )
    if args.json:
        out_file = Path(args.json)
        out_file.parent.mkdir(parents=True, exist_ok=True)
        out_file.write_text(
            json.dumps({"settings": vars(args), "machine": platform.machine(), "rows": rows}, indent=1) + "\n"
        )


if __name__ == "__main__":
    main()

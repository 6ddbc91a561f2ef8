"""The fleets of benchmarks/fleet_in_time.py beside random, greedy (each robot to the most likely
room on its own belief), sweep (the rooms in a shortest tour) and the team's plan given the true
model and every observation at once (FHPE-SA), all flown in the batched continuous world on the
fleet's own missions (each target walking by its mission seed), so every column is paired with the
fleets' capture times mission by mission.

    python benchmarks/baselines_in_time.py [--runs results/fleet_in_time/before-60-missions.json
                                            results/fleet_in_time/after-60-missions-each-on-arrival.json
                                            results/fleet_in_time/general-plan-each-on-arrival.json]
                                           [--detection node|custom] [--json results/fleet_in_time/baselines.json]

The runs are fleet_in_time.py JSON files on the same settings and seeds (the first is "before",
the others are compared with it). Maps are made as fleet_in_time.py makes them (imported with
default flags; office floors from their seeds). With --detection custom (fleet_in_time.py's) the
maps are imported with the world's sensor range as their sensing table, and the plan takes D(p)
from it (greedy's beliefs in the batched world stay on {p}: shared/world/continuous.py). Prints a row per map and N: each column's mean
capture time in seconds ± 95 % CI half-width over the missions, and each fleet's mean difference to
the first run and to every baseline, paired.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from shipped_maps import imported, map_yaml  # benchmarks/shipped_maps.py, beside this script

from shared.core.models import Sensor
from shared.engine.evaluate import mean_ci95
from shared.floorplan.occupancy import read_map
from shared.tools.fleetsim import fleet_mission_seed
from shared.world.continuous import SEARCHERS, building, fly

RANGE_M = 4.0  # the world's sensor range, as fleet_in_time.py flies it
ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--runs",
        nargs="+",
        default=[
            str(ROOT / "results" / "fleet_in_time" / "before-60-missions.json"),
            str(ROOT / "results" / "fleet_in_time" / "after-60-missions-each-on-arrival.json"),
            str(ROOT / "results" / "fleet_in_time" / "general-plan-each-on-arrival.json"),
        ],
    )
    ap.add_argument(
        "--detection", choices=("node", "custom"), default="node", help="the plan's D(p): {p} or the sensing table"
    )
    ap.add_argument("--json", default=str(ROOT / "results" / "fleet_in_time" / "baselines.json"))
    args = ap.parse_args()
    sensor = Sensor(detection=args.detection)
    sensor_range = RANGE_M if args.detection == "custom" else None
    runs = [json.loads(Path(p).read_text(encoding="utf-8")) for p in args.runs]
    names = [Path(p).stem for p in args.runs]
    seed = runs[0]["settings"]["seed"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        worlds: dict[str, object] = {}
        for first in runs[0]["rows"]:
            name, robots = first["map"], first["robots"]
            fleets = [next(r for r in run["rows"] if (r["map"], r["robots"]) == (name, robots)) for run in runs]
            missions = len(first["capture_time_s"])
            if any(len(f["capture_time_s"]) != missions for f in fleets):
                raise SystemExit(f"{name} N = {robots}: the runs flew different numbers of missions")
            if name not in worlds:
                yaml_path = map_yaml(name, Path(tmp))
                graph = imported(yaml_path, Path(tmp), sensor_range)
                worlds[name] = building(read_map(yaml_path), graph, RANGE_M)
            seeds = [fleet_mission_seed(seed, k) for k in range(missions)]
            row: dict[str, object] = {"map": name, "robots": robots, "missions": missions}
            times = {n: np.asarray(f["capture_time_s"]) for n, f in zip(names, fleets, strict=True)}
            for searcher in SEARCHERS:
                flown = fly(worlds[name], searcher, robots, missions, sensor=sensor, mission_seeds=seeds)  # type: ignore[arg-type]
                times[searcher] = flown.capture_s
            for column, x in times.items():
                mean, half = mean_ci95(x)
                row[column] = {"mean_s": mean, "ci95_s": half, "capture_time_s": [float(v) for v in x]}
            for fleet in names:
                for other in [*names[:1], *SEARCHERS]:
                    if other != fleet:
                        d, h = mean_ci95(times[fleet] - times[other])
                        row[f"{fleet}_minus_{other}"] = {"mean_s": d, "ci95_s": h}
            rows.append(row)
            cells = "  ".join(f"{c} {row[c]['mean_s']:.1f} ± {row[c]['ci95_s']:.1f}" for c in times)  # type: ignore[index]
            print(f"{name:<12} N={robots}  {cells}", flush=True)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    summary = {"runs": args.runs, "seed": seed, "detection": args.detection, "rows": rows}
    out.write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

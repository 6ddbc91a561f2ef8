"""A building the size of a real floor, from its map to a fleet flying it, with the general policy:
no training on the building at all.

    python benchmarks/general_building.py [--size-m 98] [--robots 4] [--missions 20] [--seed 0]
                                          [--json results/general_policy/building.json]

1. `office_building(seed, size_m)` (shared/floorplan/floors.py): wings of offices along corridors
   joined by a hall, furnished, with scan noise; a 98 m square is a 1,960 x 1,960 px map at 5 cm.
2. `mures map import` of it (default flags).
3. `mures fleet-sim --graph G --robots N --missions M`: a training server on the graph (its first
   version the general policy), the step world and N robot-agent processes; its progress is shown
   as it goes. The same missions' seeds are then flown by `mures evaluate --searcher greedy` and
   `--searcher general` in the batched engine for reference.
Prints each step's wall time and the capture times.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from shared.floorplan.floors import office_building

ROOT = Path(__file__).resolve().parent.parent


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


def mures(*args: str, show: bool = False) -> str:
    cmd = [sys.executable, "-m", "shared.tools.cli", *args]
    r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=None if show else subprocess.PIPE, text=True, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"mures {' '.join(args)} failed (exit {r.returncode}):\n{(r.stderr or '')[-2000:]}")
    return r.stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size-m", type=float, default=98.0)
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--missions", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=str(ROOT / "results" / "general_policy" / "building.json"))
    args = ap.parse_args()
    out: dict = {"size_m": args.size_m, "robots": args.robots, "missions": args.missions, "seed": args.seed}
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        floor = office_building(args.seed, args.size_m)
        yaml_path = floor.write(tmp, "building")
        out["map_px"] = list(floor.image.shape)
        graph = Path(tmp) / "building.json"
        mures("map", "import", str(yaml_path), "--out", str(graph), show=True)
        out["import_s"] = round(time.perf_counter() - t0, 1)
        g = json.loads(graph.read_text())
        out["nodes"], out["edges"] = len(g["nodes"]), len(g["edges"])
        say(f"imported {out['nodes']} nodes, {out['edges']} edges in {out['import_s']} s; flying the fleet")
        t0 = time.perf_counter()
        fleet = json.loads(mures("fleet-sim", "--graph", str(graph), "--robots", str(args.robots), "--missions",
                                 str(args.missions), "--seed", str(args.seed), "--json", show=True))  # fmt: skip
        out["fleet_sim_s"] = round(time.perf_counter() - t0, 1)
        out["fleet"] = {k: fleet[k] for k in ("mean_capture_time", "ci95", "censored_fraction", "policy_versions_used")}
        say(f"fleet-sim: {args.missions} missions in {out['fleet_sim_s']} s, capture time "
            f"{fleet['mean_capture_time']:.1f} steps (95% CI {fleet['ci95'][0]:.1f} .. {fleet['ci95'][1]:.1f})")  # fmt: skip
        for searcher in ("general", "greedy"):
            r = json.loads(mures("evaluate", "--graph", str(graph), "--robots", str(args.robots), "--searcher",
                                 searcher, "--episodes", "200", "--seed", "1", "--json"))  # fmt: skip
            out[searcher] = {k: r[k] for k in ("mean_capture_time", "ci95_halfwidth", "censored_fraction", "episodes")}
            say(f"evaluate {searcher}: {r['mean_capture_time']:.1f} ± {r['ci95_halfwidth']:.1f} steps (200 episodes)")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

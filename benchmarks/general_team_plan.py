"""A fleet's first version on a building it never saw, as a training server writes it
(``write_general_version``: the shipped general policy with FHPE-SA as its team searcher), flown
as robot agents fly it (`mures evaluate --searcher policy:DIR --team-searcher fhpe-sa`: each
robot's own decision code over a simulated network, links up), against the general policy alone
(each robot on its own belief, results/general_policy/general_policy.json) and the per-map CE-PG
teams of results/fig7, on the paper's maps.

    python benchmarks/general_team_plan.py [--maps office,museum] [--robots 2,3,4,5] [--episodes 500]
                                           [--json results/general_policy/team_plan.json]

Mean capture time in steps with its 95 % CI half-width, seed 1 (fig7's protocol; fewer episodes).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from shared.core.graph import builtin_graph
from shared.core.models import Sensor
from shared.core.snapshot_format import write_general_version

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--maps", default="office,museum")
    ap.add_argument("--robots", default="2,3,4,5")
    ap.add_argument("--episodes", type=int, default=500)
    ap.add_argument("--json", default=str(ROOT / "results" / "general_policy" / "team_plan.json"))
    args = ap.parse_args()
    with open(ROOT / "results" / "fig7" / "fig7.csv", encoding="utf-8") as f:
        fig7 = {(r["map"], int(r["robots"]), r["method"]): r for r in csv.DictReader(f)}
    zero = json.loads((ROOT / "results" / "general_policy" / "general_policy.json").read_text(encoding="utf-8"))
    alone = {(r["map"], r["robots"]): r for r in zero["maps"]}
    rows = []
    print(f"{'map':<7} {'N':>2} {'first version, team plan':>24} {'general alone':>14} {'per-map CE-PG':>14}")
    with tempfile.TemporaryDirectory() as tmp:
        for env in args.maps.split(","):
            graph = builtin_graph(env)
            for robots in (int(x) for x in args.robots.split(",")):
                snap = write_general_version(Path(tmp) / f"{env}-{robots}", graph, Sensor(), robots, 0, {})
                r = subprocess.run(
                    [sys.executable, "-m", "shared.tools.cli", "evaluate", "--env", env, "--robots", str(robots),
                     "--searcher", f"policy:{snap}", "--team-searcher", "fhpe-sa", "--episodes",
                     str(args.episodes), "--seed", "1", "--json"],
                    capture_output=True, text=True, cwd=ROOT,
                )  # fmt: skip
                if r.returncode != 0:
                    raise SystemExit(f"mures evaluate failed:\n{r.stderr[-2000:]}")
                team = json.loads(r.stdout)
                cepg = fig7[(env, robots, "cepg")]
                own = alone.get((env, robots)) or {}
                row = {
                    "map": env,
                    "robots": robots,
                    "episodes": args.episodes,
                    "team_plan": round(team["mean_capture_time"], 3),
                    "team_plan_ci95": round(team["ci95_halfwidth"], 3),
                    "general_alone": own.get("general"),
                    "cepg_fig7": float(cepg["mean_capture_time"]),
                    "cepg_fig7_ci95": float(cepg["ci95_halfwidth"]),
                }
                rows.append(row)
                print(
                    f"{env:<7} {robots:>2} {row['team_plan']:>15.2f} ± {row['team_plan_ci95']:.2f} "
                    f"{row['general_alone'] or float('nan'):>14.2f} {row['cepg_fig7']:>8.2f} ± {row['cepg_fig7_ci95']:.2f}",
                    flush=True,
                )
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"seed": 1, "rows": rows}, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

"""The real fleet searching together: `mures fleet-sim` on MUSEUM with N = 4 robot-agent processes,
started untrained, retrained once over HTTP after 100 missions (the retrain decides whether its
version flies as a team), then flown with links up and, on the same mission seeds, with every
observation message dropped (robot-agent --link-loss 1).

    python benchmarks/coordination_fleet.py [--missions 340] [--reuse]

Writes results/coordination/fleet-sim-museum-N4-loss{0,1}.json (fleet-sim's --json output; with
--reuse, reads them instead of flying) and prints, over the missions both runs flew with the
retrained version after its trial, each setting's capture time, their paired difference, and the
share of robot-steps flown on the team's plan.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from shared.engine.evaluate import mean_ci95

OUT = Path("results/coordination")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--missions", type=int, default=340, help="100 before the retrain, 40 of trial, 200 after")
    ap.add_argument("--reuse", action="store_true", help="read the recorded runs instead of flying")
    args = ap.parse_args()
    runs = {}
    for loss in (0, 1):
        path = OUT / f"fleet-sim-museum-N4-loss{loss}.json"
        if not args.reuse:
            argv = [
                str(Path(sys.executable).with_name("mures")),
                "fleet-sim",
                "--env",
                "museum",
                "--robots",
                "4",
                "--missions",
                str(args.missions),
            ]
            argv += ["--retrain-every", "100", "--retrains", "1", "--retrain-episodes", "30000", "--seed", "0"]
            argv += ["--link-loss", str(loss), "--json"]
            print(" ".join(argv), file=sys.stderr, flush=True)
            path.write_text(subprocess.run(argv, check=True, capture_output=True, text=True).stdout)
        runs[loss] = json.loads(path.read_text())
    up, down = runs[0]["results"], runs[1]["results"]
    trial_end = max(k for k, r in enumerate(up) if r["policy_version"] == 1) + 1
    both = [k for k in range(trial_end, len(up)) if up[k]["policy_version"] == down[k]["policy_version"] == 2]
    print(f"{len(both)} missions flown by version 2 in both runs after its trial (missions {both[0]}-{both[-1]})")
    print("| links | capture time | robot-steps on the team's plan | not captured |")
    print("| --- | --- | --- | --- |")
    times = {}
    for loss, res in ((0, up), (1, down)):
        ct = np.array([res[k]["capture_time"] for k in both], dtype=np.float64)
        team = sum(res[k]["team_steps"] for k in both)
        own = sum(res[k]["own_steps"] for k in both)
        times[loss] = ct
        m, h = mean_ci95(ct)
        lost = sum(not res[k]["captured"] for k in both)
        print(
            f"| {'up' if loss == 0 else 'down (all lost)'} | {m:.2f} ± {h:.2f} | {team / (team + own):.3f} | {lost} |"
        )
    d, h = mean_ci95(times[0] - times[1])
    print(f"paired difference, links up - down: {d:+.2f} ± {h:.2f} steps")
    for loss in (0, 1):
        team = runs[loss]["training_runs"][0]["metrics"]["team"]
        print(
            f"loss {loss}: the retrain chose {team['team_searcher']} (team {team['team_mean_capture_time']} vs alone "
            f"{team['alone_mean_capture_time']}, paired {team['paired_difference']:+} ± {team['paired_ci95']})"
        )


if __name__ == "__main__":
    main()

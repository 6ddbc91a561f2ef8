"""The general policy fine-tuned on a paper map for a fixed time, against that map's own CE-PG team
of results/fig7 (trained from scratch, 4x10^5 episodes) on the same protocol (1500 episodes, seed 1).

    python benchmarks/general_finetune.py [--maps office,museum] [--robots 4] [--minutes 10]
                                          [--beliefs em,true] [--json results/general_policy/finetune-node-bias.json]

For each map, N and belief: `mures train --env MAP --robots N --init general --episodes E --seed 0
[--belief true]` with a fine-tune's defaults (shared/learning/config.py ``fine_tune_defaults``, and
node_bias learned at the trainer's default rate; E is
what ``--minutes`` buys at the rate a short probe run measures on this machine). ``em``: EM in the
loop, the robots' beliefs starting on the uniform walk, as the fig7 teams learned theirs (from I);
``true``: the target's model known, which is what a training server's retraining does once its EM
has fitted the fleet's records. Then `mures evaluate --searcher policy:DIR` (the snapshot's own
model) and `--searcher general` (the true model) on the same episodes. Prints the capture times
and the fine-tune's wall time.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
import time
from itertools import product
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def mures(*args: str) -> str:
    r = subprocess.run([sys.executable, "-m", "shared.tools.cli", *args], capture_output=True, text=True, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"mures {' '.join(args)} failed:\n{r.stderr[-2000:]}")
    return r.stdout


def evaluate(env: str, robots: int, searcher: str) -> dict:
    out = mures("evaluate", "--env", env, "--robots", str(robots), "--searcher", searcher, "--episodes", "1500",
                "--seed", "1", "--json")  # fmt: skip
    return json.loads(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--maps", default="office,museum")
    ap.add_argument("--robots", default="4")
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--beliefs", default="em,true")
    ap.add_argument("--json", default=str(ROOT / "results" / "general_policy" / "finetune-node-bias.json"))
    args = ap.parse_args()
    fig7 = {}
    with open(ROOT / "results" / "fig7" / "fig7.csv", encoding="utf-8") as f:
        for r in csv.DictReader(f):
            fig7[(r["map"], int(r["robots"]), r["method"])] = (
                float(r["mean_capture_time"]),
                float(r["ci95_halfwidth"]),
            )
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        settings = product(args.maps.split(","), [int(x) for x in args.robots.split(",")], args.beliefs.split(","))
        for env, N, belief in settings:  # one fine-tune per map, team size and belief
            probe = Path(tmp) / f"probe-{env}-{N}-{belief}"
            t0 = time.perf_counter()
            mures("train", "--env", env, "--robots", str(N), "--init", "general", "--episodes", "4096",
                  "--belief", belief, "--seed", "0", "--quiet", "--out", str(probe))  # fmt: skip
            trained = json.loads((probe / "policy.json").read_text(encoding="utf-8"))["summary"]
            start_up = time.perf_counter() - t0 - trained["wall_seconds"]
            rate = trained["episodes"] / trained["wall_seconds"]  # the training loop's own rate
            episodes = int(rate * (args.minutes * 60 - start_up) * 0.8) // 256 * 256  # 20 % left for EM and load
            out = Path(tmp) / f"{env}-{N}-{belief}"
            t0 = time.perf_counter()
            mures("train", "--env", env, "--robots", str(N), "--init", "general", "--episodes", str(episodes),
                  "--belief", belief, "--seed", "0", "--quiet", "--out", str(out))  # fmt: skip
            wall = time.perf_counter() - t0
            tuned = evaluate(env, N, f"policy:{out}")
            zero = evaluate(env, N, "general")
            cepg, cepg_h = fig7[(env, N, "cepg")]
            row = {
                "map": env,
                "robots": N,
                "belief": belief,
                "finetune_episodes": episodes,
                "finetune_wall_s": round(wall, 1),
                "finetuned": round(tuned["mean_capture_time"], 3),
                "finetuned_ci95": round(tuned["ci95_halfwidth"], 3),
                "zero_shot": round(zero["mean_capture_time"], 3),
                "zero_shot_ci95": round(zero["ci95_halfwidth"], 3),
                "cepg_fig7": cepg,
                "cepg_fig7_ci95": cepg_h,
            }
            print(f"{env} N={N} ({belief} beliefs): fine-tuned {row['finetuned']:.2f} ± {row['finetuned_ci95']:.2f} "
                  f"({episodes:,} episodes, {wall:.0f} s), zero-shot {row['zero_shot']:.2f}, "
                  f"fig7 CE-PG {cepg:.2f} ± {cepg_h:.2f}", flush=True)  # fmt: skip
            rows.append(row)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"minutes": args.minutes, "rows": rows}, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

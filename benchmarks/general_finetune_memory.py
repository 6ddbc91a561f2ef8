"""What a fine-tune of the general policy holds on a large building: peak memory and time of
`mures train --init general` on generated office floors, with the fine-tune's defaults
(shared/learning/config.py ``fine_tune_defaults``: a batch of 24,000 / n episodes, EM on
128,000 / n missions, Gamma_hat kept on its entries above 512 nodes).

    python benchmarks/general_finetune_memory.py [--sizes 300,1000] [--robots 4] [--episodes 480]
                                                 [--em-first 96] [--json results/general_policy/finetune_memory.json]

Each size is one `mures train --graph office<n>.json --robots N --init general --episodes E
--em-first F` in a process of its own (``--em-first`` below ``--episodes``, so that the run
includes an EM update on its own missions, which the default 8,192 would put past a short run),
and with ``--beliefs em,true`` the same run with the true model (`--belief true`, no EM) beside
it; the peak is that process's maximum resident set size (wait4's, the process's own). Prints a
line per run: peak GB, wall seconds, the training batches' mean capture time before and after the
first EM update (at the same episode for the true-model run) and the EM update's passes and
distance to the true walk.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from itertools import product
from pathlib import Path

import numpy as np

from shared.core.graph import office_graph

ROOT = Path(__file__).resolve().parent.parent


def peak_of_child(cmd: list[str]) -> tuple[float, float]:
    """Run ``cmd`` as a child process (fork, then exec: the child is the command itself) and return
    its peak resident set size in GB (wait4's ru_maxrss, that process's own) and its wall time in s."""
    t0 = time.perf_counter()
    pid = os.fork()
    if pid == 0:
        os.chdir(ROOT)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.execv(cmd[0], cmd)
    _pid, status, usage = os.wait4(pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(cmd)} failed (exit {os.waitstatus_to_exitcode(status)})")
    return usage.ru_maxrss / 1024**2, time.perf_counter() - t0  # ru_maxrss is in kB on Linux


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="300,1000")
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=480)
    ap.add_argument("--em-first", type=int, default=96)
    ap.add_argument("--beliefs", default="em,true")
    ap.add_argument("--json", default=str(ROOT / "results" / "general_policy" / "finetune_memory.json"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n, belief in product([int(x) for x in args.sizes.split(",")], args.beliefs.split(",")):
            graph = Path(tmp) / f"office{n}.json"
            graph.write_text(json.dumps(office_graph(n, seed=1).to_json()), encoding="utf-8")
            out = Path(tmp) / f"ft{n}-{belief}"
            cmd = [sys.executable, "-m", "shared.tools.cli", "train", "--graph", str(graph), "--robots",
                   str(args.robots), "--init", "general", "--episodes", str(args.episodes), "--em-first",
                   str(args.em_first), "--belief", belief, "--quiet", "--out", str(out)]  # fmt: skip
            peak_gb, wall = peak_of_child(cmd)
            snapshot = json.loads((out / "policy.json").read_text(encoding="utf-8"))
            summary, training = snapshot["summary"], snapshot["training"]
            em = summary["em_updates"][0] if summary["em_updates"] else {}
            curve = [(p["episodes"], p["mean_capture_time"]) for p in summary["learning_curve"]]
            split = em.get("episodes", args.em_first)  # where EM updated the beliefs (or would have)
            before = [ct for e, ct in curve if e <= split]
            after = [ct for e, ct in curve if e > split]
            row = {
                "nodes": n,
                "robots": args.robots,
                "belief": belief,
                "episodes": summary["episodes"],
                "batch": training["batch"],
                "em_missions": training["em_missions"] if belief == "em" else None,
                "peak_gb": round(peak_gb, 2),
                "wall_s": round(wall, 1),
                "capture_time_before_em": round(float(np.mean(before)), 1) if before else None,
                "capture_time_after_em": round(float(np.mean(after)), 1) if after else None,
                "em_passes": em.get("iterations"),
                "em_seconds": em.get("seconds"),
                "em_mean_row_tv_to_true": em.get("mean_row_tv_to_true"),
            }
            print(f"n={n} N={args.robots} ({belief} beliefs): peak {row['peak_gb']:.2f} GB, {row['wall_s']:.0f} s for "
                  f"{row['episodes']} episodes (batch {row['batch']}); training batches' capture time "
                  f"{row['capture_time_before_em']} up to episode {split}, {row['capture_time_after_em']} after"
                  + (f"; EM on {row['em_missions']} missions: {row['em_passes']} passes in {row['em_seconds']} s, "
                     f"mean row TV to the true walk {row['em_mean_row_tv_to_true']}" if em else ""),
                  flush=True)  # fmt: skip
            rows.append(row)
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps({"rows": rows}, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()

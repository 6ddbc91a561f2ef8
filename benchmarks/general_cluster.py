"""The general policy's training spread over Dask workers, against one process: the same
`mures train-general` run (a shortened recipe, --floors-per-update K) in this process and on local
clusters of 1, 2, ... one-thread workers; wall time of the imitation phase and of the CE-PG updates,
the speed-up over one process, and whether the weights came out the same.

    python benchmarks/general_cluster.py [--episodes 12000] [--floors-per-update 2] [--workers 1 2]
                                         [--pool 16] [--json results/general_policy/cluster.json]

Run it with nothing else on the machine: k workers need k idle cores (and the training process one
more, mostly waiting). Everything runs with one torch thread, as `mures train-general` does by
default.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from shared.core.snapshot_format import load_general  # noqa: E402
from shared.learning.general import GeneralConfig, train_general  # noqa: E402
from shared.tools.runner import local_dask_cluster  # noqa: E402


def _run(cfg: GeneralConfig, out: Path, scheduler: str | None) -> dict:
    marks: dict[str, float] = {}
    t0 = time.perf_counter()

    def say(line: str) -> None:  # the imitation phase ends with its last epoch's line
        if line.startswith("imitation: epoch"):
            marks["imitation"] = time.perf_counter() - t0

    summary = train_general(cfg, out, say=say, scheduler=scheduler)
    wall = time.perf_counter() - t0
    return {
        "wall_seconds": round(wall, 1),
        "imitation_seconds": round(marks.get("imitation", 0.0), 1),
        "updates_seconds": round(wall - marks.get("imitation", 0.0), 1),
        "episodes": summary["episodes"],
        "updates": summary["updates"],
        "final_capture_time_per_node": summary["learning_curve"][-1]["capture_time_per_node"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=12_000)
    ap.add_argument("--floors-per-update", type=int, default=2)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--pool", type=int, default=16)
    ap.add_argument("--imitation-episodes", type=int, default=16)
    ap.add_argument("--json", help="write the figures here")
    a = ap.parse_args()
    torch.set_num_threads(1)
    cfg = GeneralConfig(
        episodes=a.episodes, pool=a.pool, floors_per_update=a.floors_per_update,
        imitation_episodes=a.imitation_episodes, checkpoint_every=1e9,
    )  # fmt: skip
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        base = _run(cfg, work / "here", None)
        runs.append({"where": "one process", "workers": 0, **base, "same_weights": True})
        reference = load_general(work / "here").weights
        for k in a.workers:
            (work / f"cluster-{k}").mkdir()
            with local_dask_cluster(k, work / f"cluster-{k}", ROOT) as address:
                row = _run(cfg, work / f"dask-{k}", address)
            weights = load_general(work / f"dask-{k}").weights
            same = all(np.array_equal(reference[name], weights[name]) for name in reference)
            runs.append({"where": f"local Dask cluster of {k}", "workers": k, **row, "same_weights": same})
        for r in runs:
            print(
                f"{r['where']:<26} {r['wall_seconds']:7.1f} s (imitation {r['imitation_seconds']:6.1f} s, "
                f"updates {r['updates_seconds']:6.1f} s)  speed-up {base['wall_seconds'] / r['wall_seconds']:.2f} "
                f"(updates {base['updates_seconds'] / r['updates_seconds']:.2f})  "
                f"weights {'identical' if r['same_weights'] else 'DIFFER'}",
                flush=True,
            )
    if a.json:
        record = {"settings": vars(a) | {"config": cfg.__dict__}, "machine": platform.machine(), "runs": runs}
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(record, indent=1) + "\n")
    if not all(r["same_weights"] for r in runs):
        sys.exit("the weights differ between one process and the cluster")


if __name__ == "__main__":
    main()

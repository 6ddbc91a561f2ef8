"""How an experiment scales over Dask workers: the same run on clusters of 1, 2, ... workers.

Run: python benchmarks/bench_cluster.py [--experiment fig6] [--train-episodes 20000] [--maps office]
                                        [--robots 2,4] [--workers 1 2] [--out results/cluster.json]

For each worker count k it starts a Dask scheduler and k one-thread workers on loopback (the
`dask scheduler` / `dask worker` commands, as on a real cluster), runs `mures experiment` on it
from an empty results directory (every team trained and every cell evaluated as a task), and
prints the wall time, the speed-up over one worker and the efficiency (speed-up / k). It checks
that every k gave the same rows. Run it with nothing else on the machine: k workers need k idle
cores. The whole protocol's time on a cluster follows from the one-worker time of its jobs and
this measured efficiency, not from an assumed linear scaling.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from shared.tools import experiments  # noqa: E402
from shared.tools.runner import local_dask_cluster  # noqa: E402


def _rows(path: Path) -> list[dict]:
    rows = json.loads(path.read_text())["rows"]
    return [{k: v for k, v in r.items() if k not in ("wall_seconds", "decision_ms")} for r in rows]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--experiment", default="fig6")
    ap.add_argument("--train-episodes", type=int, default=20_000)
    ap.add_argument("--maps", default="office")
    ap.add_argument("--robots", default="2,4")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", help="write the figures here as JSON")
    a = ap.parse_args()
    maps = tuple(a.maps.split(","))
    robots = tuple(int(x) for x in a.robots.split(","))
    runs = []
    reference = None
    for k in a.workers:
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            with local_dask_cluster(k, work, ROOT) as address:
                t0 = time.perf_counter()
                out = experiments.run(
                    a.experiment,
                    work / "results",
                    quick=False,
                    train_episodes=a.train_episodes,
                    scheduler=address,
                    maps=maps,
                    robots=robots,
                )
                wall = time.perf_counter() - t0
            rows = _rows(out / f"{a.experiment}.json")
            jobs = len(list((work / "results" / "snapshots").iterdir())) + len(
                list((work / "results" / "cells").glob("*.json"))
            )
        same = reference is None or rows == reference
        reference = reference or rows
        runs.append({"workers": k, "wall_seconds": round(wall, 1), "jobs": jobs, "same_rows": same})
        base = runs[0]["wall_seconds"] * runs[0]["workers"]
        speedup = base / wall
        print(
            f"{a.experiment} ({a.train_episodes:,} training episodes per team, maps {','.join(maps)}, "
            f"N {a.robots}): {k} worker{'s' if k > 1 else ''}: {wall:.1f} s for {jobs} jobs, speed-up "
            f"{speedup:.2f} over one worker, efficiency {speedup / k:.2f}, rows {'identical' if same else 'DIFFER'}",
            flush=True,
        )
    if a.out:
        record = {"experiment": a.experiment, "train_episodes": a.train_episodes, "maps": list(maps)}
        record |= {"robots": list(robots), "runs": runs, "machine": experiments.machine()}
        Path(a.out).write_text(json.dumps(record, indent=1) + "\n")
    if not all(r["same_rows"] for r in runs):
        sys.exit("the rows differ between worker counts")


if __name__ == "__main__":
    main()

"""The fleet's speed on loopback: the lockstep mission step of a simulated fleet and each agent's
decision step inside the running agent process, and the agents' resident memory.

    python benchmarks/bench_fleet.py [--robots 5] [--missions 100] [--env museum]

Prints the median and p90 of the lockstep period (time between consecutive steps of a mission,
measured by the simulated world: every agent's decision, move and query round trip) and of the
agents' decision step (belief update + policy + draw, from their telemetry).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.core.wire import telemetry_key, zenoh_config
from shared.tools.fleetsim import agent_rss_mb, launch


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--missions", type=int, default=100)
    ap.add_argument("--env", default="museum")
    a = ap.parse_args()
    graph = builtin_graph(a.env)
    ids = [f"r{i + 1}" for i in range(a.robots)]
    decide: list[float] = []
    lock = threading.Lock()

    def on_tel(sample: zenoh.Sample) -> None:
        with lock:
            decide.append(json.loads(sample.payload.to_bytes())["decide_us"])

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        fleet = launch(
            graph, ["--env", a.env], uniform_walk(graph), Sensor(), a.robots, Path(tmp), agent_extra=["--telemetry"]
        )
        try:
            print(f"fleet of {a.robots} agents on {graph.name} up in {time.perf_counter() - t0:.1f} s")
            with zenoh.open(zenoh_config("client", connect=[fleet.zenoh_endpoint])) as s:
                sub = s.declare_subscriber(telemetry_key("default", "*"), on_tel)
                t1 = time.perf_counter()
                steps = 0
                for k in range(a.missions):
                    m = fleet.fly(ids, seed=k)
                    steps += m["outcome"]["steps"] or m["params"]["max_steps"]
                wall = time.perf_counter() - t1
                time.sleep(0.5)
                sub.undeclare()
            rss = {r: agent_rss_mb(p.pid) for r, p in fleet.agents.items()}
            torch_mapped = [r for r, p in fleet.agents.items() if "libtorch" in Path(f"/proc/{p.pid}/maps").read_text()]
            period = np.asarray(fleet.world.step_intervals) * 1e3
            wait = np.asarray(fleet.world.step_seconds) * 1e3
        finally:
            fleet.close()
    d = np.asarray(decide)
    print(
        f"{a.missions} missions, {len(period) + a.missions} team steps in {wall:.1f} s "
        f"({wall / a.missions * 1e3:.0f} ms per mission including its REST start, records and completion)"
    )
    print(
        f"lockstep step period ({a.robots} robots): median {np.median(period):.2f} ms, "
        f"p90 {np.percentile(period, 90):.2f} ms (first report to replies: median {np.median(wait):.2f} ms)"
    )
    print(
        f"agent decision step inside the agent ({len(d)} decisions, n={graph.n}): median {np.median(d):.1f} us, "
        f"p99 {np.percentile(d, 99):.1f} us"
    )
    print(
        f"agent resident memory after the missions: {', '.join(f'{r} {v:.1f} MB' for r, v in rss.items())}; "
        f"libtorch mapped in: {torch_mapped or 'none'}"
    )


if __name__ == "__main__":
    main()

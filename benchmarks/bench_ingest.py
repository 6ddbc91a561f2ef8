"""Episode ingest throughput of the training server over Zenoh on loopback.

    python benchmarks/bench_ingest.py [--senders 20] [--records 6000] [--steps 200]

Starts a training server on free ports, then ``--senders`` concurrent senders (each its own Zenoh
session; spread over 4 processes) send records of ``--steps`` steps as queries on the episode
keys, each waiting for the server's ok as an agent does. Prints records/s acknowledged and checks
that the server stored every one (none lost, none twice).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from shared.core.files import read_token
from shared.core.graph import builtin_graph
from shared.core.http import ApiClient
from shared.core.models import Sensor
from shared.core.records import make_record
from shared.tools.fleetsim import start_server


def _payloads(graph, sender: int, count: int, steps: int) -> list[tuple[str, bytes]]:
    rng = np.random.default_rng(sender)
    out = []
    for k in range(count):
        nodes = [graph.start]
        for _ in range(steps - 1):
            nodes.append(int(rng.choice(graph.closed(nodes[-1]))))
        rec = make_record(
            graph,
            fleet="default",
            mission_id=f"b{sender}-{k}",
            robot_id=f"s{sender}",
            nodes=nodes,
            z=[0] * steps,
            sensor=Sensor(),
            captured=False,
            capture_time=None,
            captured_by=None,
        )
        out.append((f"mures/default/episodes/s{sender}/b{sender}-{k}", json.dumps(rec).encode()))
    return out


def _process(endpoint: str, senders: list[int], count: int, steps: int, start, results) -> None:
    import zenoh

    from shared.core.wire import zenoh_config

    graph = builtin_graph("museum")
    work = {s: _payloads(graph, s, count, steps) for s in senders}
    sessions = {s: zenoh.open(zenoh_config("client", connect=[endpoint])) for s in senders}
    acked = {s: 0 for s in senders}

    def run(s: int) -> None:
        for key, payload in work[s]:
            for r in sessions[s].get(key, payload=payload, timeout=30, consolidation=zenoh.ConsolidationMode.NONE):
                if r.ok is not None:
                    acked[s] += 1
                break

    start.wait()
    threads = [threading.Thread(target=run, args=(s,)) for s in senders]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for s in sessions.values():
        s.close()
    results.put(sum(acked.values()))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--senders", type=int, default=20)
    ap.add_argument("--records", type=int, default=6000, help="records in all")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--processes", type=int, default=4)
    a = ap.parse_args()
    per = a.records // a.senders
    with tempfile.TemporaryDirectory() as tmp:
        logs = Path(tmp) / "logs"
        logs.mkdir()
        proc, base, endpoint = start_server(["--env", "museum"], Path(tmp) / "data", 4, Sensor(), logs)
        try:
            ctx = mp.get_context("spawn")
            start, results = ctx.Event(), ctx.Queue()
            groups = [list(range(a.senders))[i :: a.processes] for i in range(a.processes)]
            procs = [ctx.Process(target=_process, args=(endpoint, g, per, a.steps, start, results)) for g in groups]
            for p in procs:
                p.start()
            time.sleep(8.0)  # let every process build its payloads and open its sessions
            size = len(_payloads(builtin_graph("museum"), 0, 1, a.steps)[0][1])
            t0 = time.perf_counter()
            start.set()
            acked = sum(results.get() for _ in procs)
            wall = time.perf_counter() - t0
            for p in procs:
                p.join()
            stats = ApiClient(base, read_token(Path(tmp) / "data" / "agent.token")).get("/api/v1/episodes/stats")
        finally:
            proc.terminate()
            proc.wait(30)
    print(f"{a.senders} senders, {per * a.senders} records of {a.steps} steps ({size / 1024:.1f} KiB each)")
    print(f"acknowledged {acked} in {wall:.2f} s: {acked / wall:.0f} records/s")
    print(
        f"server stored {stats['stored']}, rejected {sum(stats['rejected'].values())}: "
        f"{'none lost' if stats['stored'] == per * a.senders == acked else 'MISMATCH'}"
    )


if __name__ == "__main__":
    main()

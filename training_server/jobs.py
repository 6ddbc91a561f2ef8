"""Training runs: EM on the fleet's own records, CE-PG in simulation under the estimated model,
an evaluation gate, and a new immutable policy version.

A run executes in a separate process (multiprocessing "spawn": no Zenoh session or lock is
inherited), one at a time. The process reads the episodes through its own SQLite connection,
reports progress on a queue, polls a cancel event, and writes its snapshot under
``<data>/staging/<run>``; the supervisor thread in the server turns a passed snapshot into the
next version. A failed, cancelled or gated-out run leaves the current policy untouched.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import queue
import shutil
import sqlite3
import threading
import time
import traceback
from pathlib import Path
from typing import Any

log = logging.getLogger("mures.server.training")

DEFAULTS: dict[str, Any] = {
    "episodes": 20_000,  # CE-PG episodes in simulation, warm-started from the current policy
    "beta": 0.5,
    "lr": 0.01,
    "seed": 0,
    "max_records": 20_000,  # newest episode records used by EM
    "em_max_iter": 300,
    "gate_episodes": 1000,  # evaluation episodes for the gate (same seeds for both policies)
    "gate": True,  # False: promote whatever the run produced
    "promote": True,  # False: create the version but keep the current one
    "threads": 0,  # torch threads in the training process (0: torch's default)
}


def check_params(params: dict[str, Any]) -> dict[str, Any]:
    """Merge ``params`` into the defaults; raise ValueError naming the first bad one."""
    out = dict(DEFAULTS)
    for k, v in params.items():
        if k not in DEFAULTS:
            raise ValueError(f"unknown parameter {k!r} (expected one of {', '.join(DEFAULTS)})")
        want = type(DEFAULTS[k])
        if want is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if not isinstance(v, want) or (want is int and isinstance(v, bool)):
            raise ValueError(f"parameter {k!r} must be {want.__name__}, got {v!r}")
        out[k] = v
    if not 256 <= out["episodes"] <= 10_000_000:
        raise ValueError("episodes must be between 256 and 10,000,000")
    if not 0.0 <= out["beta"] <= 1.0:
        raise ValueError("beta must be in [0, 1]")
    if not 0.0 < out["lr"] < 1.0:
        raise ValueError("lr must be in (0, 1)")
    for k in ("max_records", "em_max_iter", "gate_episodes"):
        if out[k] < 1:
            raise ValueError(f"{k} must be at least 1")
    if out["threads"] < 0:
        raise ValueError("threads must be >= 0")
    return out


def run_training(job: dict[str, Any], events: Any, cancel: Any) -> None:
    """The training process. Puts {"type": "progress"|"done"|"failed"|"cancelled", ...} on ``events``."""
    try:
        events.put({"type": "done", **_train(job, events, cancel)})
    except _Cancelled:
        events.put({"type": "cancelled"})
    except Exception as exc:  # reported to the operator, never crashes the server
        events.put({"type": "failed", "error": f"{type(exc).__name__}: {exc}", "trace": traceback.format_exc()})


class _Cancelled(Exception):
    pass


def _train(job: dict[str, Any], events: Any, cancel: Any) -> dict[str, Any]:
    import torch

    from shared.core.graph import graph_from_dict
    from shared.core.models import uniform_walk
    from shared.engine.estimate import collect_missions, em
    from shared.engine.evaluate import evaluate
    from shared.learning.config import TrainConfig
    from shared.learning.snapshot import PolicySearcher, load_snapshot, save_snapshot
    from shared.learning.train import train

    p = job["params"]
    if p["threads"]:
        torch.set_num_threads(p["threads"])
    graph = graph_from_dict(job["graph"], "server map")
    current = load_snapshot(job["current_path"], graph)
    sensor = current.sensor
    t0 = time.perf_counter()

    def say(phase: str, **kw: Any) -> None:
        events.put({"type": "progress", "phase": phase, "elapsed_s": round(time.perf_counter() - t0, 2), **kw})

    # 1. EM on the fleet's own records (robots' positions and observations only)
    say("em", message="reading episode records")
    db = sqlite3.connect(f"file:{job['db']}?mode=ro", uri=True)
    try:
        rows = db.execute(
            "SELECT record FROM episodes WHERE fleet=? ORDER BY id DESC LIMIT ?", (job["fleet"], p["max_records"])
        ).fetchall()
    finally:
        db.close()
    data = collect_missions(((i, json.loads(r[0])) for i, r in enumerate(rows)), graph, fleet=job["fleet"])
    if len(data.length) == 0:
        raise ValueError("no usable episode records: fly some missions before training")
    say("em", message=f"EM on {len(data.length)} missions ({data.used_records} records)")
    est = em(graph, data, init=uniform_walk(graph), max_iter=p["em_max_iter"], tol=1e-5)
    model = est.model
    em_info = {
        "missions": len(data.length),
        "records": data.used_records,
        "iterations": est.iterations,
        "converged": est.converged,
        "skipped": dict(data.skipped),
    }
    if cancel.is_set():
        raise _Cancelled

    # 2. CE-PG in simulation under the estimated model, from the current policy
    cfg = TrainConfig(
        robots=current.robots,
        episodes=p["episodes"],
        beta=[p["beta"]],
        lr=[p["lr"]],
        variant=current.variant,
        belief="true",
        seed=p["seed"],
        hidden=current.policy.H,
    )
    last = [0.0]

    def on_progress(point: dict[str, Any]) -> None:
        now = time.perf_counter()
        if now - last[0] >= 0.5 or point["episodes"] >= point["total"]:
            last[0] = now
            say(
                "train",
                episodes=point["episodes"],
                total=point["total"],
                mean_capture_time=round(float(point.get("mean_capture_time", float("nan"))), 3),
            )

    res = train(graph, model, sensor, cfg, init_policy=current, progress=on_progress, should_stop=cancel.is_set)
    if res.interrupted:
        raise _Cancelled

    # 3. the evaluation gate: both policies on the same seeds under the estimated model
    say("gate", message=f"evaluating new and current policy on {p['gate_episodes']} episodes")
    from shared.learning.snapshot import Snapshot

    new = Snapshot(
        meta={"variant": current.variant, "robots": current.robots}, policy=res.policy, model=model, sensor=sensor
    )
    figures = {}
    for name, snap in (("current", current), ("new", new)):
        r = evaluate(
            graph,
            model,
            sensor,
            current.robots,
            lambda s, snap=snap: PolicySearcher(snap, graph, sensor, current.robots, seed=s),
            episodes=p["gate_episodes"],
            seed=p["seed"] + 1,
        ).summary()
        figures[name] = {k: r[k] for k in ("mean_capture_time", "ci95", "censored_fraction", "episodes")}
    passed = figures["new"]["mean_capture_time"] <= figures["current"]["mean_capture_time"]
    out = Path(job["staging"])
    shutil.rmtree(out, ignore_errors=True)
    config = {**cfg.to_dict(), "target": "em-estimate", "map": graph.name, "parent_version": job["parent"]}
    save_snapshot(
        out, res.policy, graph, model, sensor, current.variant, cfg.per_robot(cfg.beta, "beta"), config, res.summary
    )
    return {
        "metrics": {
            "em": em_info,
            "train": {k: res.summary[k] for k in ("episodes", "env_steps", "wall_seconds", "episodes_per_second")},
            "gate": {**figures, "passed": passed, "enforced": p["gate"]},
            "wall_seconds": round(time.perf_counter() - t0, 2),
        },
        "passed": passed or not p["gate"],
    }


class Supervisor:
    """Runs queued training runs one at a time, each in its own process."""

    def __init__(self, server: Any) -> None:
        self.server = server
        self.ctx = mp.get_context("spawn")
        self.queue: queue.Queue[str] = queue.Queue()
        self.cancels: dict[str, Any] = {}
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="training-supervisor", daemon=True)
        self.current_proc: Any = None

    def start(self) -> None:
        self.thread.start()

    def submit(self, run_id: str) -> None:
        with self.lock:
            self.cancels[run_id] = self.ctx.Event()
        self.queue.put(run_id)

    def cancel(self, run_id: str) -> bool:
        with self.lock:
            ev = self.cancels.get(run_id)
        if ev is None:
            return False
        ev.set()
        return True

    def stop(self) -> None:
        self.stopping.set()
        with self.lock:
            for ev in self.cancels.values():
                ev.set()
        self.queue.put("")
        proc = self.current_proc
        if proc is not None:
            proc.join(10)
            if proc.is_alive():
                proc.kill()
        self.thread.join(15)

    def _loop(self) -> None:
        while not self.stopping.is_set():
            run_id = self.queue.get()
            if not run_id or self.stopping.is_set():
                continue
            try:
                self._run(run_id)
            except Exception:
                log.exception("training run %s: supervisor error", run_id)
                self.server.store.update_run(run_id, status="failed", finished=time.time(), error="server error")
            finally:
                with self.lock:
                    self.cancels.pop(run_id, None)

    def _run(self, run_id: str) -> None:
        srv = self.server
        store = srv.store
        with self.lock:
            cancel = self.cancels[run_id]
        if cancel.is_set():
            store.update_run(run_id, status="cancelled", finished=time.time())
            return
        run = store.get_run(run_id)
        assert run is not None
        parent = srv.current_version()
        staging = srv.data_dir / "staging" / run_id
        job = {
            "params": run["params"],
            "graph": srv.graph.to_json(),
            "db": str(store.path),
            "fleet": srv.fleet,
            "current_path": str(srv.snapshot_dir(parent)),
            "parent": parent,
            "staging": str(staging),
        }
        events = self.ctx.Queue()
        proc = self.ctx.Process(target=run_training, args=(job, events, cancel), name=f"train-{run_id}", daemon=True)
        store.update_run(run_id, status="running", started=time.time(), progress={"phase": "starting"})
        log.info("training run %s started from version %s: %s", run_id, parent, json.dumps(run["params"]))
        self.current_proc = proc
        proc.start()
        result: dict[str, Any] | None = None
        while result is None:
            try:
                ev = events.get(timeout=0.5)
            except queue.Empty:
                if not proc.is_alive():
                    try:  # the last message may still be in the pipe
                        ev = events.get(timeout=1.0)
                    except queue.Empty:
                        ev = {"type": "failed", "error": f"training process died (exit code {proc.exitcode})"}
                else:
                    continue
            if ev["type"] == "progress":
                store.update_run(run_id, progress={k: v for k, v in ev.items() if k != "type"})
            else:
                result = ev
        proc.join(10)
        self.current_proc = None
        now = time.time()
        if result["type"] == "cancelled":
            store.update_run(run_id, status="cancelled", finished=now)
            log.info("training run %s cancelled", run_id)
        elif result["type"] == "failed":
            store.update_run(run_id, status="failed", finished=now, error=result["error"])
            log.warning("training run %s failed: %s", run_id, result["error"])
        elif not result["passed"]:
            g = result["metrics"]["gate"]
            store.update_run(
                run_id,
                status="failed",
                finished=now,
                metrics=result["metrics"],
                error=f"evaluation gate: new policy {g['new']['mean_capture_time']:.2f} steps, "
                f"current {g['current']['mean_capture_time']:.2f}; current policy kept",
            )
            log.info("training run %s did not pass the gate; version %s stays current", run_id, parent)
        else:
            version = srv.publish_version(
                staging, parent=parent, run_id=run_id, metrics=result["metrics"], promote=bool(run["params"]["promote"])
            )
            store.update_run(
                run_id,
                status="succeeded",
                finished=now,
                metrics=result["metrics"],
                version=version,
                progress={"phase": "done"},
            )
            log.info("training run %s succeeded: version %d", run_id, version)
        shutil.rmtree(staging, ignore_errors=True)

"""The server's promises under faults and load, measured against real processes on loopback;
writes results/reliability.json and docs/reliability.md.

    python benchmarks/reliability.py [--repeats 20] [--database sqlite|postgresql|both]
                                     [--only FAULT ...] [--load 20 50 200] [--soak-s 60]

Faults, each repeated at random moments (uniform over the window where it can hit):
  ingest       kill -9 of the server while a sender streams episode records
  training     kill -9 of the server during a training run (half of them after a cancel request)
  publication  kill -9 of a process publishing a policy version (the server's own publish_version)
  zenoh-link   the Zenoh router (the server) killed and restarted with agents mid-mission
  disk-full    the data directory's files capped (RLIMIT_FSIZE) while records arrive
  agent        kill -9 of a robot agent mid-mission, then its restart
After each: acknowledged episodes lost (must be 0), every served version complete (its artifact's
sha256 is the one listed), interrupted runs failed or cancelled, outboxes drained, the server
answers. Load: N concurrent senders for a while each: records/s acknowledged, p50/p99
acknowledgement latency, the server's memory, nothing lost. PostgreSQL runs use a throwaway
cluster of the machine's PostgreSQL (tests/conftest.py's PostgresCluster).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import random
import resource
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from shared.core.files import read_token  # noqa: E402
from shared.core.graph import builtin_graph  # noqa: E402
from shared.core.http import ApiClient, ApiError  # noqa: E402
from shared.core.models import Sensor, uniform_walk  # noqa: E402
from shared.core.records import make_record  # noqa: E402
from shared.core.wire import send_episode, zenoh_config  # noqa: E402
from shared.tools.fleetsim import _child_env, free_port, launch, reap, wait_until  # noqa: E402

GRAPH = builtin_graph("office")


def say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------- a server process
class ServerProc:
    """A training-server on fixed loopback ports (so that it can be restarted where its clients
    look for it), its logs drained by a thread of this process (a file-size cap on the server
    must not cut its log)."""

    def __init__(self, data: Path, database_url: str | None, extra: list[str] | None = None) -> None:
        self.data, self.database_url = data, database_url
        self.http, self.zport = free_port(), free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.zport}"
        self.base = f"http://127.0.0.1:{self.http}"
        self.extra = extra or []
        self.proc: subprocess.Popen | None = None
        data.parent.mkdir(parents=True, exist_ok=True)
        self.log = data.parent / f"{data.name}-server.log"
        self.starts = 0

    def start(self, fsize: int | None = None, timeout: float = 90) -> None:
        cmd = [sys.executable, "-m", "training_server", "--env", "office", "--data-dir", str(self.data)]
        cmd += ["--http", f"127.0.0.1:{self.http}", "--zenoh-listen", self.endpoint, "--robots", "3", *self.extra]
        cmd += ["--init-policy", "untrained"]  # a per-map team's runs: the faults, not the policy, are measured
        if self.database_url:
            cmd += ["--database-url", self.database_url]

        def limit() -> None:
            if fsize is not None:
                resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=_child_env(), preexec_fn=limit
        )
        threading.Thread(target=self._drain, args=(self.proc,), daemon=True).start()
        self.starts += 1
        probe = ApiClient(self.base, None)

        def up() -> bool:
            if self.proc is not None and self.proc.poll() is not None:
                raise RuntimeError(f"training-server exited with {self.proc.returncode}: see {self.log}")
            return probe.get("/api/v1/health")["status"] == "ok"

        wait_until(up, timeout, "the server to answer", every=0.1)

    def _drain(self, proc: subprocess.Popen) -> None:
        assert proc.stdout is not None
        with open(self.log, "ab") as fh:
            for line in proc.stdout:
                fh.write(line)

    def api(self) -> ApiClient:
        return ApiClient(self.base, read_token(self.data / "operator.token"))

    def kill9(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(30)

    def stop(self) -> int | None:
        """SIGTERM, then SIGKILL past 30 s: the exit status, or None where it had to be killed."""
        assert self.proc is not None
        self.proc.send_signal(signal.SIGTERM)
        return reap(self.proc, 30)

    def children(self) -> list[int]:
        """Process ids of the server's child processes (its training process)."""
        assert self.proc is not None
        out = []
        for task in Path(f"/proc/{self.proc.pid}/task").glob("*"):
            with contextlib.suppress(OSError):
                out += [int(x) for x in (task / "children").read_text().split()]
        return out


def alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


# ---------------------------------------------------------------------- records
def record(mission: str, robot: str = "r1", rng: random.Random | None = None, steps: int = 20) -> bytes:
    rng = rng or random.Random(hash(mission))
    nodes = [GRAPH.start]
    for _ in range(steps):
        nodes.append(int(rng.choice(list(GRAPH.closed(nodes[-1])))))
    return json.dumps(
        make_record(
            GRAPH,
            fleet="default",
            mission_id=mission,
            robot_id=robot,
            nodes=nodes,
            z=[0] * len(nodes),
            sensor=Sensor(),
            captured=False,
            capture_time=None,
            captured_by=None,
        )
    ).encode()


def send(session: Any, robot: str, mission: str, payload: bytes, timeout: float = 5.0) -> tuple[bool | None, Any]:
    """(True, body) stored/duplicate, (False, body) rejected, (None, None) no answer."""
    return send_episode(session, "default", robot, mission, payload, timeout)


def stored_missions(api: ApiClient, robot: str | None = None) -> Counter[str]:
    """mission_id -> records stored (every page of /api/v1/episodes)."""
    out: Counter[str] = Counter()
    after = 0
    while True:
        q = f"/api/v1/episodes?limit=1000&after={after}" + (f"&robot_id={robot}" if robot else "")
        page = api.get(q)
        out.update(e["mission_id"] for e in page["items"])
        if page["next_after"] is None:
            return out
        after = page["next_after"]


def versions_complete(srv: ServerProc) -> bool:
    """Every listed version's artifact is there and has the listed sha256."""
    import hashlib

    api = srv.api()
    for v in api.get("/api/v1/policies")["items"]:
        _status, _headers, body = api.request("GET", f"/api/v1/policies/{v['version']}/artifact")
        if hashlib.sha256(body).hexdigest() != v["sha256"]:
            return False
    return True


# ---------------------------------------------------------------------- faults
def fault_ingest(work: Path, url: str | None, repeats: int, rng: random.Random) -> dict[str, Any]:
    """kill -9 while a sender streams records; after the restart the sender resends what was not
    acknowledged (as an agent's outbox does)."""
    srv = ServerProc(work / "ingest", url)
    srv.start()
    acked: set[str] = set()
    pending: list[str] = []
    k = 0
    lost = 0
    try:
        for rep in range(repeats):
            with zenoh.open(zenoh_config("client", connect=[srv.endpoint])) as s:
                for m in list(pending):  # the outbox of the last round
                    if send(s, "r1", m, record(m))[0]:
                        acked.add(m)
                        pending.remove(m)
                stop = threading.Event()

                def stream(s: Any = s, stop: threading.Event = stop) -> None:
                    nonlocal k
                    while not stop.is_set():
                        m = f"i{k}"
                        k += 1
                        ok, _ = send(s, "r1", m, record(m), timeout=2.0)
                        (acked.add if ok else pending.append)(m)
                        if ok is None:
                            return

                t = threading.Thread(target=stream, daemon=True)
                t.start()
                time.sleep(rng.uniform(0.2, 2.0))
                srv.kill9()
                stop.set()
                t.join(10)
            srv.start()
            got = stored_missions(srv.api())
            lost += len(acked - set(got))
            if any(c > 1 for c in got.values()):
                raise AssertionError("a record stored twice")
            say(f"  ingest {rep + 1}/{repeats}: {len(acked)} acknowledged, lost {len(acked - set(got))}")
        with zenoh.open(zenoh_config("client", connect=[srv.endpoint])) as s:
            for m in pending:
                if send(s, "r1", m, record(m))[0]:
                    acked.add(m)
        got = stored_missions(srv.api())
        return {
            "repeats": repeats,
            "acknowledged": len(acked),
            "lost": lost + len(acked - set(got)),
            "resent_stored": len(set(got)) == k,
            "answers": srv.api().get("/api/v1/health")["status"] == "ok",
        }
    finally:
        srv.stop()


def _seed_records(srv: ServerProc, missions: int = 60) -> None:
    with zenoh.open(zenoh_config("client", connect=[srv.endpoint])) as s:
        for m in range(missions):
            for r in ("r1", "r2"):
                send(s, r, f"seed{m}", record(f"seed{m}", r))


def fault_training(work: Path, url: str | None, repeats: int, rng: random.Random) -> dict[str, Any]:
    """kill -9 of the server during a training run (its process running: checked just before the
    kill; a kill that came after the run had ended is not counted); every second run was asked to
    cancel first. After the restart a cancelled run stays cancelled, and another goes on where it
    was (the restarted server resumes it) to its end."""
    srv = ServerProc(work / "training", url)
    srv.start()
    _seed_records(srv)
    out = Counter[str]()
    orphans = during = late = 0
    try:
        params = {"episodes": 2048, "gate_episodes": 200, "em_max_iter": 50, "gate": False, "threads": 1}
        api = srv.api()
        run = api.post("/api/v1/training-runs", params)  # one run to the end: the window to kill in
        wait_until(lambda: srv.children(), 30, "the training process")
        t0 = time.perf_counter()
        wait_until(lambda: api.get(f"/api/v1/training-runs/{run['id']}")["status"] == "succeeded", 600, "a run")
        window = time.perf_counter() - t0
        say(f"  training: a run's process works for {window:.1f} s")
        while during < repeats and during + late < 3 * repeats:
            api = srv.api()
            run = api.post("/api/v1/training-runs", params)
            wait_until(lambda: srv.children(), 30, "the training process")
            time.sleep(rng.uniform(0.0, 0.9 * window))
            cancel = during % 2 == 1
            if cancel:
                try:
                    api.post(f"/api/v1/training-runs/{run['id']}/cancel")
                except ApiError as exc:  # it may have finished meanwhile
                    if exc.status != 409:
                        raise
            running = api.get(f"/api/v1/training-runs/{run['id']}")["status"] == "running"
            kids = srv.children()
            srv.kill9()
            try:
                wait_until(lambda kids=kids: not any(alive(p) for p in kids), 10, "the training process to die")
            except TimeoutError:
                orphans += 1
                for p in kids:
                    os.kill(p, signal.SIGKILL)
            srv.start()
            api = srv.api()
            r = api.get(f"/api/v1/training-runs/{run['id']}")
            if r["cancel_requested"] is not None and r["status"] in ("queued", "running"):
                raise AssertionError(f"a cancelled run came back {r['status']}")
            if r["status"] in ("queued", "running"):  # resumed where it was: it goes on to its end
                r = wait_until(
                    lambda run=run, api=api: (
                        (x := api.get(f"/api/v1/training-runs/{run['id']}"))["status"] not in ("queued", "running")
                        and x
                    ),
                    600,
                    "the resumed run",
                )
                r = {**r, "status": f"resumed, then {r['status']}"}
            staging = list((srv.data / "staging").iterdir())
            if staging:
                raise AssertionError(f"run {r['status']}, staging {staging}")
            if not versions_complete(srv):
                raise AssertionError("a partial version is served")
            if not running:
                late += 1
                continue
            during += 1
            out[r["status"]] += 1
            if r["cancel_requested"] is not None and r["status"] == "failed":  # it may have finished first
                raise AssertionError("a cancelled run came back failed")
            say(f"  training {during}/{repeats}: run {r['status']}{' (cancel asked)' * cancel}")
        return {
            "repeats": during,
            "run_status_after": dict(out),
            "kills_after_the_run_ended_not_counted": late,
            "training_process_outlived_server": orphans,
            "versions_complete": True,
            "answers": srv.api().get("/api/v1/health")["status"] == "ok",
        }
    finally:
        srv.stop()


_PUBLISH = """
import sys, time
from pathlib import Path
from shared.core.graph import builtin_graph
from training_server.server import Server
d = Path(sys.argv[1]); url = sys.argv[2] or None
srv = Server(d, builtin_graph("office"), "default", d / "operator.token", d / "agent.token", database_url=url)
print("ready", flush=True)
srv.publish_version(d / "policies" / "v1" / "snapshot", 1, None, {"note": "fault test"}, promote=False)
print("done", flush=True)
time.sleep(60)
"""


def fault_publication(work: Path, url: str | None, repeats: int, rng: random.Random) -> dict[str, Any]:
    """kill -9 of a process in the middle of the server's publish_version (copy, convert, tar,
    digest, database row), at a random moment; then the server starts on that data directory."""
    srv = ServerProc(work / "publication", url)
    srv.start()
    srv.stop()

    def publisher() -> subprocess.Popen:
        p = subprocess.Popen(
            [sys.executable, "-c", _PUBLISH, str(srv.data), url or ""], stdout=subprocess.PIPE, env=_child_env()
        )
        assert p.stdout is not None and p.stdout.readline().strip() == b"ready"
        return p

    p = publisher()  # one publication to the end: how long it takes
    t0 = time.perf_counter()
    assert p.stdout is not None and p.stdout.readline().strip() == b"done"
    took = time.perf_counter() - t0
    p.kill()
    p.wait()
    say(f"  publication: one takes {took * 1000:.0f} ms")
    published = 0
    for rep in range(repeats):
        p = publisher()
        time.sleep(rng.uniform(0.0, took))
        p.send_signal(signal.SIGKILL)
        p.wait()
        srv.start()
        listed = srv.api().get("/api/v1/policies")["items"]
        ok = versions_complete(srv)
        leftovers = [
            d.name for d in (srv.data / "policies").iterdir() if d.name not in {f"v{v['version']}" for v in listed}
        ]
        srv.stop()
        if not ok or leftovers:
            raise AssertionError(f"partial version served: complete={ok}, leftovers={leftovers}")
        published = len(listed) - 1
        say(f"  publication {rep + 1}/{repeats}: {published} versions published so far, all complete")
    return {
        "repeats": repeats,
        "publication_ms": round(took * 1000),
        "versions_published_before_the_kill": published,
        "versions_complete": True,
    }


def fault_disk_full(work: Path, url: str | None, repeats: int, rng: random.Random) -> dict[str, Any]:
    """Every file of the server capped (RLIMIT_FSIZE) a little above its database's size: records
    arrive until writes fail; the server must refuse them (resend later), keep answering, lose
    nothing acknowledged; restarted without the cap, the refused ones are stored on resend.
    SQLite only: with PostgreSQL the database's files are the PostgreSQL server's (not tried)."""
    if url is not None:
        return {"repeats": 0, "skipped": "PostgreSQL's own disk is not the training server's"}
    srv = ServerProc(work / "disk", url)
    srv.start()
    srv.stop()
    acked: set[str] = set()
    refused_total = 0
    k = 0
    for rep in range(repeats):
        db = [f.stat().st_size for f in srv.data.glob("mures.db*")] or [0]
        cap = max(db) + rng.randint(20_000, 200_000)
        srv.start(fsize=cap)
        refused: list[str] = []
        with zenoh.open(zenoh_config("client", connect=[srv.endpoint])) as s:
            for _ in range(3000):
                m = f"d{k}"
                k += 1
                ok, _body = send(s, "r1", m, record(m, steps=60))
                if ok:
                    acked.add(m)
                else:
                    refused.append(m)
                    if len(refused) >= 20:
                        break
        answers = srv.api().get("/api/v1/health")["status"] == "ok" and srv.proc.poll() is None  # type: ignore[union-attr]
        srv.stop()
        srv.start()
        with zenoh.open(zenoh_config("client", connect=[srv.endpoint])) as s:
            for m in refused:
                if send(s, "r1", m, record(m, steps=60))[0]:
                    acked.add(m)
        got = set(stored_missions(srv.api()))
        srv.stop()
        lost = len(acked - got)
        refused_total += len(refused)
        say(
            f"  disk-full {rep + 1}/{repeats}: cap {cap} B, {len(refused)} refused while full, answered {answers}, lost {lost}"
        )
        if lost or not answers:
            raise AssertionError(f"lost {lost}, answered {answers}")
    return {"repeats": repeats, "acknowledged": len(acked), "refused_while_full": refused_total, "lost": 0}


def _fleet(work: Path, url: str | None) -> Any:
    extra = ["--database-url", url] if url else []
    return launch(
        GRAPH,
        ["--env", "office"],
        uniform_walk(GRAPH),
        Sensor(),
        3,
        work,
        step_timeout=3.0,
        server_extra=extra,
    )


def _outboxes_empty(fleet: Any) -> bool:
    return not any(any((fleet.workdir / "agents" / r / "outbox").glob("*.json")) for r in ("r1", "r2", "r3"))


def fault_agent(work: Path, url: str | None, repeats: int, rng: random.Random) -> dict[str, Any]:
    """kill -9 of a random agent mid-mission, then its restart: its cut-short record arrives."""
    fleet = _fleet(work / "agent", url)
    robots = ["r1", "r2", "r3"]
    complete = 0
    try:
        for rep in range(repeats):
            fleet.world.step_delay = 0.05
            m = fleet.api.post("/api/v1/missions", {"robots": robots, "seed": 1000 + rep, "max_steps": 180})
            time.sleep(rng.uniform(0.05, 0.6))
            victim = rng.choice(robots)
            fleet.stop_agent(victim, signal.SIGKILL)
            fleet.world.step_delay = 0.0
            fleet.start_agent(victim)
            wait_until(lambda v=victim: v in fleet.online(), 60, f"{victim} back")
            got = wait_until(
                lambda m=m: (r := fleet.api.get(f"/api/v1/missions/{m['id']}"))["status"] == "completed" and r,
                90,
                "every record of the mission",
            )
            complete += set(got["episodes_received"]) == set(robots)
            wait_until(lambda: _outboxes_empty(fleet), 30, "outboxes to drain")
            say(f"  agent {rep + 1}/{repeats}: {victim} killed; all 3 records in")
        return {"repeats": repeats, "missions_with_every_record": complete, "outboxes_drained": True}
    finally:
        fleet.close()


def fault_zenoh_link(work: Path, url: str | None, repeats: int, rng: random.Random) -> dict[str, Any]:
    """The router (the server's Zenoh session) killed with agents mid-mission and restarted on the
    same endpoint after a while: agents reconnect, outboxes drain, nothing acknowledged is lost."""
    fleet = _fleet(work / "link", url)
    robots = ["r1", "r2", "r3"]
    data = fleet.workdir / "server"
    srv = ServerProc(data, url)  # the same data dir and ports as the fleet's server
    base_port = int(fleet.api.base.rsplit(":", 1)[1])
    srv.http, srv.base = base_port, fleet.api.base
    srv.endpoint, srv.zport = fleet.zenoh_endpoint, int(fleet.zenoh_endpoint.rsplit(":", 1)[1])
    srv.proc = fleet.server
    missions = []
    try:
        for rep in range(repeats):
            fleet.world.step_delay = 0.05
            m = fleet.api.post("/api/v1/missions", {"robots": robots, "seed": 2000 + rep, "max_steps": 180})
            missions.append(m["id"])
            time.sleep(rng.uniform(0.05, 0.6))
            srv.kill9()
            time.sleep(rng.uniform(0.5, 3.0))
            srv.start()
            fleet.server = srv.proc
            fleet.world.step_delay = 0.0
            wait_until(lambda: set(robots) <= set(fleet.online()), 60, "the agents to reconnect")
            wait_until(lambda: _outboxes_empty(fleet), 90, "outboxes to drain")
            with contextlib.suppress(TimeoutError):  # a shortfall is reported below, not raised
                wait_until(lambda m=m: stored_missions(fleet.api)[m["id"]] == 3, 60, "the mission's records")
            got = stored_missions(fleet.api)
            say(f"  zenoh-link {rep + 1}/{repeats}: records of this mission stored: {got[m['id']]}")
        got = stored_missions(fleet.api)
        return {
            "repeats": repeats,
            "missions": len(missions),
            "records_expected": 3 * len(missions),
            "records_stored": sum(got[m] for m in missions),
            "outboxes_drained": True,
        }
    finally:
        fleet.close()


FAULTS = {
    "ingest": fault_ingest,
    "training": fault_training,
    "publication": fault_publication,
    "zenoh-link": fault_zenoh_link,
    "disk-full": fault_disk_full,
    "agent": fault_agent,
}


# ---------------------------------------------------------------------- load
def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def load(work: Path, url: str | None, senders: int, seconds: float) -> dict[str, Any]:
    """``senders`` threads, each sending records one after another for ``seconds`` over a few Zenoh
    sessions; the acknowledgement latency of each, the server's memory once a second."""
    srv = ServerProc(work / f"load{senders}", url)
    srv.start()
    sessions = [zenoh.open(zenoh_config("client", connect=[srv.endpoint])) for _ in range(min(senders, 8))]
    lat: list[float] = []
    acked: list[str] = []
    failed = Counter[str]()
    lock = threading.Lock()
    stop = threading.Event()
    mem: list[float] = []

    def sender(i: int) -> None:
        s = sessions[i % len(sessions)]
        k = 0
        while not stop.is_set():
            m = f"s{i}-{k}"
            k += 1
            payload = record(m, robot=f"r{i}")
            t = time.perf_counter()
            ok, body = send(s, f"r{i}", m, payload, timeout=10)
            dt = time.perf_counter() - t
            with lock:
                if ok:
                    lat.append(dt)
                    acked.append(f"r{i}/{m}")
                else:
                    failed[(body or {}).get("reason", "no answer")] += 1

    threads = [threading.Thread(target=sender, args=(i,), daemon=True) for i in range(senders)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    while time.perf_counter() - t0 < seconds:
        time.sleep(1.0)
        assert srv.proc is not None
        mem.append(rss_mb(srv.proc.pid))
    stop.set()
    for t in threads:
        t.join(30)
    wall = time.perf_counter() - t0
    for s in sessions:
        s.close()
    stats = srv.api().get("/api/v1/episodes/stats")
    srv.stop()
    a = np.array(lat) * 1000
    return {
        "senders": senders,
        "seconds": round(wall, 1),
        "acknowledged": len(acked),
        "records_per_s": round(len(acked) / wall, 1),
        "p50_ms": round(float(np.percentile(a, 50)), 1) if len(a) else None,
        "p99_ms": round(float(np.percentile(a, 99)), 1) if len(a) else None,
        "not_acknowledged": dict(failed),
        "stored": stats["stored"],
        "lost": len(acked) - stats["stored"] if stats["stored"] <= len(acked) else 0,
        "server_rss_mb": {"first": round(mem[0], 1), "max": round(max(mem), 1), "last": round(mem[-1], 1)},
    }


# ---------------------------------------------------------------------- fuzzing
def fuzz_api(work: Path, url: str | None, seconds: float) -> dict[str, Any]:
    """Schemathesis, every check, against the served OpenAPI with each token, ``seconds`` each (the
    server with a high --sign-in-limit: see tests/test_api_fuzz.py)."""
    import re

    srv = ServerProc(work / "api-fuzz", url, ["--sign-in-limit", "1000000"])
    srv.start()
    out: dict[str, Any] = {}
    try:
        for who in ("operator", "agent", None):
            exe = Path(sys.executable).with_name("schemathesis")
            cmd = [str(exe), "run", f"{srv.base}/openapi.json", "--checks", "all", "--workers", "1", "--no-color"]
            cmd += ["--exclude-path", "/api/v1/events"]  # a stream that runs until the client leaves
            cmd += ["--max-time", str(int(seconds)), "--max-examples", "100000"]
            if who:
                cmd += ["-H", f"Authorization: Bearer {read_token(srv.data / f'{who}.token')}"]
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds * 3 + 300, cwd=work)
            text = r.stdout + r.stderr
            cases = re.search(r"(\d+) generated", text)
            found = re.search(r"(\d+) unique failures?", text)
            out[who or "none"] = {
                "cases": int(cases.group(1)) if cases else None,
                "findings": int(found.group(1)) if found else 0,
                "exit_status": r.returncode,
            }
            if r.returncode != 0:
                (work / f"schemathesis-{who or 'none'}.txt").write_text(text)
            say(f"  api-fuzz {who or 'no token'}: {out[who or 'none']}")
        out["server_answers"] = srv.api().get("/api/v1/health")["status"] == "ok"
    finally:
        srv.stop()
    return out


def fuzz_ingest(work: Path, url: str | None, examples: int) -> dict[str, Any]:
    """Hypothesis-generated records over Zenoh (tests/record_strategies.py): every invalid one
    must be rejected with its reason, every valid one stored once; the counts must add up."""
    from hypothesis import HealthCheck, given, settings
    from record_strategies import Sending, sendings

    from shared.core.records import canonical_record, parse_record

    srv = ServerProc(work / "ingest-fuzz", url)
    srv.start()
    stored: dict[tuple[str, str], bytes] = {}
    rejected: Counter[str] = Counter()
    sent: Counter[str] = Counter()
    wrong: list[str] = []
    try:
        with zenoh.open(zenoh_config("client", connect=[srv.endpoint])) as session:

            @settings(max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))
            @given(s=sendings(GRAPH, "default"))
            def one(s: Sending) -> None:
                ok, body = send(session, s.robot, s.mission, s.payload, timeout=10)
                sent["valid" if s.valid else "invalid"] += 1
                if s.valid:
                    want = "duplicate" if (s.robot, s.mission) in stored else "stored"
                    if not (ok is True and body == {"status": want}):
                        wrong.append(f"valid record answered {ok} {body}")
                    stored.setdefault((s.robot, s.mission), s.payload)
                else:
                    if not (ok is False and body.get("reason") == s.reason):
                        wrong.append(f"invalid ({s.reason}) answered {ok} {body}")
                    rejected[s.reason] += 1

            one()
        api = srv.api()
        stats = api.get("/api/v1/episodes/stats")
        mismatched = 0
        for (robot, mission), payload in stored.items():
            want = canonical_record(parse_record(json.loads(payload), GRAPH, "default"), GRAPH)
            mismatched += api.get(f"/api/v1/episodes/{robot}/{mission}") != want
        return {
            "records_sent": sum(sent.values()),
            "valid_sent": sent["valid"],
            "distinct_valid_stored": stats["stored"],
            "expected_stored": len(stored),
            "invalid_sent": sent["invalid"],
            "rejected_by_server": sum(stats["rejected"].values()),
            "rejected_by_reason": dict(sorted(stats["rejected"].items())),
            "wrong_answers": len(wrong),
            "stored_records_differing_from_sent": mismatched,
            "server_answers": api.get("/api/v1/health")["status"] == "ok" and srv.proc.poll() is None,  # type: ignore[union-attr]
            "examples_of_wrong_answers": wrong[:5],
        }
    finally:
        srv.stop()


# ---------------------------------------------------------------------- report
def write_report(res: dict[str, Any], path: Path) -> None:
    lines = [
        "# Reliability",
        "",
        "Generated by "
        + ", ".join(f"`{c}`" for c in res.get("commands", [res["command"]]))
        + " on "
        + res["date"]
        + f" ({res['machine']}); the data is in "
        "results/reliability.json. Each fault was injected at random moments into real processes on loopback "
        "(benchmarks/reliability.py says how); the test suite runs each once more on every CI run "
        "(tests/test_faults.py), and fuzzes the API (tests/test_api_fuzz.py) and the ingest "
        "(tests/test_ingest_fuzz.py).",
        "",
    ]
    if res.get("notes"):
        lines += [res["notes"], ""]
    for db, r in res["databases"].items():
        lines += [f"## {db}", ""]
        if r.get("faults"):
            lines += ["| fault | times survived | acknowledged episodes lost | details |", "| --- | --- | --- | --- |"]
        for name, f in r["faults"].items():
            if "error" in f:
                lines.append(f"| {name} | FAILED | ? | {f['error']} |")
                continue
            if "skipped" in f:
                lines.append(f"| {name} | not tried | - | {f['skipped']} |")
                continue
            details = ", ".join(f"{k} {v}" for k, v in f.items() if k not in ("repeats", "lost"))
            lost = f.get("lost", f.get("records_expected", 0) - f.get("records_stored", 0))
            lines.append(f"| {name} | {f['repeats']} | {lost} | {details} |")
        if r.get("api_fuzz"):
            af = r["api_fuzz"]
            lines += [
                "",
                "API fuzzing (Schemathesis `--checks all` on the served OpenAPI):",
                "",
                "| token | cases | findings |",
                "| --- | --- | --- |",
            ]
            lines += [
                f"| {who} | {af[who]['cases']} | {af[who]['findings']} |" for who in ("operator", "agent", "none")
            ]
        if r.get("ingest_fuzz"):
            f = r["ingest_fuzz"]
            lines += [
                "",
                f"Ingest fuzzing (Hypothesis, over Zenoh): {f['records_sent']} records sent, {f['valid_sent']} valid "
                f"({f['expected_stored']} distinct, {f['distinct_valid_stored']} stored, the rest answered duplicate), "
                f"{f['invalid_sent']} invalid, {f['rejected_by_server']} rejected by the server "
                f"({', '.join(f'{k} {v}' for k, v in f['rejected_by_reason'].items())}); wrong answers "
                f"{f['wrong_answers']}, stored records differing from what was sent "
                f"{f['stored_records_differing_from_sent']}; the server answered throughout: {f['server_answers']}.",
            ]
        if r.get("load"):
            lines += [
                "",
                "| concurrent senders | seconds | acknowledged | records/s | p50 ms | p99 ms | lost | server RSS MB (first/max/last) |",
                "| --- | --- | --- | --- | --- | --- | --- | --- |",
            ]
            for L in r["load"]:
                m = L["server_rss_mb"]
                lines.append(
                    f"| {L['senders']} | {L['seconds']} | {L['acknowledged']} | {L['records_per_s']} | {L['p50_ms']} "
                    f"| {L['p99_ms']} | {L['lost']} | {m['first']}/{m['max']}/{m['last']} |"
                )
        lines.append("")
    path.write_text("\n".join(lines) + "\n")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--database", choices=("sqlite", "postgresql", "both"), default="both")
    p.add_argument("--only", nargs="*", choices=sorted(FAULTS), help="these faults only (default all)")
    p.add_argument("--load", type=int, nargs="*", default=[20, 50, 200], help="concurrent senders per load run")
    p.add_argument("--load-s", type=float, default=30.0, help="seconds per load run")
    p.add_argument("--sections", nargs="*", choices=("faults", "load", "fuzz"), default=["faults", "load", "fuzz"])
    p.add_argument("--fuzz-s", type=float, default=120.0, help="seconds of Schemathesis per token")
    p.add_argument("--fuzz-records", type=int, default=10_000, help="Hypothesis-generated records sent")
    p.add_argument("--merge", action="store_true", help="update the sections run in an existing --out file")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--work", default="/tmp/mures-reliability")
    p.add_argument("--out", default=str(ROOT / "results" / "reliability.json"))
    p.add_argument("--report", default=str(ROOT / "docs" / "reliability.md"))
    args = p.parse_args()
    rng = random.Random(args.seed)
    work = Path(args.work)
    import shutil

    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    dbs = ["sqlite", "postgresql"] if args.database == "both" else [args.database]
    res: dict[str, Any] = {
        "command": "python benchmarks/reliability.py " + " ".join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "seed": args.seed,
        "databases": {},
    }
    cluster = None
    try:
        for db in dbs:
            url = None
            if db == "postgresql":
                from conftest import PostgresCluster, _postgres_bin

                if cluster is None:
                    bindir = _postgres_bin()
                    if bindir is None:
                        raise SystemExit("PostgreSQL is not installed (apt-get install postgresql)")
                    cluster = PostgresCluster(bindir)
            out: dict[str, Any] = {"faults": {}, "load": []}
            res["databases"][db] = out
            for name in (args.only or list(FAULTS)) if "faults" in args.sections else []:
                if cluster is not None and db == "postgresql":
                    url = cluster.database()
                say(f"{db}: {name} x{args.repeats}")
                t0 = time.perf_counter()
                try:
                    out["faults"][name] = FAULTS[name](work / db, url, args.repeats, rng)
                except Exception as exc:
                    out["faults"][name] = {"error": f"{type(exc).__name__}: {exc}"}
                out["faults"][name]["seconds"] = round(time.perf_counter() - t0, 1)
                say(f"{db}: {name}: {out['faults'][name]}")
            for n in args.load if "load" in args.sections else []:
                if cluster is not None and db == "postgresql":
                    url = cluster.database()
                say(f"{db}: load, {n} senders for {args.load_s:.0f} s")
                out["load"].append(load(work / db, url, n, args.load_s))
                say(f"{db}: {out['load'][-1]}")
            if "fuzz" in args.sections:
                if cluster is not None and db == "postgresql":
                    url = cluster.database()
                say(f"{db}: API fuzzing, {args.fuzz_s:.0f} s per token")
                out["api_fuzz"] = fuzz_api(work / db, url, args.fuzz_s)
                if cluster is not None and db == "postgresql":
                    url = cluster.database()
                say(f"{db}: ingest fuzzing, {args.fuzz_records} records")
                out["ingest_fuzz"] = fuzz_ingest(work / db, url, args.fuzz_records)
                say(f"{db}: {out['ingest_fuzz']}")
    finally:
        if cluster is not None:
            cluster.stop()
    if args.merge and Path(args.out).exists():  # keep the sections not run this time
        old = json.loads(Path(args.out).read_text())
        for db, r in res["databases"].items():
            kept = old["databases"].setdefault(db, {})
            kept.update({k: v for k, v in r.items() if v})
        old["commands"] = sorted({*old.get("commands", [old["command"]]), res["command"]})
        res = {**old, "date": res["date"]}
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    write_report(res, Path(args.report))
    say(f"wrote {args.out} and {args.report}")
    failed = [(db, n) for db, r in res["databases"].items() for n, f in r["faults"].items() if "error" in f]
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())

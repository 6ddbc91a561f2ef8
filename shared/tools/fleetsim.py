"""`mures fleet-sim`: the whole product on one machine, on loopback.

Starts a training server (or attaches to one with --server/--zenoh-connect/--token-file), a
simulated world that owns the hidden target (shared/tools/world.py), and N `robot-agent` processes
with the simulated backend; then flies M missions through the REST API, optionally retraining
every K missions over HTTP, and reports the capture times per policy version.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.files import read_token
from shared.core.graph import Graph
from shared.core.http import ApiClient, ApiError
from shared.core.models import Sensor, TargetModel
from shared.core.wire import zenoh_config
from shared.engine.evaluate import mean_ci95


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_until(pred: Any, timeout: float, what: str, every: float = 0.05) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        try:
            got = pred()
        except (OSError, ApiError, urllib.error.URLError):
            got = None
        if got:
            return got
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(every)


def reap(proc: subprocess.Popen[Any], timeout: float) -> int | None:
    """Wait up to ``timeout`` s for a signalled process to exit, and kill it if it has not: its exit
    status, or None where it had to be killed."""
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return None


class SimulatedOperator:
    """The operator of a simulated fleet under ``--capture confirm``: it confirms each pending
    detection whose robot really had the target in its detection set at that step (the world's
    truth) and dismisses the others as false alarms, through the REST API as a person would in the
    console. Polls every ``every`` seconds in a thread of its own until ``close``."""

    ACTOR = "fleet-sim simulated operator"  # what the audit log and the detections' decided_by say

    def __init__(self, api: ApiClient, world: Any, every: float = 0.02) -> None:
        # its own client: the same token, but every decision is recorded as the simulated operator's
        self.api = ApiClient(api.base, api.token, api.timeout, actor=self.ACTOR)
        self.api.context = api.context
        self.world, self.every = world, every
        self.decided: dict[str, int] = {"confirm": 0, "dismiss": 0}
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._loop, name="simulated-operator", daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while not self.stopping.wait(self.every):
            try:
                pending = self.api.get("/api/v1/detections?status=pending")["items"]
            except (OSError, ApiError):
                continue
            for d in pending:
                seen = self.world.seen(d["mission_id"], d["robot_id"], d["t"])
                if seen is None:
                    continue  # not a step of this world's (yet): look again next time
                verb = "confirm" if seen else "dismiss"
                try:
                    self.api.post(f"/api/v1/detections/{d['id']}/{verb}", {})
                    self.decided[verb] += 1
                except ApiError as exc:
                    if exc.status != 409:  # 409: the mission ended first
                        raise

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(5)


KILLED_RECORD_WAIT_S = 15.0  # how long a mission waits for the records of its killed robots, started again


@dataclass
class Fleet:
    """Handles of a running simulated fleet (server, world, agents)."""

    graph: Graph
    api: ApiClient
    zenoh_endpoint: str
    workdir: Path
    agent_token_file: Path
    server: subprocess.Popen | None = None
    agents: dict[str, subprocess.Popen] = field(default_factory=dict)
    session: Any = None
    world: Any = None
    log_dir: Path | None = None
    operator: SimulatedOperator | None = None

    def start_agent(self, robot: str, extra: list[str] | None = None) -> subprocess.Popen:
        assert self.log_dir is not None
        cmd = [
            sys.executable,
            "-m",
            "robot_agent.agent",
            "--robot-id",
            robot,
            "--server",
            self.api.base,
            "--zenoh-connect",
            self.zenoh_endpoint,
            "--token-file",
            str(self.agent_token_file),
            "--state-dir",
            str(self.workdir / "agents" / robot),
            "--backend",
            "sim",
            *(extra or []),
        ]
        log = open(self.log_dir / f"agent-{robot}.log", "ab")  # noqa: SIM115 - owned by the process
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=_child_env(agent=True))
        self.agents[robot] = proc
        return proc

    def stop_agent(self, robot: str, sig: int = signal.SIGTERM, timeout: float = 20.0) -> int | None:
        proc = self.agents.pop(robot)
        proc.send_signal(sig)
        return reap(proc, timeout)

    def online(self) -> list[str]:
        return [a["robot_id"] for a in self.api.get("/api/v1/fleet")["agents"] if a["online"]]

    def fly(self, robots: list[str], seed: int, timeout: float = 120.0, **extra: Any) -> dict[str, Any]:
        """Start a mission and wait until every robot's record is stored."""
        m = self.api.post("/api/v1/missions", {"robots": robots, "seed": seed, **extra})
        mid = m["id"]
        return wait_until(
            lambda: (r := self.api.get(f"/api/v1/missions/{mid}"))["status"] == "completed" and r,
            timeout,
            f"mission {mid}",
            every=0.01,
        )

    def fly_losing(
        self, robots: list[str], seed: int, kill: int, kill_by: int, timeout: float = 300.0, **extra: Any
    ) -> dict[str, Any]:
        """A mission in which ``kill`` of ``robots`` (drawn from the mission seed) are killed
        (SIGKILL: their liveliness goes, as a robot's that dies) each at a step drawn from 1..``kill_by``;
        they are started again once the others have finished (their journals send what they flew)
        and the mission (``extra``: more fields of its POST, its limits) is returned when every
        record is stored, with ``killed``: [robot, step]."""
        rng = np.random.default_rng([seed, 57])
        victims = [robots[i] for i in rng.choice(len(robots), size=kill, replace=False)]
        schedule = sorted(zip((int(s) for s in rng.integers(1, kill_by + 1, size=kill)), victims, strict=True))
        mid = self.api.post("/api/v1/missions", {"robots": robots, "seed": seed, **extra})["id"]
        world = self.world.missions
        killed = []
        for step, robot in schedule:
            wait_until(
                lambda step=step: mid in world and (world[mid].t >= step or world[mid].ended),
                timeout,
                "the step",
                every=0.002,
            )
            if world[mid].ended:
                break
            self.stop_agent(robot, signal.SIGKILL)
            killed.append([robot, world[mid].t])
        survivors = set(robots) - {r for r, _t in killed}
        wait_until(
            lambda: survivors <= set(self.api.get(f"/api/v1/missions/{mid}")["episodes_received"]),
            timeout,
            f"the records of mission {mid}'s robots left",
            every=0.02,
        )
        for robot, _t in killed:
            self.start_agent(robot)
        wait_until(
            lambda: {r for r, _t in killed} <= set(self.online()), 90, "the killed robots back online", every=0.1
        )
        try:  # a robot killed before its journal held a step has no record to send
            m = wait_until(
                lambda: (r := self.api.get(f"/api/v1/missions/{mid}"))["status"] == "completed" and r,
                KILLED_RECORD_WAIT_S,
                f"mission {mid}",
                every=0.02,
            )
        except TimeoutError:  # ended with the records there are: its robots are free for the next mission
            if self.api.get(f"/api/v1/missions/{mid}")["status"] == "running":
                self.api.post(f"/api/v1/missions/{mid}/stop", {})
            m = self.api.get(f"/api/v1/missions/{mid}")
        return {**m, "killed": killed}

    def close(self) -> None:
        if self.operator is not None:
            self.operator.close()
        for robot in list(self.agents):
            self.stop_agent(robot)
        if self.world is not None:
            self.world.close()
        if self.session is not None:
            self.session.close()
        if self.server is not None:
            self.server.send_signal(signal.SIGTERM)
            reap(self.server, 30)


def agent_rss_mb(pid: int) -> float:
    """Resident memory of a process in MB (VmRSS of /proc/<pid>/status; Linux)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise ValueError(f"no VmRSS for process {pid}")


def _child_env(agent: bool = False) -> dict[str, str]:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if agent:
        env.setdefault("OMP_NUM_THREADS", "1")  # agents do tiny numpy work; no thread pools
    return env


def start_server(
    graph_args: list[str],
    data_dir: Path,
    robots: int,
    sensor: Sensor | None,
    log_dir: Path,
    extra: list[str] | None = None,
    ca_file: str | None = None,
    zenoh_proto: str = "tcp",
) -> tuple[subprocess.Popen, str, str]:
    """A training-server process on free loopback ports: (process, base URL, zenoh endpoint).
    ``sensor`` None: the server's own defaults for its initial policy's sensor.
    With ``ca_file`` the server is expected to serve https (``extra`` holds --tls-cert/--tls-key);
    ``zenoh_proto`` "tls" listens on a tls/ endpoint (``extra`` holds --zenoh-tls-cert/--zenoh-tls-key)."""
    http_port, z_port = free_port(), free_port()
    endpoint = f"{zenoh_proto}/127.0.0.1:{z_port}"
    cmd = [
        sys.executable,
        "-m",
        "training_server",
        *graph_args,
        "--data-dir",
        str(data_dir),
        "--http",
        f"127.0.0.1:{http_port}",
        "--zenoh-listen",
        endpoint,
        "--robots",
        str(robots),
        *(
            []
            if sensor is None
            else ["--eta-fn", str(sensor.eta_fn), "--eta-fp", str(sensor.eta_fp), "--detection", sensor.detection]
        ),
        *(extra or []),
    ]
    log = open(log_dir / "server.log", "ab")  # noqa: SIM115 - owned by the process
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=_child_env())
    base = f"{'https' if ca_file else 'http'}://127.0.0.1:{http_port}"
    probe = ApiClient(base, None, ca_file=ca_file)

    def up() -> bool:
        if proc.poll() is not None:
            tail = (log_dir / "server.log").read_text(errors="replace")[-2000:]
            raise RuntimeError(f"training-server exited with status {proc.returncode}:\n{tail}")
        return probe.get("/api/v1/health")["status"] == "ok"

    wait_until(up, 90, "the training server to answer /api/v1/health", every=0.2)
    return proc, base, endpoint


def launch(
    graph: Graph,
    graph_args: list[str],
    target: TargetModel,
    sensor: Sensor,
    robots: int,
    workdir: Path,
    server: str | None = None,
    zenoh_connect: str | None = None,
    token_file: str | None = None,
    agent_token_file: str | None = None,
    step_delay: float = 0.0,
    step_timeout: float = 10.0,
    server_extra: list[str] | None = None,
    agent_extra: list[str] | None = None,
    simulated_operator: bool = True,
    building: Any = None,
    motion: Any = None,
) -> Fleet:
    """Start (or attach to) a server, the world and ``robots`` agents r1..rN; wait until all are online.
    With ``simulated_operator`` a ``SimulatedOperator`` decides the detections that await one. With
    ``building`` (shared/world/continuous.py) the world is the continuous one, its robots and target
    moving as ``motion`` says (shared/tools/timed_world.py), else the step world."""
    import zenoh

    from shared.tools.world import World

    workdir.mkdir(parents=True, exist_ok=True)
    log_dir = workdir / "logs"
    log_dir.mkdir(exist_ok=True)
    proc = None
    if server:
        if not (zenoh_connect and token_file):
            raise ValueError("--server needs --zenoh-connect and --token-file (the operator token)")
        base, endpoint = server, zenoh_connect
        op_token = read_token(token_file)
        agent_tok = Path(agent_token_file or token_file)
    else:
        data_dir = workdir / "server"
        proc, base, endpoint = start_server(graph_args, data_dir, robots, sensor, log_dir, server_extra)
        op_token = read_token(data_dir / "operator.token")
        agent_tok = data_dir / "agent.token"
    fleet = Fleet(
        graph=graph,
        api=ApiClient(base, op_token),
        zenoh_endpoint=endpoint,
        workdir=workdir,
        agent_token_file=agent_tok,
        server=proc,
        log_dir=log_dir,
    )
    try:
        health = fleet.api.get("/api/v1/health")
        if health["graph_id"] != graph.graph_id:
            raise ValueError(f"the server at {base} serves another map ({health['graph_id'][:20]}...)")
        fleet.session = zenoh.open(zenoh_config("client", connect=[endpoint]))
        if building is not None:
            from shared.tools.timed_world import TimedWorld

            fleet.world = TimedWorld(fleet.session, health["fleet"], building, sensor, motion, step_timeout)
        else:
            fleet.world = World(
                fleet.session, health["fleet"], graph, target, sensor, step_timeout=step_timeout, step_delay=step_delay
            )
        if simulated_operator:
            fleet.operator = SimulatedOperator(fleet.api, fleet.world)
        for i in range(robots):
            fleet.start_agent(f"r{i + 1}", agent_extra)
        want = {f"r{i + 1}" for i in range(robots)}
        wait_until(lambda: want <= set(fleet.online()), 90, f"{robots} agents to come online", every=0.2)
    except BaseException:
        fleet.close()
        raise
    return fleet


def _serve(fleet: Fleet, robots: int) -> None:
    """Keep server, world and agents up, saying where the console is, until SIGINT or SIGTERM."""
    server_dir = fleet.workdir / "server"
    op = server_dir / "operator.token" if fleet.server is not None else None
    print(
        f"fleet-sim: {robots} robots ready. Console: {fleet.api.base}/ ; sign in with the operator token"
        + (f" ({op})" if op else "")
        + f" or the agent token ({fleet.agent_token_file}) for a read-only view. Ctrl-C stops.",
        file=sys.stderr,
        flush=True,
    )

    def interrupt(*_a: Any) -> None:
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, interrupt)
    try:
        while True:
            if fleet.server is not None and fleet.server.poll() is not None:
                print(f"fleet-sim: the server exited ({fleet.server.returncode})", file=sys.stderr)
                return
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("fleet-sim: stopping", file=sys.stderr, flush=True)
    finally:
        signal.signal(signal.SIGTERM, old)


def fleet_mission_seed(seed: int, k: int) -> int:
    """The seed of fleet-sim --seed ``seed``'s mission k (from 0): the world's target path follows
    from it alone (shared/world/continuous.py ``target_generator``)."""
    return seed * 100_003 + k


def run_fleet_sim(
    graph: Graph,
    graph_args: list[str],
    target: TargetModel,
    sensor: Sensor,
    robots: int,
    missions: int,
    seed: int,
    retrain_every: int,
    retrain_params: dict[str, Any],
    workdir: Path | None,
    serve: bool = False,
    retrains: int | None = None,
    kill: int = 0,
    kill_by: int = 10,
    limits: dict[str, Any] | None = None,
    **launch_kw: Any,
) -> dict[str, Any]:
    """Fly ``missions`` missions and return the summary (see ``mures fleet-sim``), retraining
    every ``retrain_every`` missions (at most ``retrains`` times), killing ``kill`` robots in each
    at steps up to ``kill_by`` (``Fleet.fly_losing``); ``limits``: each mission's max_steps and
    max_seconds where given (POST /api/v1/missions; the server's defaults otherwise); with
    ``serve``, then keep the fleet up for the operator console until Ctrl-C (or SIGTERM)."""

    def say(text: str) -> None:  # progress on stderr, also beside --json's object on stdout
        print(text, file=sys.stderr, flush=True)

    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="mures-fleet-")
        workdir = Path(tmp.name)
    t0 = time.perf_counter()
    what = f"attaching to {launch_kw['server']}" if launch_kw.get("server") else "starting a server"
    say(f"fleet-sim: {what}, the world and {robots} agents on loopback (work dir {workdir})")
    fleet = launch(graph, graph_args, target, sensor, robots, workdir, **launch_kw)
    ids = [f"r{i + 1}" for i in range(robots)]
    results: list[dict[str, Any]] = []
    runs: list[dict[str, Any]] = []
    trials: list[dict[str, Any]] = []  # the new versions' trials beside the current one, as decided
    on_trial: int | None = None
    try:
        say(f"fleet-sim: {robots} agents online after {time.perf_counter() - t0:.1f} s; flying {missions} missions")
        for k in range(missions):
            mission_seed = fleet_mission_seed(seed, k)
            if kill:
                m = fleet.fly_losing(ids, mission_seed, kill, kill_by, **(limits or {}))
                results.append({**_mission_result(fleet, m), "killed": m["killed"]})
            else:
                results.append(_mission_result(fleet, fleet.fly(ids, seed=mission_seed, **(limits or {}))))
            if on_trial is not None:
                trial = _trial_decided(fleet, on_trial, say)
                if trial is not None:
                    trials.append(trial)
                    on_trial = None
            if (k + 1) % max(1, missions // 10) == 0 or k + 1 == missions:
                mean, half = mean_ci95([r["capture_time"] for r in results])
                say(f"fleet-sim: {k + 1}/{missions} missions, mean capture time {mean:.2f} ± {half:.2f}")
            due = retrain_every and (k + 1) % retrain_every == 0 and k + 1 < missions
            if due and (retrains is None or len(runs) < retrains):
                say(f"fleet-sim: retraining over HTTP after {k + 1} missions ({json.dumps(retrain_params)})")
                run = _retrain(fleet, {**retrain_params, "seed": seed + k}, say)
                runs.append({key: run[key] for key in ("id", "status", "version", "error", "metrics")})
                if run["status"] == "succeeded" and (run.get("progress") or {}).get("phase") == "canary":
                    on_trial = run["version"]
                    trial = fleet.api.get(f"/api/v1/policies/{on_trial}")["meta"].get("canary") or {}
                    say(
                        f"fleet-sim: version {on_trial} on trial: it flies every other mission beside version "
                        f"{trial.get('baseline')} for {trial.get('pairs')} pairs, then is kept or rolled back"
                    )
        if serve:
            since = time.time()
            _serve(fleet, robots)
            results += _missions_flown_since(fleet, since, {r["mission_id"] for r in results})
        stats = fleet.api.get("/api/v1/episodes/stats")
    finally:
        fleet.close()
        if tmp is not None:
            tmp.cleanup()
    mean, half = mean_ci95([r["capture_time"] for r in results])
    step_ms = np.asarray(fleet.world.step_seconds) * 1e3 if fleet.world else np.zeros(0)
    in_time = {}
    if results and all("capture_time_s" in r for r in results):  # the continuous world's clock
        mean_s, half_s = mean_ci95([r["capture_time_s"] for r in results])
        in_time = {"mean_capture_time_s": mean_s, "ci95_halfwidth_s": half_s}
    return {
        **in_time,
        "missions": len(results),
        "robots": robots,
        "map": graph.name,
        "seed": seed,
        "mean_capture_time": mean,
        "ci95": [mean - half, mean + half],
        "censored_fraction": float(np.mean([not r["captured"] for r in results])) if results else float("nan"),
        "episodes_stored": stats["stored"],
        "episodes_rejected": stats["rejected"],
        "policy_versions_used": sorted({r["policy_version"] for r in results}),
        "coordinated_share": _share([r["team_steps"] for r in results], [r["own_steps"] for r in results]),
        "by_policy_version": _by_version(results),
        "training_runs": runs,
        "trials": trials,
        "lockstep_step_ms_median": float(np.median(step_ms)) if len(step_ms) else None,
        "wall_seconds": round(time.perf_counter() - t0, 2),
        "results": results,
    }


def _missions_flown_since(fleet: Fleet, since: float, known: set[str]) -> list[dict[str, Any]]:
    """The missions started by others (the console, the REST API) since ``since`` and completed,
    oldest first, as summary lines: under --serve the summary counts what the operator flew."""
    out: list[dict[str, Any]] = []
    if fleet.server is not None and fleet.server.poll() is not None:
        return out  # the server is gone: nothing to ask
    try:
        items = fleet.api.get("/api/v1/missions?limit=1000")["items"]
    except (OSError, ApiError):
        return out
    for m in reversed(items):
        if m["created"] >= since and m["id"] not in known and m["status"] == "completed" and m["outcome"]:
            out.append(_mission_result(fleet, m))
    return out


def _mission_result(fleet: Fleet, m: dict[str, Any]) -> dict[str, Any]:
    """A flown mission's line in the summary: a censored mission counts its step limit (at a time
    limit: its last step); the robots' decisions on their team's plan (complete or partial) and on
    their own policies, from their records."""
    out = m["outcome"] or {}
    ct = out.get("capture_time")
    time_limited = m["params"].get("max_seconds") and out.get("steps") is not None  # its step limit a guard
    censored = out["steps"] if time_limited else m["params"]["max_steps"]
    team = own = 0
    for robot in m.get("episodes_received", m["robots"]):  # a robot killed before its first step sends none
        coordination = fleet.api.get(f"/api/v1/episodes/{robot}/{m['id']}").get("coordination") or {}
        team += coordination.get("team_steps", 0) + coordination.get("partial_steps", 0)
        own += coordination.get("own_steps", 0)
    seconds = {}
    if hasattr(fleet.world, "seconds"):  # the continuous world: the mission clock of the capture (or of its end)
        clock = wait_until(lambda: fleet.world.seconds.get(m["id"]), 10, f"mission {m['id']}'s end in the world")
        seconds = {"capture_time_s": clock["time_s"]}
    return {
        **seconds,
        "mission_id": m["id"],
        "captured": ct is not None,
        "capture_time": ct if ct is not None else censored,
        "policy_version": (out.get("policy_versions") or [m["policy_version"]])[0],
        "team_steps": team,
        "own_steps": own,
    }


def _trial_decided(fleet: Fleet, version: int, say: Callable[[str], None]) -> dict[str, Any] | None:
    """Version ``version``'s trial beside the current version once the server has decided it
    (kept or rolled back), else None."""
    trial = fleet.api.get(f"/api/v1/policies/{version}")["meta"].get("canary") or {}
    if trial.get("state") in (None, "flying"):
        return None
    evidence = (
        f": {trial['canary_mean']:.2f} vs {trial['baseline_mean']:.2f} steps for version "
        f"{trial['baseline']} over {trial['pairs']} pairs of missions"
        if "canary_mean" in trial
        else ""
    )
    say(f"fleet-sim: version {version} {trial['state']} after its trial{evidence}")
    return {"version": version, **trial}


def _retrain(fleet: Fleet, params: dict[str, Any], say: Callable[[str], None]) -> dict[str, Any]:
    """A training run over HTTP, as an operator starts one, followed to its end (an hour at most)."""
    run = fleet.api.post("/api/v1/training-runs", params)
    last = [""]

    def finished() -> dict[str, Any] | None:
        r = fleet.api.get(f"/api/v1/training-runs/{run['id']}")
        prog = r.get("progress") or {}
        line = f"{prog.get('phase', '')} {prog.get('episodes', '')}/{prog.get('total', '')}"
        if line != last[0] and prog.get("phase") in ("em", "gate", "train"):
            last[0] = line
            if prog.get("phase") != "train" or prog.get("episodes", 0) >= prog.get("total", 1):
                say(f"fleet-sim:   {prog.get('phase')}: {prog.get('message') or line}")
        return r if r["status"] in ("succeeded", "failed", "cancelled") else None

    r = wait_until(finished, 3600, f"training run {run['id']}", every=0.25)
    say(
        f"fleet-sim: run {r['id']} {r['status']}"
        + (f": version {r['version']}" if r["version"] else f" ({r['error']})")
    )
    team = (r.get("metrics") or {}).get("team") or {}
    unit = ((r.get("metrics") or {}).get("gate") or {}).get("unit", "steps")  # or ticks, on the clock
    if "team_mean_capture_time" in team:
        say(
            f"fleet-sim:   team searcher {team['team_searcher']}: on {team['episodes']} episodes the team "
            f"captured in {team['team_mean_capture_time']:.2f} {unit}, the policy alone in "
            f"{team['alone_mean_capture_time']:.2f} "
            f"(paired {team['paired_difference']:+.2f} ± {team['paired_ci95']:.2f})"
        )
    return r


def _share(team: list[int], own: list[int]) -> float | None:
    """The share of robot-steps flown on the team's plan (None when no step is counted)."""
    total = sum(team) + sum(own)
    return sum(team) / total if total else None


def _by_version(results: list[dict[str, Any]]) -> dict[str, Any]:
    """The missions' capture times per policy version that flew them."""
    by_version: dict[str, Any] = {}
    for v in sorted({r["policy_version"] for r in results}):
        x = [r["capture_time"] for r in results if r["policy_version"] == v]
        mv, hv = mean_ci95(x)
        by_version[str(v)] = {
            "missions": len(x),
            "mean_capture_time": mv,
            "ci95_halfwidth": hv,
            "censored_fraction": float(np.mean([not r["captured"] for r in results if r["policy_version"] == v])),
            "coordinated_share": _share(
                [r["team_steps"] for r in results if r["policy_version"] == v],
                [r["own_steps"] for r in results if r["policy_version"] == v],
            ),
        }
    return by_version

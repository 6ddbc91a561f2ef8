"""A real robot's detection ends a search: robot-agent processes with a backend that is not the
fleet simulator (tests/scripted_backend.py), a training server under --capture auto and confirm,
and the operator's decisions over the REST API."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from shared.core.files import read_token
from shared.core.http import ApiClient, ApiError
from shared.core.models import Sensor
from shared.tools.fleetsim import _child_env, reap, start_server, wait_until

pytestmark = pytest.mark.slow

TESTS = Path(__file__).resolve().parent
BACKEND = "scripted_backend:ScriptedBackend"


@pytest.fixture(scope="module")
def robots(tmp_path_factory):
    """A server (capture auto by default: the sensor has no false positives) and agents r1, r2 on
    the scripted backend: r1 reads z = 1 at t = 5, r2 at t = 5 and 7, r1 again at t = 12."""
    work = tmp_path_factory.mktemp("capture")
    (work / "logs").mkdir()
    proc, base, endpoint = start_server(["--env", "office"], work / "server", 2, Sensor(), work / "logs")
    api = ApiClient(base, read_token(work / "server" / "operator.token"))
    env = _child_env(agent=True)
    env["PYTHONPATH"] = f"{TESTS}:{env['PYTHONPATH']}"
    env["MURES_TEST_DETECT"] = "r1:5,r2:5,r2:7,r1:12"
    env["MURES_TEST_STEP_S"] = "0.05"
    agents = []
    for r in ("r1", "r2"):
        cmd = [
            sys.executable,
            "-m",
            "robot_agent.agent",
            "--robot-id",
            r,
            "--server",
            base,
            "--zenoh-connect",
            endpoint,
        ]
        cmd += [
            "--token-file",
            str(work / "server" / "agent.token"),
            "--state-dir",
            str(work / r),
            "--backend",
            BACKEND,
        ]
        log = open(work / "logs" / f"{r}.log", "ab")  # noqa: SIM115 - owned by the process
        agents.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env))
    online = lambda: {a["robot_id"] for a in api.get("/api/v1/fleet")["agents"] if a["online"]}  # noqa: E731
    wait_until(lambda: online() >= {"r1", "r2"}, 90, "two agents online", every=0.2)
    api.work, api.env, api.endpoint = work, env, endpoint  # for the tests that start more agents
    yield api
    for p in agents:
        p.terminate()
        reap(p, 20)
    proc.terminate()
    reap(proc, 30)


def _done(api, mid, timeout=60):
    return wait_until(
        lambda: (m := api.get(f"/api/v1/missions/{mid}"))["status"] == "completed" and m, timeout, mid, every=0.05
    )


def test_auto_a_detection_ends_the_mission_as_captured(robots):
    api = robots
    m = api.post("/api/v1/missions", {"robots": ["r1", "r2"], "seed": 1, "max_steps": 40})
    assert m["params"]["capture"] == "auto"  # the sensor has no false positives
    done = _done(api, m["id"])
    # both read z = 1 at t = 5 (each on its own clock: these robots are not in lockstep): the
    # mission is captured at 5 by one of them, and the other's detection is recorded and closed
    assert done["outcome"]["captured"] and done["outcome"]["capture_time"] == 5
    by = done["event"]["captured_by"]
    assert by in ("r1", "r2") and done["outcome"]["captured_by"] == by
    dets = api.get(f"/api/v1/detections?mission_id={m['id']}")["items"]
    assert [(d["robot_id"], d["t"], d["decided_by"]) for d in dets if d["status"] == "confirmed"] == [(by, 5, "auto")]
    assert all(d["status"] == "closed" for d in dets if (d["robot_id"], d["t"]) != (by, 5))
    assert next(d["decided_by"] for d in dets if d["robot_id"] == "r1") == "auto"
    for r in ("r1", "r2"):  # the records end at the capture
        rec = api.get(f"/api/v1/episodes/{r}/{m['id']}")
        assert len(rec["steps"]) == 6 and rec["outcome"]["capture_time"] == 5


def test_confirm_waits_for_the_operator_and_a_dismissal_lets_the_search_go_on(robots):
    api = robots
    m = api.post("/api/v1/missions", {"robots": ["r1", "r2"], "seed": 2, "max_steps": 200, "capture": "confirm"})
    pending = wait_until(
        lambda: (d := api.get("/api/v1/detections?status=pending")["items"]) and len(d) >= 3 and d, 30, "detections"
    )
    assert sorted((d["robot_id"], d["t"]) for d in pending[:3]) == [("r1", 5), ("r2", 5), ("r2", 7)]
    assert api.get(f"/api/v1/missions/{m['id']}")["status"] == "running"  # waits for the operator
    alerts = api.get("/api/v1/alerts")["items"]
    assert {a["subject"] for a in alerts if a["kind"] == "detection"} >= {str(d["id"]) for d in pending[:3]}
    by = {(d["robot_id"], d["t"]): d["id"] for d in pending}
    assert api.post(f"/api/v1/detections/{by['r1', 5]}/dismiss", {})["status"] == "dismissed"
    with pytest.raises(ApiError) as again:  # decided once
        api.post(f"/api/v1/detections/{by['r1', 5]}/confirm", {})
    assert again.value.status == 409
    api.post(f"/api/v1/detections/{by['r2', 5]}/dismiss", {})
    assert api.get(f"/api/v1/missions/{m['id']}")["status"] == "running"  # a false alarm ends nothing
    confirmed = api.post(f"/api/v1/detections/{by['r2', 7]}/confirm", {})
    assert confirmed["status"] == "confirmed" and confirmed["decided_by"] == "operator"
    done = _done(api, m["id"])
    assert done["outcome"]["capture_time"] == 7 and done["event"]["captured_by"] == "r2"
    statuses = {
        (d["robot_id"], d["t"]): d["status"] for d in api.get(f"/api/v1/detections?mission_id={m['id']}")["items"]
    }
    assert statuses[("r1", 5)] == "dismissed" and statuses[("r2", 7)] == "confirmed"
    # r1's record: its dismissed z = 1 at t = 5 is a false alarm before the capture at 7
    rec = api.get(f"/api/v1/episodes/r1/{m['id']}")
    assert rec["outcome"] == {"captured": True, "capture_time": 7, "captured_by": "r2"} and rec["steps"][5]["z"] == 1


def test_a_mission_the_robots_end_at_their_step_limit_says_when_and_after_how_many_steps(robots):
    api = robots

    def counted() -> int:
        items = api.get("/api/v1/policies/performance")["items"]
        return items[0]["missions"] if items else 0

    before = counted()
    m = api.post("/api/v1/missions", {"robots": ["r1", "r2"], "seed": 3, "max_steps": 4})
    done = _done(api, m["id"])
    assert done["outcome"]["captured"] is False and done["outcome"]["steps"] == 4
    assert done["ended"] is not None and done["event"]["reason"] == "step limit"
    assert counted() == before + 1  # a miss at the step limit counts too (its limit)


def test_an_unloadable_backend_ends_the_agent_with_one_line_and_status_2(tmp_path):
    cmd = [sys.executable, "-m", "robot_agent.agent", "--robot-id", "r1", "--server", "http://127.0.0.1:9"]
    for backend, words in (
        ("nosuch:Thing", "cannot load"),
        ("robot_agent.examples.nav_goal", "MODULE:CLASS"),
        ("robot_agent.backend:Nothing", "cannot load"),
    ):
        out = subprocess.run(
            [*cmd, "--zenoh-connect", "tcp/127.0.0.1:9", "--state-dir", str(tmp_path), "--backend", backend],
            capture_output=True,
            text=True,
            timeout=60,
            env=_child_env(agent=True),
        )
        lines = out.stderr.strip().splitlines()
        assert out.returncode == 2 and len(lines) == 1 and lines[0].startswith("robot-agent: error:"), out.stderr
        assert words in lines[0], lines[0]


def test_deploys_default_backend_refuses_to_start_and_the_fleet_shows_why(robots):
    """deploy/'s example backend is an adapter to subclass: launched as it is, the agent stops with
    one line and status 2 (systemd does not restart it: RestartPreventExitStatus=2), and the fleet
    view says why the robot is down."""
    api = robots
    cmd = [sys.executable, "-m", "robot_agent.agent", "--robot-id", "r3", "--server", api.base]
    cmd += ["--zenoh-connect", api.endpoint, "--token-file", str(api.work / "server" / "agent.token")]
    cmd += ["--state-dir", str(api.work / "r3"), "--backend", "robot_agent.examples.nav_goal:NavGoalBackend"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=api.env)
    last = out.stderr.strip().splitlines()[-1]
    assert out.returncode == 2 and last.startswith("robot-agent: error: --backend"), out.stderr[-2000:]
    assert "adapter to subclass" in last
    r3 = wait_until(
        lambda: next(
            (a for a in api.get("/api/v1/fleet")["agents"] if a["robot_id"] == "r3" and not a["online"]), None
        ),
        30,
        "r3 to show as down",
    )
    assert "adapter to subclass" in (r3["down_reason"] or "")


def test_within_the_capture_window_the_earliest_step_wins_then_the_robot_listed_first():
    """Under --capture auto the server decides CAPTURE_WINDOW_S after the first detection, from all
    that arrived by then: so robots flying in lockstep (fleet-sim) give the same outcome whatever
    order their detections arrive in."""
    from types import SimpleNamespace

    from training_server.bus import Bus

    bus = object.__new__(Bus)  # the decision alone, without a Zenoh session
    decided: list[tuple[str, int, str]] = []
    bus.server = SimpleNamespace(capture=lambda det, by: decided.append((det["robot_id"], det["t"], by)))
    found = [(6, 0, {"robot_id": "r1", "t": 6}), (5, 2, {"robot_id": "r3", "t": 5}), (5, 1, {"robot_id": "r2", "t": 5})]
    bus.capturing = {"m-1": (0.0, found), "m-2": (float("inf"), [(1, 0, {"robot_id": "r1", "t": 1})])}
    bus._decide_captures()
    assert decided == [("r2", 5, "auto")]
    assert list(bus.capturing) == ["m-2"]  # its window is still open


def _agent(api, robot, *extra, env=None):
    cmd = [sys.executable, "-m", "robot_agent.agent", "--robot-id", robot, "--server", api.base]
    cmd += ["--zenoh-connect", api.endpoint, "--token-file", str(api.work / "server" / "agent.token")]
    cmd += ["--state-dir", str(api.work / robot), *extra]
    log = open(api.work / "logs" / f"{robot}.log", "ab")  # noqa: SIM115 - owned by the process
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env or api.env)


def test_a_backend_that_breaks_the_contract_withdraws_its_robot_and_nothing_stays_stuck(robots):
    """A backend whose begin() returns None, or whose detect() returns the string "1", or whose
    move() raises: the agent withdraws that robot from the mission with a one-line reason and stays
    up; the server ends the robot's part at once, ends a mission no robot is left flying, and the
    robot can fly the next mission."""
    api = robots
    env = {**api.env, "MURES_TEST_FAULT": "r5:begin-none,r6:detect-string,r7:move-raises"}
    procs = [_agent(api, r, "--backend", BACKEND, env=env) for r in ("r5", "r6", "r7")]
    try:
        online = lambda: {a["robot_id"] for a in api.get("/api/v1/fleet")["agents"] if a["online"]}  # noqa: E731
        wait_until(lambda: online() >= {"r5", "r6", "r7"}, 90, "r5-r7 online", every=0.2)
        # r5 alone: withdrawn before z_0, so the mission ends at once, not at its deadline
        m = api.post("/api/v1/missions", {"robots": ["r5"], "seed": 4, "max_steps": 40})
        done = _done(api, m["id"], timeout=30)
        assert done["event"]["type"] == "stop" and done["event"]["reason"].startswith("no robot left: r5 withdrew")
        why = done["withdrawn"]["r5"]
        assert why["steps"] == 0 and "begin() returned None" in why["reason"]
        assert "expected a node label" in why["reason"]
        r5 = wait_until(
            lambda: next(
                (a for a in api.get("/api/v1/fleet")["agents"] if a["robot_id"] == "r5" and a.get("last_failure")), None
            ),
            20,
            "r5's failure in the fleet view",
        )
        assert r5["online"] and r5["state"] == "idle" and r5["last_failure"]["mission_id"] == m["id"]
        again = api.post("/api/v1/missions", {"robots": ["r5"], "seed": 5, "max_steps": 40})  # not 409: r5 is free
        assert _done(api, again["id"], timeout=30)["withdrawn"]["r5"]["steps"] == 0
        # r1 flies on while r6 (detect() -> "1" from t = 2) and r7 (move() raises) withdraw
        m = api.post("/api/v1/missions", {"robots": ["r1", "r6", "r7"], "seed": 6, "max_steps": 40})
        done = _done(api, m["id"], timeout=60)
        assert done["outcome"]["captured"] and done["event"]["captured_by"] == "r1"  # r1 reads z = 1 at t = 5
        assert "detect() returned '1' (str); expected 0 or 1" in done["withdrawn"]["r6"]["reason"]
        assert done["withdrawn"]["r6"]["steps"] == 2
        assert "move() raised OSError: the base controller is not answering" in done["withdrawn"]["r7"]["reason"]
        rec = api.get(f"/api/v1/episodes/r7/{m['id']}")  # the steps it flew are kept
        assert len(rec["steps"]) == 3 and not rec["outcome"]["captured"]
        assert all(p.poll() is None for p in procs)  # every agent is still up
    finally:
        for p in procs:
            p.terminate()
            reap(p, 20)
    log = (api.work / "logs" / "r5.log").read_text()
    assert "Traceback" not in log and "withdrawn after 0 steps" in log


def test_a_backend_module_in_the_working_directory_or_a_file_path_loads(tmp_path):
    """--backend MODULE:CLASS finds a module in the folder the agent starts from (no PYTHONPATH),
    and --backend path/to/file.py:CLASS loads that file; a module it cannot find says where it looked."""
    from robot_agent.backend import resolve_backend

    (tmp_path / "printbot_here.py").write_text(
        "class PrintBot:\n    def begin(self, m): return 0\n    def detect(self): return 0\n"
        "    def move(self, g): return g\n    def end(self): pass\n"
    )
    assert resolve_backend(f"{tmp_path / 'printbot_here.py'}:PrintBot").__name__ == "PrintBot"
    code = "from robot_agent.backend import resolve_backend as r; print(r('printbot_here:PrintBot').__name__)"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert out.stdout.strip() == "PrintBot", out.stderr
    with pytest.raises(ValueError, match=r"working directory .*PYTHONPATH"):
        resolve_backend("printbot_nowhere:PrintBot")


def test_checked_backend_refuses_what_breaks_the_contract():
    from robot_agent.backend import BackendError, CheckedBackend, MissionOver
    from shared.core.graph import builtin_graph

    graph = builtin_graph("office")

    class Bad:
        def __init__(self, begin, z):
            self.b, self.z = begin, z

        def begin(self, mission):
            return self.b

        def detect(self):
            if self.z == "over":
                raise MissionOver
            return self.z

        def move(self, goal):
            return goal

        def end(self):
            pass

    ok = CheckedBackend(Bad(int(graph.labels[0]), True), graph)
    assert ok.begin({}) == int(graph.labels[0]) and ok.detect() == 1
    for begin, words in ((None, "returned None"), (True, "returned True"), (10**6, "not on the map"), ("3", "'3'")):
        with pytest.raises(BackendError, match=words):
            CheckedBackend(Bad(begin, 0), graph).begin({})
    for z in ("1", 2, 0.5, None):
        with pytest.raises(BackendError, match="expected 0 or 1"):
            CheckedBackend(Bad(0, z), graph).detect()
    with pytest.raises(MissionOver):
        CheckedBackend(Bad(0, "over"), graph).detect()
    # a backend that is not the simulated world's is not told the team's wait nor asked a world's clock
    ok.tell_team_wait(0.5)
    assert not hasattr(ok.backend, "wait_s") and ok.world_clock(0.1) is None and ok.clock() is None

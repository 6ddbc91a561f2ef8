"""The continuous world served to robot agents (shared/tools/timed_world.py): each robot on its own
clock, readings answered in the order of the mission clock whatever order the reports come in, and
the whole fleet (server, agents, records) flown in it by `mures fleet-sim --world`."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest
from test_continuous_world import _two_rooms
from test_floorplan import NAV2, mures

from shared.core.clock import move_seconds
from shared.core.graph import load_graph_file
from shared.core.models import Sensor, uniform_walk
from shared.floorplan.occupancy import read_map
from shared.tools.fleetsim import fleet_mission_seed
from shared.tools.timed_world import Motion, TimedWorld
from shared.world.continuous import building, fly


class _Session:
    """What World needs of a Zenoh session, for driving it by hand: declarations that do nothing,
    puts kept."""

    def __init__(self) -> None:
        self.puts: list[tuple[str, dict]] = []

    def declare_subscriber(self, *_a, **_k):
        return self

    declare_queryable = declare_subscriber

    def undeclare(self) -> None:
        pass

    def put(self, key, payload, **_k) -> None:
        self.puts.append((str(key), json.loads(payload)))


class _Query:
    """A robot's report (t, node) on mures/<fleet>/sim/<mission>/<robot>, and the world's answer."""

    def __init__(self, mission: str, robot: str, t: int, node: int, **extra) -> None:
        self.key_expr = f"mures/default/sim/{mission}/{robot}"
        body = json.dumps({"t": t, "node": node, **extra}).encode()
        self.payload = type("P", (), {"to_bytes": lambda _s: body})()
        self.answer: dict | None = None
        self.error: str | None = None

    def reply(self, _key, payload) -> None:
        self.answer = json.loads(payload)

    def reply_err(self, payload) -> None:
        self.error = payload.decode()

    def drop(self) -> None:
        pass


def _world(tmp_path, **motion):
    grid, graph = _two_rooms(tmp_path)
    world = TimedWorld(_Session(), "default", building(grid, graph, 20.0), Sensor(), Motion(**motion), 60.0)
    world.close()  # its event thread stopped: the test calls its handlers itself
    return world, graph


def test_a_robot_asking_the_simulated_world_its_clock_is_told_which_it_keeps(tmp_path):
    from shared.core.wire import WORLD_CLOCK_PROBE
    from shared.tools.world import World

    timed, graph = _world(tmp_path)
    step = World(_Session(), "default", graph, uniform_walk(graph), Sensor())
    step.close()
    for world, clock in ((timed, "seconds"), (step, "steps")):
        q = _Query(WORLD_CLOCK_PROBE, "r1", 0, 0)
        world._on_query(q)
        assert q.answer == {"clock": clock} and q.error is None
        assert not world.parked  # not taken for a mission whose start is still on its way


def _start(world, mid: str, robots: list[str], seed: int, max_steps: int = 50) -> None:
    start = {"type": "start", "mission_id": mid, "robots": robots, "seed": seed, "max_steps": max_steps}
    world._on_message(json.dumps(start).encode())


def test_each_robot_reads_on_its_own_clock_and_waits_for_no_step_index(tmp_path):
    world, graph = _world(tmp_path)
    here, there = (int(x) for x in graph.labels[[graph.start, 1 - graph.start]])
    _start(world, "m1", ["r1", "r2"], seed=4)
    a0 = _Query("m1", "r1", 0, here)
    world._on_query(a0)
    assert a0.answer is None  # r2 may still read earlier: nothing is answered until it has reported
    b0 = _Query("m1", "r2", 0, here)
    world._on_query(b0)
    assert a0.answer["time_s"] == b0.answer["time_s"] == 0.0  # read together at the start
    a1 = _Query("m1", "r1", 1, there)  # r1 crosses to the other room: its length along free space at 0.5 m/s
    world._on_query(a1)
    walk = world.building.length_m[world.building.edge_of[graph.start, 1 - graph.start]] / 0.5
    assert walk > 10  # two rooms of 6 m, through a door at the top
    b = [_Query("m1", "r2", t, here) for t in range(1, 30)]  # r2 stays: a second a step
    for q in b:
        world._on_query(q)
        if a1.answer is not None:
            break
    # r2's steps 1..k came first, each a second apart, while r1 was still on its way; r1 read on arrival
    done = [q for q in b if q.answer is not None]
    assert [q.answer["time_s"] for q in done] == pytest.approx(list(range(1, len(done) + 1)))
    assert a1.answer["time_s"] == pytest.approx(walk, abs=1e-3)
    assert len(done) >= int(walk) - 1
    m = world.missions["m1"]
    assert m.next_t == {"r1": 2, "r2": len(done) + 1}  # their step counts apart, as real robots' are
    # a move to a node outside N[p] or a step out of order is refused, and changes nothing
    bad = _Query("m1", "r1", 5, here)
    world._on_query(bad)
    assert "not robot r1's next" in bad.error and m.next_t["r1"] == 2


@pytest.mark.parametrize("wait_s", [0.0, 0.5, None])
def test_robots_arriving_close_together_are_answered_together_only_within_the_earliest_ones_wait(tmp_path, wait_s):
    world, graph = _world(tmp_path)
    here = int(graph.labels[graph.start])
    _start(world, "m1", ["r1", "r2"], seed=4)
    said = {} if wait_s is None else {"wait_s": wait_s}  # an agent that says nothing: the step rule's 0.5 s
    for r in ("r1", "r2"):
        world._on_query(_Query("m1", r, 0, here, **said))
    m = world.missions["m1"]
    a1 = _Query("m1", "r1", 1, here, **said)
    world._on_query(a1)
    m.due_s["r1"] = 1.3  # r1 reads 0.3 s after r2 (both stay: r2's reading is at 1 s)
    b1 = _Query("m1", "r2", 1, here, **said)
    world._on_query(b1)
    assert b1.answer["time_s"] == pytest.approx(1.0)
    if wait_s == 0.0:  # r2 decides at once: r1 is answered after r2's next report, and hears of r2's move
        assert a1.answer is None
        world._on_query(_Query("m1", "r2", 2, here, **said))
        assert a1.answer["time_s"] == pytest.approx(1.3) and world.missions["m1"].next_t["r2"] == 2
    else:  # r2 waits up to 0.5 s for its teammates' observations: r1's is answered with it
        assert a1.answer["time_s"] == pytest.approx(1.3)
    bad = _Query("m1", "r1", 2, here, wait_s=-1)
    world._on_query(bad)
    assert "wait_s must be seconds" in bad.error and "r1" not in m.reports


def test_a_move_held_up_takes_its_stop_on_top_of_its_travel_time(tmp_path):
    world, graph = _world(tmp_path, stop_prob=1.0, stop_s=30.0)
    here, there = graph.start, 1 - graph.start
    walk = world.building.length_m[world.building.edge_of[here, there]] / 0.5
    _start(world, "m1", ["r1"], seed=4)
    m = world.missions["m1"]
    held = [world._travel_s(m, "r1", here, there) - walk for _ in range(400)]
    assert min(held) > 0 and np.mean(held) == pytest.approx(30.0, rel=0.15)  # every move, 30 s on average
    assert world._travel_s(m, "r1", here, here) == 1.0  # a stay is not held up
    (tmp_path / "free").mkdir()
    free, _graph = _world(tmp_path / "free")
    _start(free, "m1", ["r1"], seed=4)
    assert free._travel_s(free.missions["m1"], "r1", here, there) == pytest.approx(walk)


def test_the_same_seed_reads_the_same_whatever_order_the_reports_come_in(tmp_path):
    def fly(order: list[str]) -> tuple[list[tuple], dict]:
        world, graph = _world(tmp_path, speed_cv=0.3)
        labels = [int(x) for x in graph.labels]
        _start(world, "m", ["r1", "r2"], seed=9, max_steps=12)  # a robot at its step limit reads no more
        rng = np.random.default_rng(1)
        plan = {r: [labels[graph.start]] + [labels[int(k)] for k in rng.integers(0, 2, 12)] for r in ("r1", "r2")}
        asked: dict[str, _Query] = {}
        answers: list[tuple] = []
        for _ in range(100):
            for r in order:  # each robot reports its next step as soon as its last is answered
                last = asked.get(r)
                if last is not None and last.answer is None:
                    continue
                t = 0 if last is None else json.loads(last.payload.to_bytes())["t"] + 1
                if last is not None and (r, t - 1) not in {(a[0], a[1]) for a in answers}:
                    answers.append((r, t - 1, last.answer["z"], last.answer["time_s"]))
                if t < len(plan[r]):
                    asked[r] = _Query("m", r, t, plan[r][t])
                    world._on_query(asked[r])
        return sorted(answers), world.seconds["m"]

    first, end = fly(["r1", "r2"])
    assert (first, end) == fly(["r2", "r1"]) and len(first) == 26
    assert {z for _r, _t, z, _s in first} == {0, 1}  # the target was seen, and missed
    # every robot read its step limit: the mission is over in the world, not captured, at its last reading
    assert not end["captured"] and end["time_s"] == pytest.approx(max(s for *_x, s in first), abs=1e-3)


def test_fleet_sim_flies_the_agents_in_the_continuous_world(tmp_path):
    depot = NAV2 / "depot.yaml"
    graph_file, team = tmp_path / "depot.json", tmp_path / "team"
    assert mures("map", "import", str(depot), "--out", str(graph_file)).returncode == 0
    r = mures("train", "--graph", str(graph_file), "--robots", "2", "--episodes", "2000", "--team-searcher",
              "fhpe-sa", "--out", str(team))  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = mures("fleet-sim", "--graph", str(graph_file), "--world", str(depot), "--robots", "2", "--missions", "4",
              "--seed", "2", "--init-policy", str(team), "--speed-cv", "0.2", "--team-clock", "steps",
              "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["missions"] == 4 and res["episodes_stored"] == 8
    assert res["mean_capture_time_s"] >= 0 and res["ci95_halfwidth_s"] >= 0
    assert 0 < res["coordinated_share"] <= 1  # the version's team searcher flies, on the robots' own clocks
    world = building(read_map(depot), load_graph_file(graph_file), 4.0)
    fastest = min(1.0, world.length_m.min() / (0.5 * 2))  # a stay, or the shortest edge at twice the speed
    for m in res["results"]:
        assert m["capture_time_s"] >= m["capture_time"] * fastest - 1e-6  # steps take time
    assert np.mean([m["capture_time_s"] for m in res["results"]]) == pytest.approx(res["mean_capture_time_s"])
    # on the mission clock (fleet-sim's default with --world): the agents decide without waiting for
    # travelling teammates, and their records carry each reading's time, the capturing one's the
    # world's capture time; each mission is limited to 3 n moves of the median edge in time
    work = tmp_path / "on-the-clock"
    r = mures("fleet-sim", "--graph", str(graph_file), "--world", str(depot), "--robots", "2", "--missions", "4",
              "--seed", "2", "--init-policy", str(team), "--workdir", str(work), "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    timed = json.loads(r.stdout)
    assert timed["episodes_stored"] == 8 and 0 < timed["coordinated_share"] <= 1
    with sqlite3.connect(next((work / "server").glob("*.db"))) as db:
        records = [json.loads(row[0]) for row in db.execute("SELECT record FROM episodes")]
        events = {mid: json.loads(ev) for mid, ev in db.execute("SELECT id, event FROM missions")}
        limits = [json.loads(p) for (p,) in db.execute("SELECT params FROM missions")]
    graph = load_graph_file(graph_file)
    expected = round(3 * graph.n * move_seconds(graph, 0.5), 1)  # the graph file's median edge at 0.5 m/s
    assert [p["max_seconds"] for p in limits] == [expected] * 4 and all(p["max_steps"] == 100_000 for p in limits)
    assert len(records) == 8 and all("time_s" in step for rec in records for step in rec["steps"])
    by_mission = {(rec["mission_id"], rec["robot_id"]): rec for rec in records}
    for m in timed["results"]:
        if m["captured"]:
            by = next(rec["outcome"]["captured_by"] for (mid, _r), rec in by_mission.items()
                      if mid == m["mission_id"] and rec["outcome"]["captured"])  # fmt: skip
            capturer = by_mission[m["mission_id"], by]
            assert capturer["steps"][capturer["outcome"]["capture_time"]]["time_s"] == pytest.approx(
                m["capture_time_s"], abs=1e-3
            )
            # the server's captured message (GET /api/v1/missions/{id}'s outcome.capture_time_s) says the moment
            assert events[m["mission_id"]]["time_s"] == pytest.approx(m["capture_time_s"], abs=1e-3)
            for robot in ("r1", "r2"):  # each robot's own readings up to the capture's moment, whatever its step count
                rec = by_mission[m["mission_id"], robot]
                assert rec["outcome"]["captured"] and rec["steps"][-1]["time_s"] <= m["capture_time_s"] + 1e-3


def test_a_first_version_on_the_clock_flies_the_batched_worlds_plan_mission_by_mission(tmp_path):
    """The server's first version (beliefs on the uniform walk, FHPE-SA on every observation heard)
    flown by robot-agent processes on the mission clock decides as the batched world's fhpe-sa
    searcher given every observation at once: on the same missions, the same capture times, to the
    batched world's 0.1 s ticks. Robots arriving close together are answered one after another, so
    each hears where the one before it is headed (a window of 0.5 s made this fleet 1.3 times later
    on this map with N = 4, its robots planning on teammates' stale goals)."""
    depot = NAV2 / "depot.yaml"
    graph_file = tmp_path / "depot.json"
    assert mures("map", "import", str(depot), "--out", str(graph_file)).returncode == 0
    r = mures("fleet-sim", "--graph", str(graph_file), "--world", str(depot), "--robots", "4", "--missions", "8",
              "--seed", "1", "--init-policy", "general", "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["coordinated_share"] == 1.0
    fleet = np.array([m["capture_time_s"] for m in res["results"]])
    graph = load_graph_file(graph_file)
    seeds = [fleet_mission_seed(1, k) for k in range(8)]
    plan = fly(building(read_map(depot), graph, 4.0), "fhpe-sa", 4, 8, mission_seeds=seeds).capture_s
    assert fleet.mean() > 10  # missions that take moves, not only captures at the start node
    assert np.abs(fleet - plan) == pytest.approx(np.zeros(8), abs=0.15), (fleet, plan)


def test_a_mission_on_the_clock_ends_at_its_time_limit_whatever_each_robots_step_count(tmp_path):
    depot = NAV2 / "depot.yaml"
    graph_file, work = tmp_path / "depot.json", tmp_path / "work"
    assert mures("map", "import", str(depot), "--out", str(graph_file)).returncode == 0
    r = mures("fleet-sim", "--graph", str(graph_file), "--world", str(depot), "--robots", "2", "--missions", "4",
              "--seed", "5", "--max-seconds", "12", "--speed-cv", "0.3", "--workdir", str(work),
              "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["missions"] == 4 and res["episodes_stored"] == 8
    with sqlite3.connect(next((work / "server").glob("*.db"))) as db:
        records = {(mid, robot): json.loads(rec) for mid, robot, rec in db.execute(
            "SELECT mission_id, robot_id, record FROM episodes")}  # fmt: skip
        events = {mid: json.loads(ev) for mid, ev in db.execute("SELECT id, event FROM missions")}
    timed_out = [m for m in res["results"] if not m["captured"]]
    assert timed_out, "a 12 s limit on the depot leaves some mission uncaptured"
    for m in timed_out:
        assert events[m["mission_id"]]["reason"] == "time limit"
        ends = []
        for robot in ("r1", "r2"):
            times = [step["time_s"] for step in records[m["mission_id"], robot]["steps"]]
            assert times[-1] >= 12 and all(x < 12 for x in times[:-1])  # each stops at its first reading past it
            ends.append(times[-1])
        assert m["capture_time_s"] == pytest.approx(max(ends), abs=1e-3)  # the world's clock at the mission's end
        assert m["capture_time"] == max(len(records[m["mission_id"], r]["steps"]) for r in ("r1", "r2")) - 1
    for m in res["results"]:
        if m["captured"]:
            assert m["capture_time_s"] < 12 + 1e-3 or events[m["mission_id"]]["type"] == "captured"
    # a time limit needs the mission clock of the continuous world
    r = mures("fleet-sim", "--graph", str(graph_file), "--robots", "2", "--missions", "1", "--max-seconds", "12")
    assert r.returncode == 2 and "--max-seconds goes with --world" in r.stderr


def test_fleet_sim_kill_in_the_continuous_world_keeps_the_missions_time_limit(tmp_path):
    """fleet-sim --kill: a robot of each mission killed (SIGKILL) at a step, the others fly on; its
    missions have the same limits as any (in the continuous world, the time limit)."""
    depot = NAV2 / "depot.yaml"
    graph_file, work = tmp_path / "depot.json", tmp_path / "work"
    assert mures("map", "import", str(depot), "--out", str(graph_file)).returncode == 0
    r = mures("fleet-sim", "--graph", str(graph_file), "--world", str(depot), "--robots", "3", "--missions", "2",
              "--kill", "1", "--kill-by", "3", "--seed", "4", "--workdir", str(work), "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["missions"] == 2 and all(len(m["killed"]) == 1 for m in res["results"])
    with sqlite3.connect(next((work / "server").glob("*.db"))) as db:
        limits = [json.loads(p) for (p,) in db.execute("SELECT params FROM missions")]
    graph = load_graph_file(graph_file)
    assert [p.get("max_seconds") for p in limits] == [round(3 * graph.n * move_seconds(graph, 0.5), 1)] * 2


def test_a_fleet_on_the_clock_retrains_over_http_on_its_timestamped_records_and_flies_a_team_trained_on_it(tmp_path):
    depot = NAV2 / "depot.yaml"
    graph_file, team = tmp_path / "depot.json", tmp_path / "team"
    assert mures("map", "import", str(depot), "--out", str(graph_file)).returncode == 0
    r = mures("fleet-sim", "--graph", str(graph_file), "--world", str(depot), "--robots", "2", "--missions", "4",
              "--seed", "2", "--team-clock", "seconds", "--retrain-every", "2", "--retrains", "1",
              "--retrain-episodes", "256", "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    run = json.loads(r.stdout)["training_runs"][0]
    metrics = run["metrics"]
    assert metrics["em"]["per"] == "1 s tick" and metrics["em"]["records"] == 2 and not metrics["em"]["skipped"]
    assert metrics["gate"]["unit"] == "ticks of 1 s" and metrics["gate"]["current"]["episodes"] == 1000
    assert run["status"] == "succeeded" or run["error"].startswith("evaluation gate: new policy"), run
    if run["status"] == "succeeded":  # the team's plan against the policy alone, both on the travel times
        assert metrics["team"]["decided_by"] == "comparison" and metrics["team"]["episodes"] == 200
    # a team trained on the clock flies on it without --team-clock: its records carry the readings' times
    r = mures("train", "--graph", str(graph_file), "--robots", "2", "--episodes", "256", "--em-first", "128",
              "--em-missions", "8", "--speed", "0.5", "--out", str(team), "--quiet")  # fmt: skip
    assert r.returncode == 0, r.stderr
    work = tmp_path / "clock-team"
    r = mures("fleet-sim", "--graph", str(graph_file), "--world", str(depot), "--robots", "2", "--missions", "2",
              "--seed", "3", "--init-policy", str(team), "--workdir", str(work), "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    with sqlite3.connect(next((work / "server").glob("*.db"))) as db:
        records = [json.loads(row[0]) for row in db.execute("SELECT record FROM episodes")]
    assert len(records) == 4 and all("time_s" in step for rec in records for step in rec["steps"])


def test_world_flags_that_do_not_fit_are_refused_in_one_line(tmp_path):
    depot = NAV2 / "depot.yaml"
    graph_file = tmp_path / "depot.json"
    assert mures("map", "import", str(depot), "--out", str(graph_file)).returncode == 0
    for args, says in (
        (["--env", "office", "--world", str(depot)], "--world goes with --graph"),
        (["--graph", str(graph_file), "--world", str(NAV2 / "warehouse.yaml")], "was not imported from"),
        (["--graph", str(graph_file), "--world", str(depot), "--step-delay", "1"], "--step-delay"),
    ):
        for command in ("fleet-sim", "world"):
            extra = ["--robots", "2", "--missions", "1"] if command == "fleet-sim" else []
            r = mures(command, *args, *extra)
            assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, (command, args, r.stderr)


def test_a_mission_started_over_rest_for_robots_on_the_clock_is_limited_in_time(tmp_path):
    """A server on an imported map, `mures world --world` and two `robot-agent --backend sim` started
    by hand, on `--team-clock auto`: they ask the world its clock and fly on the mission clock, and
    their telemetry says so, at 0.5 m/s; a mission an operator starts with no limit is then limited
    to 3 n moves of the median edge in time (the step limit a guard), the world keeps the same
    limit, and the mission completes on it with every reading timed."""
    import subprocess
    import sys
    from pathlib import Path

    from fleet_checks import stop_processes

    from shared.core.files import read_token
    from shared.core.http import ApiClient
    from shared.tools.fleetsim import start_server, wait_until

    depot = NAV2 / "depot.yaml"
    graph_file, logs, data = tmp_path / "depot.json", tmp_path / "logs", tmp_path / "data"
    logs.mkdir()
    assert mures("map", "import", str(depot), "--out", str(graph_file)).returncode == 0
    graph = load_graph_file(graph_file)
    proc, base, endpoint = start_server(["--graph", str(graph_file)], data, 2, Sensor(), logs)
    procs: list[subprocess.Popen] = []

    def launch(name: str, cmd: list[str]) -> None:
        log = open(logs / f"{name}.log", "w")  # noqa: SIM115 - owned by the process
        procs.append(subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT))

    try:
        mures_bin = str(Path(sys.executable).with_name("mures"))
        launch("world", [mures_bin, "world", "--graph", str(graph_file), "--world", str(depot),
                         "--zenoh-connect", endpoint])  # fmt: skip
        for robot in ("r1", "r2"):  # --team-clock auto: the world's clock
            launch(robot, [sys.executable, "-m", "robot_agent.agent", "--robot-id", robot, "--server", base,
                           "--zenoh-connect", endpoint, "--token-file", str(data / "agent.token"),
                           "--state-dir", str(tmp_path / robot)])  # fmt: skip
        api = ApiClient(base, read_token(data / "operator.token"))
        wait_until(lambda: "simulating fleet 'default'" in (logs / "world.log").read_text(), 60, "the world")
        wait_until(
            lambda: [a["speed"] for a in api.get("/api/v1/fleet")["agents"] if a["online"]] == [0.5, 0.5],
            60,
            "the agents' telemetry to say they fly on the clock",
        )
        m = api.post("/api/v1/missions", {"robots": ["r1", "r2"], "seed": 4})
        expected = round(3 * graph.n * move_seconds(graph, 0.5), 1)
        assert m["params"]["max_seconds"] == expected and m["params"]["max_steps"] == 100_000
        got = wait_until(
            lambda: (r := api.get(f"/api/v1/missions/{m['id']}"))["episodes_received"] == ["r1", "r2"] and r,
            120,
            "both records",
        )
        assert got["outcome"]["captured"] or got["event"]["reason"] == "time limit", got
        for robot in ("r1", "r2"):
            steps = api.get(f"/api/v1/episodes/{robot}/{m['id']}")["steps"]
            assert all("time_s" in s for s in steps) and steps[-1]["time_s"] < expected + 60
    finally:
        stop_processes(*procs, proc)

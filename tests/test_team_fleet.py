"""Robot-agent processes searching as a team over the fleet's Zenoh bus (robot_agent/teamwork.py):
with links up they fly the team's plan; a teammate killed mid-mission or a robot whose link is cut
never holds the others up: they drop the one whose liveliness went, fall back from a silent one,
and finish."""

from __future__ import annotations

import json
import signal

import pytest
from fleet_checks import long_mission

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.tools.cli import main
from shared.tools.fleetsim import launch, wait_until

pytestmark = pytest.mark.slow  # a server, the world and three agent processes

ROBOTS = ["r1", "r2", "r3"]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    team = tmp_path_factory.mktemp("team") / "snapshot"
    argv = ["train", "--env", "office", "--robots", "3", "--episodes", "256", "--belief", "true", "--quiet"]
    assert main([*argv, "--team-searcher", "fhpe-sa", "--out", str(team)]) == 0
    assert json.loads((team / "policy.json").read_text())["team_searcher"] == "fhpe-sa"
    graph = builtin_graph("office")
    f = launch(
        graph,
        ["--env", "office"],
        uniform_walk(graph),
        Sensor(),
        3,
        tmp_path_factory.mktemp("fleet"),
        step_timeout=3.0,
        server_extra=["--init-policy", str(team)],
    )
    yield f
    f.close()


def _records(fleet, mission_id, robots):
    return {r: fleet.api.get(f"/api/v1/episodes/{r}/{mission_id}") for r in robots}


def test_with_links_up_the_robots_fly_the_teams_plan(fleet):
    steps = {"team": 0, "own": 0}
    heard = sent = 0
    for seed in range(3):
        m = fleet.fly(ROBOTS, seed=seed, max_steps=40)
        for rec in _records(fleet, m["id"], ROBOTS).values():
            c = rec["coordination"]
            assert c["team_searcher"] == "fhpe-sa"
            assert c["team_steps"] + c["partial_steps"] + c["own_steps"] >= len(rec["steps"]) - 1
            steps["team"] += c["team_steps"]
            steps["own"] += c["partial_steps"] + c["own_steps"]
            heard, sent = heard + c["observations_heard"], sent + c["observations_sent"]
    # a teammate's t = 0 can come before a robot has subscribed (its own first step then falls
    # back); every later step is complete on loopback
    assert steps["team"] >= 0.8 * (steps["team"] + steps["own"]) > 0
    assert 0.8 * sent <= heard <= sent  # what the links delivered: nearly all of it


def test_a_teammate_killed_mid_mission_holds_nobody_up(fleet):
    fleet.world.step_delay = 0.05
    try:
        mid = long_mission(fleet, ROBOTS, 11)
        # the fleet view says how each flying robot decided its last step (its telemetry)
        modes = wait_until(
            lambda: [a.get("mode") for a in fleet.api.get("/api/v1/fleet")["agents"] if a.get("mode")],
            10,
            "the robots' modes",
        )
        assert set(modes) <= {"team", "partial", "own"}
        fleet.stop_agent("r2", signal.SIGKILL)
        # r2's liveliness goes: r1 and r3 drop it from their plan at once and go on as a team of
        # two (the world withdraws r2 after its step timeout), and finish
        wait_until(
            lambda: set(fleet.api.get(f"/api/v1/missions/{mid}")["episodes_received"]) == {"r1", "r3"},
            60,
            "r1 and r3 to report",
        )
    finally:
        fleet.world.step_delay = 0.0
    for rec in _records(fleet, mid, ["r1", "r3"]).values():
        c = rec["coordination"]
        # on the plan before the kill and after it, without r2
        assert c["teammates_dropped"] == 1 and c["team_steps"] >= len(rec["steps"]) - 3, c
    fleet.start_agent("r2")
    wait_until(lambda: "r2" in fleet.online(), 60, "r2 back online")


def test_a_robot_whose_link_is_cut_holds_nobody_up(fleet):
    """r1's observations never leave it (robot-agent --link-loss 1): r2 and r3 plan without it
    until they drop it, then for the two of them; the mission ends as any other."""
    fleet.stop_agent("r1")
    fleet.start_agent("r1", ["--link-loss", "1"])
    wait_until(lambda: "r1" in fleet.online(), 60, "r1 back online")
    try:
        fleet.world.step_delay = 0.02
        mid = long_mission(fleet, ROBOTS, 41)
        wait_until(lambda: fleet.api.get(f"/api/v1/missions/{mid}")["status"] == "completed", 60, "the mission")
    finally:
        fleet.world.step_delay = 0.0
    recs = _records(fleet, mid, ROBOTS)
    for r in ("r2", "r3"):
        c = recs[r]["coordination"]
        assert c["partial_steps"] >= 1 and c["team_steps"] >= 1  # r1 missing, then dropped
    assert sum(v for k, v in recs["r1"]["coordination"].items() if k.endswith("_steps")) >= 4


def test_a_retrain_decides_whether_its_version_flies_as_a_team(fleet):
    """team_searcher auto: the run flies the new policy alone and as a team on the same episodes
    and records what it chose and why; the version carries the choice, and its robots fly it."""
    run = fleet.api.post(
        "/api/v1/training-runs",
        {"episodes": 512, "seed": 2, "canary_pairs": 0, "min_missions": 3, "gate": False, "team_episodes": 30},
    )
    done = wait_until(
        lambda: (r := fleet.api.get(f"/api/v1/training-runs/{run['id']}"))["status"] not in ("queued", "running") and r,
        300,
        "the training run",
    )
    assert done["status"] == "succeeded", done
    team = done["metrics"]["team"]
    assert team["decided_by"] == "comparison" and team["episodes"] == 30
    # the gate's links lose what the fleet's lost: its team missions so far lost little
    links = team["links"]
    assert links["records"] >= 9 and 0.0 <= links["link_loss"] < 0.5 and 0.0 < links["coordinated_share"] <= 1.0
    better = team["paired_difference"] + team["paired_ci95"] < 0
    assert team["team_searcher"] == ("fhpe-sa" if better else "none")
    snapshot = fleet.workdir / "server" / "policies" / f"v{done['version']}" / "snapshot" / "policy.json"
    assert json.loads(snapshot.read_text())["team_searcher"] == team["team_searcher"]
    m = fleet.fly(ROBOTS, seed=7, max_steps=40)
    flown = {rec["coordination"]["team_searcher"] for rec in _records(fleet, m["id"], ROBOTS).values()}
    assert flown == {None if team["team_searcher"] == "none" else team["team_searcher"]}

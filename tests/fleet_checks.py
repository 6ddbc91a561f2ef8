"""Checks of a simulated fleet's records shared by the fleet tests (tests/ is on sys.path)."""

from __future__ import annotations

import signal
import subprocess

import numpy as np

from robot_agent.agent import mission_seed
from shared.core.models import Sensor
from shared.core.records import make_record
from shared.core.snapshot_format import PolicyAgent, read_snapshot
from shared.tools.fleetsim import wait_until


def stop_processes(*procs: subprocess.Popen) -> None:
    """Stop processes started by hand (agents, worlds, then their server), each with SIGTERM and up
    to 30 s to exit, in the order given."""
    for p in procs:
        p.send_signal(signal.SIGTERM)
        p.wait(30)


def snapshot_dir(fleet, version):
    """Where the server of a simulated fleet keeps policy version ``version``."""
    return fleet.workdir / "server" / "policies" / f"v{version}" / "snapshot"


def replay(fleet, robot, mission):
    """Re-decide a robot's mission from its own record only: its nodes and z's, the mission seed
    and its index; the policy of the record's version must choose exactly the recorded moves."""
    rec = fleet.api.get(f"/api/v1/episodes/{robot}/{mission['id']}")
    snap = read_snapshot(snapshot_dir(fleet, rec["policy_version"]), fleet.graph)  # what the agent reads
    g = fleet.graph
    index = mission["robots"].index(robot)
    agent = PolicyAgent(snap, g, index, seed=mission_seed(mission["params"]["seed"], index))
    steps = rec["steps"]
    for k, st in enumerate(steps):
        p = g.index[st["node"]]
        agent.reset(p, st["z"]) if k == 0 else agent.observe(p, st["z"])
        if k + 1 < len(steps):
            assert g.labels[agent.act(p)] == steps[k + 1]["node"], f"{robot} step {k} of {mission['id']}"
    return rec


def walk_record(graph, mission_id: str, steps: int, rng: np.random.Generator) -> dict:
    """Robot r1's record of a mission that walked ``steps`` random moves from the start and saw
    nothing (no capture): what a fleet's early missions look like to EM."""
    nodes = [graph.start]
    for _ in range(steps):
        nodes.append(int(rng.choice(graph.closed(nodes[-1]))))
    return make_record(
        graph,
        fleet="default",
        mission_id=mission_id,
        robot_id="r1",
        nodes=nodes,
        z=[0] * len(nodes),
        sensor=Sensor(),
        captured=False,
        capture_time=None,
        captured_by=None,
    )


def long_mission(fleet, robots: list[str], seed0: int, steps: int = 4, max_steps: int = 60) -> str:
    """The id of a mission of ``robots`` still running after ``steps`` steps (slow the world down
    first): seeds from ``seed0`` on, each mission that ended sooner left to complete."""
    world = fleet.world.missions
    for seed in range(seed0, seed0 + 30):
        mid = fleet.api.post("/api/v1/missions", {"robots": robots, "seed": seed, "max_steps": max_steps})["id"]
        wait_until(lambda mid=mid: mid in world and (world[mid].t >= steps or world[mid].ended), 30, f"{steps} steps")
        if not world[mid].ended:
            return mid
        wait_until(lambda mid=mid: fleet.api.get(f"/api/v1/missions/{mid}")["status"] == "completed", 30, "mission")
    raise AssertionError(f"no mission ran past {steps} steps")

"""Checks of a simulated fleet's records shared by the fleet tests (tests/ is on sys.path)."""

from __future__ import annotations

from robot_agent.agent import mission_seed
from shared.core.snapshot_format import PolicyAgent, read_snapshot


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

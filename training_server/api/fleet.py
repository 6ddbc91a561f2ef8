"""GET /api/v1/fleet: every robot heard of since the server started: online or dropped off (from
its liveliness token), flying or idle (from the running missions), and where it is and what policy
it runs (from its telemetry); and every robot whose credentials were revoked, as revoked."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

import training_server.credentials as credentials
from training_server.api.deps import READ, Srv, errors
from training_server.api.models import Agent, FleetOut

router = APIRouter(tags=["fleet"], dependencies=READ, responses=errors(401))


@router.get("/fleet")
def fleet(srv: Srv) -> FleetOut:
    return fleet_view(srv)


def fleet_view(srv: Any) -> FleetOut:
    heard = srv.bus.agents()
    busy = srv.store.busy_robots(srv.fleet)
    agents = []
    for robot, a in heard.items():
        live = a["live"] or {}
        mission = busy.get(robot)
        same = live.get("state") == "mission" and live.get("mission_id") == mission
        agents.append(
            Agent(
                robot_id=robot,
                online=a["online"],
                since=a["since"],
                last_seen=a["last_seen"],
                state="offline" if not a["online"] else "flying" if mission else "idle",
                mission_id=mission,
                step=live.get("t") if same else None,
                node=live.get("node"),
                policy_version=live.get("policy_version"),
                z=live.get("z") if same else None,
                mode=live.get("mode") if same and live.get("mode") in ("team", "partial", "own") else None,
                backend=live.get("backend"),
                speed=live.get("speed") if live.get("clock") == "seconds" else None,
                down_reason=live.get("reason") if live.get("state") == "down" and not a["online"] else None,
                last_failure=live.get("last_failure") if live.get("state") == "idle" and not mission else None,
            )
        )
    for robot, entry in credentials.revoked(srv.data_dir).items():  # listed as revoked, heard of or not
        known = next((a for a in agents if a.robot_id == robot), None)
        if known is None:
            known = Agent(robot_id=robot, online=False, since=None, last_seen=entry["revoked"], state="revoked")
            agents.append(known)
        known.state, known.revoked = "revoked", entry["revoked"]
    agents.sort(key=lambda a: a.robot_id)
    return FleetOut(fleet=srv.fleet, online=sum(a.online for a in agents), agents=agents)

"""GET /api/v1/fleet: the agents online (from their liveliness tokens)."""

from __future__ import annotations

from fastapi import APIRouter

from training_server.api.deps import READ, Srv, errors
from training_server.api.schemas import Agent, FleetOut

router = APIRouter(tags=["fleet"], dependencies=READ, responses=errors(401))


@router.get("/fleet")
def fleet(srv: Srv) -> FleetOut:
    online = srv.bus.agents_online()
    return FleetOut(
        fleet=srv.fleet,
        online=len(online),
        agents=[Agent(robot_id=r, since=s) for r, s in sorted(online.items())],
    )

"""GET /api/v1/map: the map the fleet searches (agents fetch it at start)."""

from __future__ import annotations

from fastapi import APIRouter

from training_server.api.deps import READ, Srv, errors
from training_server.api.schemas import MapOut

router = APIRouter(tags=["map"], dependencies=READ, responses=errors(401))


@router.get("/map")
def get_map(srv: Srv) -> MapOut:
    return MapOut(**srv.graph.to_json(), graph_id=srv.graph.graph_id)

"""GET /api/v1/map: the map the fleet searches (agents fetch it at start)."""

from __future__ import annotations

from fastapi import APIRouter

from training_server.api.deps import READ, Srv, errors
from training_server.api.models import MapLayout, MapOut

router = APIRouter(tags=["map"], dependencies=READ, responses=errors(401))


@router.get("/map")
def get_map(srv: Srv) -> MapOut:
    return MapOut(**srv.graph.to_json(), graph_id=srv.graph.graph_id)


@router.get("/map/layout")
def map_layout(srv: Srv) -> MapLayout:
    """Where to draw each node: the graph file's positions, or an automatic layout when it has none."""
    layout = getattr(srv, "_map_layout", None)
    if layout is None:
        from training_server.console.layout import node_layout

        layout = srv._map_layout = node_layout(srv.graph)
    positions, source = layout
    return MapLayout(positions={str(k): list(v) for k, v in positions.items()}, source=source)

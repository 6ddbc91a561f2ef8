"""GET /api/v1/map: the map the fleet searches (agents fetch it at start); its layout for drawing,
and the building's map image under it when the server has one (`training-server --map-image`)."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Response

from training_server.api.deps import READ, Srv, errors
from training_server.api.models import MapImage, MapLayout, MapOut

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
    picture = getattr(srv, "map_picture", None)
    image = None
    if picture is not None and layout.source == "file":
        x_min, y_min, x_max, y_max = picture.bounds
        left, top = layout.to_screen(x_min, y_max)
        image = MapImage(
            url="/api/v1/map/image",
            x=round(left, 5),
            y=round(top, 5),
            width=round((x_max - x_min) / layout.span, 5),
            height=round((y_max - y_min) / layout.span, 5),
        )
    return MapLayout(
        positions={str(k): list(v) for k, v in layout.positions.items()}, source=layout.source, image=image
    )


@router.get(
    "/map/image",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "the building's map"}, **errors(404)},
)
def map_image(srv: Srv) -> Response:
    """The building's occupancy map as a PNG (free white, occupied black, unknown grey), to draw
    under the graph where `GET /api/v1/map/layout` says; 404 when the server has none."""
    picture = getattr(srv, "map_picture", None)
    if picture is None:
        raise HTTPException(404, "this server has no map image (training-server --graph G.json --map-image MAP.yaml)")
    return Response(picture.png, media_type="image/png", headers={"Cache-Control": "private, max-age=3600"})

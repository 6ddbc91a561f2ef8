"""GET /api/v1/health: liveness, no token needed."""

from __future__ import annotations

import time

from fastapi import APIRouter

import shared
from training_server.api.deps import Srv
from training_server.api.models import Health

router = APIRouter(tags=["health"])


@router.get("/health")
def health(srv: Srv) -> Health:
    return Health(
        status="ok",
        version=shared.__version__,
        fleet=srv.fleet,
        graph_id=srv.graph.graph_id,
        current_policy=srv.current_version(),
        uptime_s=round(time.time() - srv.started, 1),
    )

"""The console's live side: who a token is, the alerts, and one server-sent-events stream.

GET /api/v1/events (text/event-stream; send the bearer token as on every route, e.g. with fetch()
and a ReadableStream) sends:
  event: fleet    at most 5 a second, when it changed: GET /api/v1/fleet's body with each robot's
                  last observation z, and "truth": {mission_id: {"t", "target", "robots"}}, the
                  simulated world's ground truth of running missions (fleet-sim only)
  event: belief   with ?belief=ROBOT: that robot's last reported beliefs {"robot_id", "mission_id",
                  "t", "belief": [n floats in the map's node order], "team_belief": the team's
                  collective belief it holds, alike (null unless it flies with a team searcher)},
                  when they changed
  event: status   at most once a second, when it changed: current policy, running missions, the
                  last training runs with their progress, episode counts, alerts
and a comment line every 15 s when nothing changed. ?once=true sends one of each and ends.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import StreamingResponse
from starlette.concurrency import run_in_threadpool

from shared.core.records import ID_RE
from training_server.api.deps import READ, Srv, errors
from training_server.api.models import AlertList, WhoAmI
from training_server.console.hub import FLEET_EVERY, STATUS_EVERY, Hub

router = APIRouter(tags=["live"], dependencies=READ)

KEEPALIVE_S = 15.0


def hub_of(srv: Any) -> Hub:
    hub: Hub | None = getattr(srv, "console_hub", None)
    if hub is None:
        hub = srv.console_hub = Hub(srv)
    return hub


@router.get("/whoami", responses=errors(401))
def whoami(request: Request) -> WhoAmI:
    """The caller's role: "operator" (may act) or "agent" (reads only); ``who`` as in the audit log."""
    who = getattr(request.state, "who", "agent")
    return WhoAmI(role="operator" if who == "operator" or who.startswith("operator (") else "agent", who=who)


@router.get("/alerts", responses=errors(401))
def alerts(srv: Srv) -> AlertList:
    """What needs an operator's eye now: robots offline, runs failed or gated out in the last day,
    episode records rejected in the last minute."""
    return AlertList(items=hub_of(srv).alerts())


def _sse(event: str, data: Any) -> bytes:
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()


@router.get(
    "/events",
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}, "description": "the live stream"}, **errors(401, 422)},
)
async def events(
    request: Request,
    srv: Srv,
    belief: Annotated[str | None, Query(pattern=ID_RE.pattern, description="also stream this robot's belief")] = None,
    once: Annotated[bool, Query(description="send the current state once and end")] = False,
) -> StreamingResponse:
    hub = hub_of(srv)
    stopping = getattr(srv, "is_stopping", lambda: False)

    async def stream() -> AsyncIterator[bytes]:
        yield b"retry: 2000\n\n"
        sent: dict[str, Any] = {}
        last_out = time.monotonic()
        next_status = 0.0
        while not stopping():
            out = []
            fleet, key = await run_in_threadpool(hub.fleet)
            if key != sent.get("fleet"):
                sent["fleet"] = key
                out.append(_sse("fleet", fleet))
            if belief is not None:
                b = await run_in_threadpool(hub.belief, belief)
                bkey = None if b is None else (b["mission_id"], b["t"])
                if b is not None and bkey != sent.get("belief"):
                    sent["belief"] = bkey
                    out.append(_sse("belief", b))
            if time.monotonic() >= next_status:
                next_status = time.monotonic() + STATUS_EVERY
                status, skey = await run_in_threadpool(hub.status)
                if skey != sent.get("status"):
                    sent["status"] = skey
                    out.append(_sse("status", status))
            if out:
                last_out = time.monotonic()
                yield b"".join(out)
            elif time.monotonic() - last_out >= KEEPALIVE_S:
                last_out = time.monotonic()
                yield b": keep-alive\n\n"
            if once or await request.is_disconnected():
                return
            await asyncio.sleep(FLEET_EVERY)

    return StreamingResponse(
        stream(), media_type="text/event-stream", headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
    )

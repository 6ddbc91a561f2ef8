"""/api/v1/detections: what robots reported seeing, and the operator's decision on each.

A robot that reads z = 1 publishes a detection (docs/SPEC.md section 6). Under ``--capture
auto`` the server ends the mission as captured at once; under ``confirm`` the detection waits
here, ``pending``, until an operator confirms it (the mission ends as captured at the detection's
step, by its robot) or dismisses it (recorded as a false alarm; the search goes on).
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Path, Query, Request

from training_server.api.deps import READ, WRITE, Srv, errors
from training_server.api.models import MAX_ID, Detection, DetectionList

router = APIRouter(prefix="/detections", tags=["detections"])


DetectionId = Annotated[int, Path(ge=1, le=MAX_ID, description="the detection's id")]


def _detection(srv: Srv, detection_id: int) -> Detection:
    d = srv.store.detection(detection_id)
    if d is None:
        raise HTTPException(404, f"no detection {detection_id}")
    return Detection(**d)


@router.get("", dependencies=READ, responses=errors(401, 422))
def list_detections(
    srv: Srv,
    status: Annotated[Literal["pending", "confirmed", "dismissed", "closed"] | None, Query()] = None,
    mission_id: Annotated[str | None, Query(max_length=128)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> DetectionList:
    """The fleet's detections, oldest first: ``?status=pending`` are those awaiting a decision."""
    return DetectionList(
        items=[
            Detection(**d) for d in srv.store.detections(srv.fleet, mission_id=mission_id, status=status, limit=limit)
        ]
    )


@router.get("/{detection_id}", dependencies=READ, responses=errors(401, 404, 422))
def get_detection(detection_id: DetectionId, srv: Srv) -> Detection:
    return _detection(srv, detection_id)


def _decide(detection_id: int, request: Request, srv: Srv, confirm: bool) -> Detection:
    det = _detection(srv, detection_id)
    if det.status != "pending":
        raise HTTPException(409, f"detection {detection_id} is {det.status}, not pending: nothing to decide")
    who = getattr(request.state, "who", None) or "operator"
    done = srv.capture(det.model_dump(), by=who) if confirm else srv.dismiss(det.model_dump(), by=who)
    if not done:
        now = _detection(srv, detection_id)
        raise HTTPException(409, f"detection {detection_id} is {now.status}: its mission ended before the decision")
    return _detection(srv, detection_id)


@router.post("/{detection_id}/confirm", dependencies=WRITE, responses=errors(401, 403, 404, 409, 422))
def confirm_detection(detection_id: DetectionId, request: Request, srv: Srv) -> Detection:
    """The target is there: end the mission as captured at the detection's step, by its robot."""
    return _decide(detection_id, request, srv, confirm=True)


@router.post("/{detection_id}/dismiss", dependencies=WRITE, responses=errors(401, 403, 404, 409, 422))
def dismiss_detection(detection_id: DetectionId, request: Request, srv: Srv) -> Detection:
    """A false alarm: recorded as one, and the search goes on."""
    return _decide(detection_id, request, srv, confirm=False)

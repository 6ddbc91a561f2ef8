"""/api/v1/episodes: the stored episode records, paged; counts; one record."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request

from shared.core.records import ID_RE
from training_server.api.deps import READ, Srv, errors, robot_scope
from training_server.api.models import MAX_ID, EpisodePage, EpisodeRecord, EpisodeStats, EpisodeSummary

router = APIRouter(prefix="/episodes", tags=["episodes"], dependencies=READ)


@router.get("", responses=errors(401, 403, 422))
def episodes(
    request: Request,
    srv: Srv,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    after: Annotated[
        int, Query(ge=0, le=MAX_ID, description="return episodes with id > after (use next_after to page)")
    ] = 0,
    mission_id: Annotated[str | None, Query(pattern=ID_RE.pattern, description="this mission's only")] = None,
    robot_id: Annotated[str | None, Query(pattern=ID_RE.pattern, description="this robot's only")] = None,
    set_aside: Annotated[
        bool | None, Query(description="true: only records set aside (no target path explains them); false: none")
    ] = None,
) -> EpisodePage:
    robot_id = robot_scope(request, robot_id) or robot_id  # a robot's own token lists its own records
    items = srv.store.list_episodes(srv.fleet, limit, after, mission_id, robot_id, set_aside)
    return EpisodePage(
        items=[EpisodeSummary(**i) for i in items], next_after=items[-1]["id"] if len(items) == limit else None
    )


@router.get("/stats", responses=errors(401))
def episode_stats(srv: Srv) -> EpisodeStats:
    return EpisodeStats(**srv.store.episode_stats(srv.fleet))


@router.get(
    "/{robot_id}/{mission_id}",
    responses=errors(401, 403, 404),
    response_model_by_alias=True,
    response_model_exclude_unset=True,  # the record as stored: no coordination where it had none
)
def episode(request: Request, robot_id: str, mission_id: str, srv: Srv) -> EpisodeRecord:
    robot_scope(request, robot_id)
    rec = srv.store.get_record(srv.fleet, robot_id, mission_id)
    if rec is None:
        raise HTTPException(404, f"no episode of robot {robot_id!r} in mission {mission_id!r}")
    return EpisodeRecord.model_validate(rec)

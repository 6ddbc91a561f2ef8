"""/api/v1/missions: start a mission, list and follow them, stop one."""

from __future__ import annotations

import random
import time
import uuid
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query, Request, Response

from shared.core.clock import default_time_limit_s, has_edge_lengths
from training_server.api.deps import READ, WRITE, Srv, errors, fleet_scope
from training_server.api.models import (
    MAX_ID,
    MAX_MISSION_STEPS,
    Mission,
    MissionList,
    MissionParams,
    MissionReplay,
    MissionRequest,
    RobotReplay,
)

router = APIRouter(prefix="/missions", tags=["missions"])


def mission_view(srv: Any, mid: str, m: dict[str, Any] | None = None) -> Mission:
    m = m or srv.store.get_mission(mid)
    if m is None:
        raise HTTPException(404, f"no mission {mid!r}")
    recs = srv.store.mission_records(srv.fleet, mid)
    got = sorted(r for r, *_ in recs)
    if m["status"] == "running" and set(m["robots"]) <= set(got):  # the robots ended it: so does the server
        srv.records_complete(mid)
        m = srv.store.get_mission(mid) or m
    status = m["status"]
    no_record = {r for r, w in m["withdrawn"].items() if w["steps"] == 0}  # withdrew before z_0: none comes
    if status != "running" and set(m["robots"]) <= set(got) | no_record:
        status = "completed"
    outcome = None
    if recs:
        caps = [ct for _r, c, ct, _pv in recs if c and ct is not None]
        outcome = {
            "captured": bool(caps),
            "capture_time": min(caps) if caps else None,
            # the capture time, or the last step any robot recorded when none captured
            "steps": max((ct or 0) for *_x, ct, _pv in recs) if caps else srv.store.mission_steps(srv.fleet, mid) - 1,
            "policy_versions": sorted({pv for *_x, pv in recs if pv is not None}),
        }
        if m["event"] and m["event"].get("type") == "captured":
            outcome["captured_by"] = m["event"].get("captured_by")
            if m["event"].get("time_s") is not None:  # robots on the mission clock: the capture in seconds
                outcome["capture_time_s"] = m["event"]["time_s"]
    return Mission(
        id=m["id"],
        status=status,
        robots=m["robots"],
        params=MissionParams(**m["params"]),
        policy_version=m["policy_version"],
        created=m["created"],
        ended=m["ended"],
        deadline=m["deadline"],
        event=m["event"],
        episodes_received=got,
        withdrawn=m["withdrawn"],
        outcome=outcome,
    )


def default_time_limit(srv: Any, robots: list[str]) -> float | None:
    """A mission's time limit when its request gives no limit: where some of ``robots`` fly on the
    mission clock (their telemetry says so, with their speed), the step limit's horizon in time, 3 n
    moves of the map's median edge at the slowest one's speed (as `mures fleet-sim --world` sets);
    None when none does (or the map has no edge lengths): the step limit of 3 n alone. A robot on the
    clock that the plan keeps where it is reads once a second, so a step limit would end it early."""
    heard = srv.bus.agents()
    speeds = []
    for robot in robots:
        live = (heard.get(robot) or {}).get("live") or {}
        if live.get("clock") == "seconds" and live.get("speed"):
            speeds.append(float(live["speed"]))
    if not speeds or not has_edge_lengths(srv.graph):
        return None
    return default_time_limit_s(srv.graph, min(speeds))


@router.post("", status_code=201, dependencies=WRITE, responses=errors(401, 403, 409, 422))
def start_mission(req: MissionRequest, response: Response, srv: Srv) -> Mission:
    """Start a mission for the agents online (or the ones named); the Location header names it."""
    online = srv.bus.agents_online()
    robots = req.robots if req.robots is not None else sorted(online)
    if not robots:
        raise HTTPException(409, "no agents online to fly a mission")
    if len(set(robots)) != len(robots):
        raise HTTPException(422, "robots lists a robot twice")
    missing = [r for r in robots if r not in online]
    if missing:
        raise HTTPException(409, f"robots not online: {', '.join(missing)}")
    busy = srv.store.busy_robots(srv.fleet)
    if any(r in busy for r in robots):
        flying = ", ".join(f"{r} (mission {busy[r]})" for r in robots if r in busy)
        raise HTTPException(409, f"robots busy with a running mission: {flying}; stop it or wait for it to end")
    mid = req.mission_id or f"m-{time.strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:8]}"
    if srv.store.get_mission(mid) is not None:
        raise HTTPException(409, f"mission {mid!r} exists")
    timeout = min(req.timeout_s or srv.mission_timeout, srv.mission_timeout)
    seed = req.seed if req.seed is not None else random.SystemRandom().randrange(2**31)
    pv, seed, canary = srv.mission_policy(seed)  # during a canary, every other mission flies it
    max_seconds = req.max_seconds
    if max_seconds is None and req.max_steps is None:
        max_seconds = default_time_limit(srv, robots)
    params: dict[str, Any] = {
        "seed": seed,
        # under a time limit the step limit only guards: a robot on the clock that stays reads once a second
        "max_steps": req.max_steps or (MAX_MISSION_STEPS if max_seconds else 3 * srv.graph.n),
        "start_node": int(srv.graph.labels[srv.graph.start]),
        "capture": req.capture or srv.default_capture(),
    }
    if max_seconds is not None:
        params["max_seconds"] = max_seconds
    if canary is not None:
        params["canary"] = canary
    srv.store.add_mission(mid, srv.fleet, robots, params, pv, deadline=time.time() + timeout)
    srv.bus.publish_mission({"type": "start", "mission_id": mid, "robots": robots, "policy_version": pv, **params})
    response.headers["Location"] = f"/api/v1/missions/{mid}"
    return mission_view(srv, mid)


@router.get("", dependencies=READ, responses=errors(401, 422))
def list_missions(
    srv: Srv,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=MAX_ID, description="missions to skip (newest first)")] = 0,
) -> MissionList:
    """The fleet's missions, newest first, with their status and outcome."""
    items, total = srv.store.list_missions(srv.fleet, limit, offset)
    return MissionList(items=[mission_view(srv, m["id"], m) for m in items], total=total)


@router.get("/{mission_id}", dependencies=READ, responses=errors(401, 404))
def get_mission(mission_id: str, srv: Srv) -> Mission:
    return mission_view(srv, mission_id)


@router.get(
    "/{mission_id}/export.mcap",
    dependencies=READ,
    response_class=Response,
    responses={
        200: {"content": {"application/octet-stream": {}}, "description": "the MCAP file"},
        **errors(401, 403, 404),
    },
)
def export_mission(mission_id: str, request: Request, srv: Srv) -> Response:
    """The mission as an MCAP file for Foxglove: the map, each robot's states and its own belief
    per step (recomputed from its record), the outcome (training_server/export.py)."""
    from training_server.export import mission_mcap

    fleet_scope(request, "the export")
    m = mission_view(srv, mission_id)
    records = {r: srv.store.get_record(srv.fleet, r, mission_id) for r in m.episodes_received}
    data = mission_mcap(srv, m, {r: rec for r, rec in records.items() if rec is not None})
    return Response(
        data,
        media_type="application/octet-stream",
        headers={"Content-Disposition": f'attachment; filename="{mission_id}.mcap"'},
    )


@router.get("/{mission_id}/replay", dependencies=READ, responses=errors(401, 403, 404))
def replay_mission(mission_id: str, request: Request, srv: Srv) -> MissionReplay:
    """The mission step by step from its stored records: each robot's positions and observations,
    and its own belief after each step recomputed from its record alone (Eq. 1) with the belief
    model of the version it flew (null when that version is gone); and the team's collective
    belief from all the records (Eq. 6-7)."""
    from training_server.export import recomputed_beliefs, recomputed_team_belief

    fleet_scope(request, "a replay")
    m = mission_view(srv, mission_id)
    robots: dict[str, RobotReplay] = {}
    cache: dict[int, Any] = {}
    records = {}
    for r in m.episodes_received:
        rec = srv.store.get_record(srv.fleet, r, mission_id)
        if rec is None:
            continue
        records[r] = rec
        beliefs = recomputed_beliefs(srv, rec, cache)
        robots[r] = RobotReplay(
            policy_version=rec.get("policy_version"),
            steps=rec["steps"],
            belief=None if beliefs is None else [[round(float(x), 4) for x in b] for b in beliefs],
        )
    team = recomputed_team_belief(srv, records, cache)
    return MissionReplay(
        mission=m,
        nodes=[int(v) for v in srv.graph.labels],
        robots=robots,
        team_belief=None if team is None else [[round(float(x), 4) for x in b] for b in team],
    )


@router.post("/{mission_id}/stop", dependencies=WRITE, responses=errors(401, 403, 404))
def stop_mission(mission_id: str, srv: Srv) -> Mission:
    """Stop a running mission (a finished one is returned as it is)."""
    m = mission_view(srv, mission_id)
    if m.status == "running":
        msg = {"type": "stop", "mission_id": mission_id, "reason": "operator"}
        srv.bus.publish_mission(msg)
        srv.store.mission_event(mission_id, msg, "stopped")
    return mission_view(srv, mission_id)

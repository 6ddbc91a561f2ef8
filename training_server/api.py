"""The REST API under /api/v1 (FastAPI; OpenAPI at /openapi.json, docs at /docs).

Bearer tokens: the operator token for everything that changes state, the agent token (or the
operator's) for reading. Missing or wrong token: 401; the agent token on an operator action: 403.
Handlers are plain ``def`` so FastAPI runs them in its thread pool: SQLite and Zenoh calls never
block the event loop.
"""

from __future__ import annotations

import hmac
import random
import time
import uuid
from typing import Annotated, Any, Literal

from fastapi import Depends, FastAPI, Header, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse, JSONResponse, PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ConfigDict, Field

import shared
from shared.core.records import ID_RE
from training_server.jobs import check_params

ROLE_AGENT, ROLE_OPERATOR = 1, 2


class MissionRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    robots: list[Annotated[str, Field(pattern=ID_RE.pattern)]] | None = Field(
        default=None, description="robot ids to fly (default: every agent online)", min_length=1, max_length=256
    )
    seed: int | None = Field(default=None, description="mission seed (agents' and simulated world's randomness)")
    max_steps: int | None = Field(
        default=None, ge=1, le=100_000, description="step limit (default 3n, docs/SPEC.md section 1)"
    )
    mission_id: str | None = Field(default=None, pattern=ID_RE.pattern, description="default: generated")


class TrainingRunRequest(BaseModel):
    """A retrain's settings; every field is optional (defaults in training_server/jobs.py)."""

    model_config = ConfigDict(extra="forbid")
    episodes: int | None = Field(default=None, ge=256, le=10_000_000, description="CE-PG episodes (default 20000)")
    beta: float | None = Field(default=None, ge=0.0, le=1.0, description="Eq. 9 beta (default 0.5; 1 = PG)")
    lr: float | None = Field(default=None, gt=0.0, lt=1.0, description="Adam learning rate (default 0.01)")
    seed: int | None = Field(default=None, description="training and gate seed (default 0)")
    max_records: int | None = Field(default=None, ge=1, description="newest records used by EM (default 20000)")
    em_max_iter: int | None = Field(default=None, ge=1, description="EM iterations at most (default 300)")
    gate_episodes: int | None = Field(default=None, ge=1, description="episodes of the evaluation gate (1000)")
    gate: bool | None = Field(default=None, description="publish only if not worse than the current (true)")
    promote: bool | None = Field(default=None, description="make the new version current (true)")
    threads: int | None = Field(default=None, ge=0, description="torch threads in the run (0: torch's default)")


class PromoteRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    version: int = Field(ge=1)


class Mission(BaseModel):
    id: str
    status: Literal["running", "captured", "stopped", "completed"]
    robots: list[str]
    params: dict[str, Any]
    policy_version: int | None
    created: float
    ended: float | None
    event: dict[str, Any] | None
    episodes_received: list[str]
    outcome: dict[str, Any] | None


def create_app(srv: Any) -> FastAPI:
    app = FastAPI(title="MuRES fleet training server", version="1", description=__doc__)
    bearer = HTTPBearer(auto_error=False)

    def role(creds: HTTPAuthorizationCredentials | None = Depends(bearer)) -> int:  # noqa: B008
        if creds is None or creds.scheme.lower() != "bearer":
            raise HTTPException(401, "missing bearer token", headers={"WWW-Authenticate": "Bearer"})
        tok = creds.credentials.encode()
        if hmac.compare_digest(tok, srv.operator_token.encode()):
            return ROLE_OPERATOR
        if hmac.compare_digest(tok, srv.agent_token.encode()):
            return ROLE_AGENT
        raise HTTPException(401, "wrong bearer token", headers={"WWW-Authenticate": "Bearer"})

    def operator(r: int = Depends(role)) -> int:
        if r != ROLE_OPERATOR:
            raise HTTPException(403, "this action needs the operator token")
        return r

    reader = Depends(role)
    writer = Depends(operator)

    @app.exception_handler(HTTPException)
    def _http_error(_req: Request, exc: HTTPException) -> JSONResponse:
        return JSONResponse({"error": exc.detail}, status_code=exc.status_code, headers=exc.headers)

    # ------------------------------------------------------------------ health, map, fleet
    @app.get("/api/v1/health")
    def health() -> dict[str, Any]:
        return {
            "status": "ok",
            "version": shared.__version__,
            "fleet": srv.fleet,
            "graph_id": srv.graph.graph_id,
            "current_policy": srv.current_version(),
            "uptime_s": round(time.time() - srv.started, 1),
        }

    @app.get("/api/v1/map", dependencies=[reader])
    def get_map() -> dict[str, Any]:
        return {**srv.graph.to_json(), "graph_id": srv.graph.graph_id}

    @app.get("/api/v1/fleet", dependencies=[reader])
    def fleet() -> dict[str, Any]:
        online = srv.bus.agents_online()
        return {
            "fleet": srv.fleet,
            "online": len(online),
            "agents": [{"robot_id": r, "since": s} for r, s in sorted(online.items())],
        }

    # ------------------------------------------------------------------ missions
    def mission_view(mid: str) -> Mission:
        m = srv.store.get_mission(mid)
        if m is None:
            raise HTTPException(404, f"no mission {mid!r}")
        recs = srv.store.mission_records(srv.fleet, mid)
        got = sorted(r for r, *_ in recs)
        status = m["status"]
        if set(m["robots"]) <= set(got):
            status = "completed"
        outcome = None
        if recs:
            caps = [ct for _r, c, ct, _pv in recs if c and ct is not None]
            outcome = {
                "captured": bool(caps),
                "capture_time": min(caps) if caps else None,
                "steps": max((ct or 0) for *_x, ct, _pv in recs) if caps else None,
                "policy_versions": sorted({pv for *_x, pv in recs if pv is not None}),
            }
            if m["event"] and m["event"].get("type") == "captured":
                outcome["captured_by"] = m["event"].get("captured_by")
        return Mission(
            id=m["id"],
            status=status,
            robots=m["robots"],
            params=m["params"],
            policy_version=m["policy_version"],
            created=m["created"],
            ended=m["ended"],
            event=m["event"],
            episodes_received=got,
            outcome=outcome,
        )

    @app.post("/api/v1/missions", status_code=201, dependencies=[writer])
    def start_mission(req: MissionRequest, response: Response) -> Mission:
        online = srv.bus.agents_online()
        robots = req.robots if req.robots is not None else sorted(online)
        if not robots:
            raise HTTPException(409, "no agents online to fly a mission")
        if len(set(robots)) != len(robots):
            raise HTTPException(422, "robots lists a robot twice")
        missing = [r for r in robots if r not in online]
        if missing:
            raise HTTPException(409, f"robots not online: {', '.join(missing)}")
        mid = req.mission_id or f"m-{time.strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:8]}"
        if srv.store.get_mission(mid) is not None:
            raise HTTPException(409, f"mission {mid!r} exists")
        params = {
            "seed": req.seed if req.seed is not None else random.SystemRandom().randrange(2**31),
            "max_steps": req.max_steps or 3 * srv.graph.n,
            "start_node": int(srv.graph.labels[srv.graph.start]),
        }
        pv = srv.current_version()
        srv.store.add_mission(mid, srv.fleet, robots, params, pv)
        srv.bus.publish_mission({"type": "start", "mission_id": mid, "robots": robots, "policy_version": pv, **params})
        response.headers["Location"] = f"/api/v1/missions/{mid}"
        return mission_view(mid)

    @app.get("/api/v1/missions/{mission_id}", dependencies=[reader])
    def get_mission(mission_id: str) -> Mission:
        return mission_view(mission_id)

    @app.post("/api/v1/missions/{mission_id}/stop", dependencies=[writer])
    def stop_mission(mission_id: str) -> Mission:
        m = mission_view(mission_id)
        if m.status == "running":
            msg = {"type": "stop", "mission_id": mission_id, "reason": "operator"}
            srv.bus.publish_mission(msg)
            srv.store.mission_event(mission_id, msg, "stopped")
        return mission_view(mission_id)

    # ------------------------------------------------------------------ episodes
    @app.get("/api/v1/episodes", dependencies=[reader])
    def episodes(
        limit: int = Query(100, ge=1, le=1000),
        after: int = Query(0, ge=0, description="return episodes with id > after (use next_after to page)"),
        mission_id: str | None = None,
        robot_id: str | None = None,
    ) -> dict[str, Any]:
        items = srv.store.list_episodes(srv.fleet, limit, after, mission_id, robot_id)
        return {"items": items, "next_after": items[-1]["id"] if len(items) == limit else None}

    @app.get("/api/v1/episodes/stats", dependencies=[reader])
    def episode_stats() -> dict[str, Any]:
        return srv.store.episode_stats(srv.fleet)

    @app.get("/api/v1/episodes/{robot_id}/{mission_id}", dependencies=[reader])
    def episode(robot_id: str, mission_id: str) -> dict[str, Any]:
        rec = srv.store.get_record(srv.fleet, robot_id, mission_id)
        if rec is None:
            raise HTTPException(404, f"no episode of robot {robot_id!r} in mission {mission_id!r}")
        return rec

    # ------------------------------------------------------------------ policies
    def policy_view(version: int) -> dict[str, Any]:
        p = srv.store.policy(version)
        if p is None:
            raise HTTPException(404, f"no policy version {version}")
        return {**p, "current": version == srv.current_version(), "artifact": f"/api/v1/policies/{version}/artifact"}

    @app.get("/api/v1/policies", dependencies=[reader])
    def policies() -> dict[str, Any]:
        cur = srv.current_version()
        return {"current": cur, "items": [{**p, "current": p["version"] == cur} for p in srv.store.policies()]}

    @app.get("/api/v1/policies/current", dependencies=[reader])
    def current_policy() -> dict[str, Any]:
        return policy_view(srv.current_version())

    @app.post("/api/v1/policies/current", dependencies=[writer])
    def promote(req: PromoteRequest) -> dict[str, Any]:
        """Promote a version (or roll back to an earlier one): agents take it before their next mission."""
        try:
            srv.set_current(req.version)
        except KeyError:
            raise HTTPException(404, f"no policy version {req.version}") from None
        return policy_view(req.version)

    @app.get("/api/v1/policies/{version}", dependencies=[reader])
    def get_policy(version: int) -> dict[str, Any]:
        return policy_view(version)

    @app.get("/api/v1/policies/{version}/artifact", dependencies=[reader], response_model=None)
    def artifact(version: int, if_none_match: str | None = Header(default=None)) -> Response:
        p = srv.store.policy(version)
        if p is None:
            raise HTTPException(404, f"no policy version {version}")
        etag = f'"{p["sha256"]}"'
        if if_none_match and etag in [t.strip() for t in if_none_match.split(",")]:
            return Response(status_code=304, headers={"ETag": etag})
        return FileResponse(
            srv.artifact(version),
            media_type="application/x-tar",
            headers={"ETag": etag},
            filename=f"policy-v{version}.tar",
        )

    # ------------------------------------------------------------------ training runs
    @app.post("/api/v1/training-runs", status_code=202, dependencies=[writer])
    def start_run(response: Response, req: TrainingRunRequest | None = None) -> dict[str, Any]:
        """Queue a retrain: EM on the stored records, CE-PG from the current policy, the gate, a new version."""
        try:
            full = check_params(req.model_dump(exclude_none=True) if req else {})
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        if srv.store.episode_stats(srv.fleet)["stored"] == 0:
            raise HTTPException(409, "no episodes stored yet: fly some missions before training")
        run_id = f"run-{time.strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:6]}"
        srv.store.add_run(run_id, full)
        srv.supervisor.submit(run_id)
        response.headers["Location"] = f"/api/v1/training-runs/{run_id}"
        return srv.store.get_run(run_id)

    @app.get("/api/v1/training-runs", dependencies=[reader])
    def runs() -> dict[str, Any]:
        return {"items": srv.store.runs()}

    @app.get("/api/v1/training-runs/{run_id}", dependencies=[reader])
    def get_run(run_id: str) -> dict[str, Any]:
        r = srv.store.get_run(run_id)
        if r is None:
            raise HTTPException(404, f"no training run {run_id!r}")
        return r

    @app.post("/api/v1/training-runs/{run_id}/cancel", status_code=202, dependencies=[writer])
    def cancel_run(run_id: str) -> dict[str, Any]:
        r = srv.store.get_run(run_id)
        if r is None:
            raise HTTPException(404, f"no training run {run_id!r}")
        if r["status"] not in ("queued", "running"):
            raise HTTPException(409, f"run {run_id!r} is {r['status']}; nothing to cancel")
        srv.supervisor.cancel(run_id)
        return srv.store.get_run(run_id)

    # ------------------------------------------------------------------ metrics
    @app.get("/metrics", response_class=PlainTextResponse)
    def metrics() -> str:
        st = srv.store.episode_stats(srv.fleet)
        runs = srv.store.runs()
        lines = [
            "# HELP mures_episodes_stored Episode records stored.",
            "# TYPE mures_episodes_stored gauge",
            f"mures_episodes_stored {st['stored']}",
            "# HELP mures_episodes_rejected_total Episode records rejected, by reason.",
            "# TYPE mures_episodes_rejected_total counter",
            *[f'mures_episodes_rejected_total{{reason="{r}"}} {c}' for r, c in st["rejected"].items()],
            "# HELP mures_agents_online Agents with a liveliness token.",
            "# TYPE mures_agents_online gauge",
            f"mures_agents_online {len(srv.bus.agents_online())}",
            "# HELP mures_training_runs Training runs by status.",
            "# TYPE mures_training_runs gauge",
            *[
                f'mures_training_runs{{status="{s}"}} {sum(r["status"] == s for r in runs)}'
                for s in ("queued", "running", "succeeded", "failed", "cancelled")
            ],
            "# HELP mures_policy_current_version The policy version agents are told to fly.",
            "# TYPE mures_policy_current_version gauge",
            f"mures_policy_current_version {srv.current_version()}",
            "# HELP mures_ingest_seconds_total Time spent validating and storing episode batches.",
            "# TYPE mures_ingest_seconds_total counter",
            f"mures_ingest_seconds_total {srv.bus.stats['ingest_seconds']:.6f}",
            f"mures_ingest_batches_total {srv.bus.stats['ingest_batches']}",
        ]
        return "\n".join(lines) + "\n"

    return app

"""/api/v1/policies: versions, the current one (promote or roll back), artifacts for agents."""

from __future__ import annotations

import math
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Header, HTTPException, Path, Response
from fastapi.responses import FileResponse

from training_server.api.deps import READ, WRITE, Srv, errors
from training_server.api.models import (
    MAX_ID,
    PerformanceOut,
    PolicyList,
    PolicyVersion,
    PromoteRequest,
    TargetModelOut,
    VersionPerformance,
)

router = APIRouter(prefix="/policies", tags=["policies"])

Version = Annotated[int, Path(ge=1, le=MAX_ID)]


def policy_view(srv: Any, version: int) -> PolicyVersion:
    p = srv.store.policy(version)
    if p is None:
        raise HTTPException(404, f"no policy version {version}")
    return PolicyVersion(**p, current=version == srv.current_version(), artifact=f"/api/v1/policies/{version}/artifact")


@router.get("", dependencies=READ, responses=errors(401))
def policies(srv: Srv) -> PolicyList:
    cur = srv.current_version()
    return PolicyList(
        current=cur,
        items=[
            PolicyVersion(**p, current=p["version"] == cur, artifact=f"/api/v1/policies/{p['version']}/artifact")
            for p in srv.store.policies()
        ],
    )


@router.get("/current", dependencies=READ, responses=errors(401))
def current_policy(srv: Srv) -> PolicyVersion:
    return policy_view(srv, srv.current_version())


@router.post("/current", dependencies=WRITE, responses=errors(401, 403, 404, 422))
def promote(req: PromoteRequest, srv: Srv) -> PolicyVersion:
    """Promote a version (or roll back to an earlier one): agents take it before their next mission."""
    try:
        srv.set_current(req.version)
    except KeyError:
        raise HTTPException(404, f"no policy version {req.version}") from None
    return policy_view(srv, req.version)


@router.get("/performance", dependencies=READ, responses=errors(401))
def performance(srv: Srv) -> PerformanceOut:
    """Capture time per policy version from the fleet's own missions, with its 95 % CI. A mission
    counts when some robot captured the target or it ran to its step limit (which a miss counts);
    missions stopped or timed out early, or flown with mixed versions, are left out. Missions flown
    on the mission clock also count in seconds (a robot's step count on the clock is its own)."""
    from shared.engine.evaluate import mean_ci95

    times: dict[int, list[float]] = {}
    seconds: dict[int, list[float]] = {}  # the missions flown on the mission clock
    caught: dict[int, int] = {}
    excluded = 0
    for o in srv.store.mission_outcomes(srv.fleet):
        v, ct = o["policy_version"], srv.store.counted_capture_time(o)
        if v is None or ct is None:
            excluded += 1
            continue
        times.setdefault(v, []).append(ct)
        if (sec := srv.store.counted_seconds(o)) is not None:
            seconds.setdefault(v, []).append(sec)
        caught[v] = caught.get(v, 0) + int(o["captured"] and o["capture_time"] is not None)
    items = []
    for v in sorted(times):
        mean, half = mean_ci95(times[v])
        mean_s, half_s = mean_ci95(seconds.get(v, []))
        items.append(
            VersionPerformance(
                version=v,
                missions=len(times[v]),
                captured=caught.get(v, 0),
                mean_capture_time=round(mean, 4),
                ci95=None if math.isnan(half) else round(half, 4),
                missions_on_clock=len(seconds.get(v, [])),
                mean_capture_time_s=None if math.isnan(mean_s) else round(mean_s, 3),
                ci95_s=None if math.isnan(half_s) else round(half_s, 3),
            )
        )
    return PerformanceOut(items=items, excluded=excluded)


@router.get("/{version}", dependencies=READ, responses=errors(401, 404, 422))
def get_policy(version: Version, srv: Srv) -> PolicyVersion:
    return policy_view(srv, version)


@router.get("/{version}/model", dependencies=READ, responses=errors(401, 404, 422))
def target_model(version: Version, srv: Srv) -> TargetModelOut:
    """The version's estimated target model: Gamma_hat per node over its closed neighbourhood, b0,
    and Gamma_hat's stationary distribution (where the target tends to be)."""
    from shared.core.snapshot_format import SnapshotError, read_snapshot

    if srv.store.policy(version) is None:
        raise HTTPException(404, f"no policy version {version}")
    try:
        model = read_snapshot(srv.snapshot_dir(version), srv.graph).model
    except (OSError, SnapshotError, ValueError) as exc:
        raise HTTPException(404, f"policy version {version} has no readable snapshot on this server ({exc})") from None
    g = srv.graph
    gamma = model.dense()
    labels = [int(v) for v in g.labels]
    moves = {
        str(labels[u]): {str(labels[int(v)]): round(float(gamma[u, v]), 6) for v in g.closed(u) if gamma[u, v] > 0}
        for u in range(g.n)
    }
    pi = stationary(gamma)
    return TargetModelOut(
        version=version,
        nodes=labels,
        b0=[round(float(x), 6) for x in model.b0],
        moves=moves,
        stationary=[round(float(x), 6) for x in pi],
    )


def stationary(gamma: np.ndarray, iterations: int = 1000) -> np.ndarray:
    """(n,) pi with pi = Gamma^T pi (the target's long-run distribution), by power iteration from
    uniform; for a periodic or reducible Gamma, the average of the last two iterates (a fixed point)."""
    pi = np.full(len(gamma), 1.0 / len(gamma))
    for _ in range(iterations):
        nxt = gamma.T @ pi
        nxt /= nxt.sum()
        if float(np.abs(nxt - pi).sum()) < 1e-12:
            return nxt
        pi = nxt
    avg = 0.5 * (pi + gamma.T @ pi)
    return avg / avg.sum()


@router.get(
    "/{version}/artifact",
    dependencies=READ,
    response_class=FileResponse,
    responses={
        200: {"content": {"application/x-tar": {}}, "description": "The snapshot as a tar (ETag = sha256)"},
        304: {"description": "Not modified: the If-None-Match ETag is the artifact's"},
        **errors(401, 404, 422),
    },
)
def artifact(version: Version, srv: Srv, if_none_match: Annotated[str | None, Header()] = None) -> Response:
    """The version's snapshot as a tar; send If-None-Match with its ETag to get 304 when unchanged."""
    p = srv.store.policy(version)
    if p is None:
        raise HTTPException(404, f"no policy version {version}")
    etag = f'"{p["sha256"]}"'
    if if_none_match and etag in [t.strip() for t in if_none_match.split(",")]:
        return Response(status_code=304, headers={"ETag": etag})
    return FileResponse(
        srv.artifact(version), media_type="application/x-tar", headers={"ETag": etag}, filename=f"policy-v{version}.tar"
    )

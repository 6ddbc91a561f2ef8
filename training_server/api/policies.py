"""/api/v1/policies: versions, the current one (promote or roll back), artifacts for agents."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Header, HTTPException, Path, Response
from fastapi.responses import FileResponse

from training_server.api.deps import READ, WRITE, Srv, errors
from training_server.api.schemas import MAX_ID, PolicyList, PolicyVersion, PromoteRequest

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


@router.get("/{version}", dependencies=READ, responses=errors(401, 404, 422))
def get_policy(version: Version, srv: Srv) -> PolicyVersion:
    return policy_view(srv, version)


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

"""Dependencies shared by the routers: the server state, the two roles, and the documented errors.

Bearer tokens (compared in constant time): the operator token may do everything, the agent token
(or the operator's) may read. Missing or wrong token: 401; the agent token on an operator action:
403.
"""

from __future__ import annotations

import hmac
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from training_server.api.schemas import Error

ROLE_AGENT, ROLE_OPERATOR = 1, 2

_bearer = HTTPBearer(auto_error=False)

DESCRIPTIONS = {
    304: "Not modified: the If-None-Match ETag is the artifact's",
    400: "Bad request",
    401: "Missing or wrong bearer token",
    403: "The agent token on an operator action",
    404: "No such resource",
    409: "Conflicts with the current state",
    422: "The request does not validate; the message names the field",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` for the error statuses a route really returns, all with the Error schema."""
    return {code: {"model": Error, "description": DESCRIPTIONS[code]} for code in codes}


def get_server(request: Request) -> Any:
    """The training_server.server.Server the app was created for (typed Any: that module imports
    this package lazily, and a type import back would be an import circle)."""
    return request.app.state.server


Srv = Annotated[Any, Depends(get_server)]


def role(request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> int:
    srv = get_server(request)
    if creds is None or creds.scheme.lower() != "bearer":
        raise HTTPException(401, "missing bearer token", headers={"WWW-Authenticate": "Bearer"})
    tok = creds.credentials.encode()
    if hmac.compare_digest(tok, srv.operator_token.encode()):
        return ROLE_OPERATOR
    if hmac.compare_digest(tok, srv.agent_token.encode()):
        return ROLE_AGENT
    raise HTTPException(401, "wrong bearer token", headers={"WWW-Authenticate": "Bearer"})


def operator(r: Annotated[int, Depends(role)]) -> int:
    if r != ROLE_OPERATOR:
        raise HTTPException(403, "this action needs the operator token")
    return r


READ = [Depends(role)]  # route dependencies: any fleet token
WRITE = [Depends(operator)]  # route dependencies: the operator token

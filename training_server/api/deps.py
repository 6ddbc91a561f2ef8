"""Dependencies shared by the routers: the server state, the two roles, and the documented errors.

Bearer tokens (compared in constant time): the operator token may do everything, the agent token
(or the operator's) may read. Missing or wrong token: 401; the agent token on an operator action:
403.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

import training_server.credentials as credentials
from training_server.api.models import Error

ROLE_AGENT, ROLE_OPERATOR = 1, 2

_bearer = HTTPBearer(auto_error=False)

DESCRIPTIONS = {
    304: "Not modified: the If-None-Match ETag is the artifact's",
    400: "The request body is not valid JSON",
    401: "Missing or wrong bearer token",
    403: "The agent token on an operator action",
    404: "No such resource",
    409: "Conflicts with the current state",
    413: "The request body is larger than the limit (1 MiB); it was not read",
    422: "The request does not validate; the message names the field",
    429: "Too many failed sign-ins from this address; see Retry-After",
}


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` for the error statuses a route really returns, all with the Error schema
    (a route that checks tokens can also answer 429)."""
    if 401 in codes:
        codes = (*codes, 429)
    return {code: {"model": Error, "description": DESCRIPTIONS[code]} for code in codes}


def get_server(request: Request) -> Any:
    """The training_server.server.Server the app was created for (typed Any: that module imports
    this package lazily, and a type import back would be an import circle)."""
    return request.app.state.server


Srv = Annotated[Any, Depends(get_server)]


def _client(request: Request) -> str:
    return request.client.host if request.client else "unknown"


ACTOR_RE = re.compile(r"[A-Za-z0-9 _.:()-]{1,64}")


def _who(request: Request, role_name: str) -> str:
    """The token's role, and the program acting with it when it says so (X-Mures-Actor), for the
    audit log and the decisions it records: "operator (fleet-sim simulated operator)"."""
    actor = request.headers.get("x-mures-actor", "")
    return f"{role_name} ({actor})" if ACTOR_RE.fullmatch(actor) else role_name


def role(request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> int:
    """The caller's role from its bearer token. No token: 401. A wrong one is a failed sign-in,
    logged; past a limit per address (training_server/security.py) the address is refused with
    429 for a while, whatever token it sends (a right guess must not be told apart then)."""
    srv = get_server(request)
    client = _client(request)
    if creds is None or creds.scheme.lower() != "bearer":  # no guess was made: nothing to count
        raise HTTPException(401, "missing bearer token", headers={"WWW-Authenticate": "Bearer"})
    wait = srv.sign_ins.blocked_for(client)
    if wait > 0:
        raise HTTPException(
            429,
            f"too many failed sign-ins from {client}; try again in {math.ceil(wait)} s",
            headers={"Retry-After": str(math.ceil(wait))},
        )
    tok = creds.credentials.encode()
    if srv.tokens["operator"].matches(tok):
        request.state.who = _who(request, "operator")
        return ROLE_OPERATOR
    if srv.tokens["agent"].matches(tok):
        request.state.who = _who(request, "agent")
        return ROLE_AGENT
    robot = credentials.robot_for_token(srv.data_dir, tok)
    if robot is not None:  # a robot's own token: the agent's reads, its own records only
        request.state.who = f"robot:{robot}"
        request.state.robot = robot
        return ROLE_AGENT
    gone = credentials.revoked_robot_for_token(srv.data_dir, tok)
    why = f"robot {gone}'s credentials were revoked" if gone else "wrong bearer token"
    srv.sign_ins.failed(client, why, request.url.path)
    raise HTTPException(
        401,
        f"{why} (training-server robots revoke {gone}); an operator can issue new ones" if gone else why,
        headers={"WWW-Authenticate": "Bearer"},
    )


def operator(request: Request, r: Annotated[int, Depends(role)]) -> int:
    """The operator token is needed; the action is written to the audit log (create_app)."""
    request.state.audit = True
    if r != ROLE_OPERATOR:
        raise HTTPException(403, "this action needs the operator token")
    return r


def robot_scope(request: Request, robot_id: str | None) -> str | None:
    """The robot a robot's own token may read records of: 403 for another's; None for fleet tokens."""
    own: str | None = getattr(request.state, "robot", None)
    if own is not None and robot_id is not None and robot_id != own:
        raise HTTPException(403, f"this token is robot {own}'s; it cannot read robot {robot_id}'s records")
    return own


def fleet_scope(request: Request, what: str) -> None:
    """``what`` holds every robot's records: 403 for a robot's own token."""
    if getattr(request.state, "robot", None) is not None:
        raise HTTPException(403, f"a robot's own token reads its own records only; {what} holds every robot's")


READ = [Depends(role)]  # route dependencies: any fleet token
WRITE = [Depends(operator)]  # route dependencies: the operator token

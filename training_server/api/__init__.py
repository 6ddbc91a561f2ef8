"""The REST API (FastAPI): one router per resource under /api/v1, /metrics beside them.

OpenAPI at /openapi.json (docs at /docs) lists every route's request and response models and the
error statuses it really returns, all with one schema ``{"error": "..."}`` (docs/SPEC.md
section 9). Handlers are plain ``def`` so FastAPI runs them in its thread pool: SQLite and Zenoh
calls never block the event loop.
"""

from __future__ import annotations

import logging
import re
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse
from fastapi_offline import FastAPIOffline
from starlette.exceptions import HTTPException as StarletteHTTPException

from training_server.api import (
    detections,
    episodes,
    fleet,
    health,
    live,
    maps,
    metrics,
    missions,
    policies,
    training_runs,
)
from training_server.api.deps import DESCRIPTIONS
from training_server.api.limits import BodyLimit
from training_server.console import mount as mount_console

log = logging.getLogger("mures.server.api")

API_PREFIX = "/api/v1"


def _validation_message(exc: RequestValidationError) -> str:
    """One line naming the fields that failed, e.g. 'body.seed: Input should be a valid integer'."""
    parts = []
    for e in exc.errors()[:3]:
        where = ".".join(str(x) for x in e.get("loc", ()))
        parts.append(f"{where}: {e.get('msg', 'invalid')}" if where else str(e.get("msg", "invalid")))
    more = len(exc.errors()) - 3
    return "; ".join(parts) + (f" (and {more} more)" if more > 0 else "")


def _methods_of(app: FastAPI, path: str) -> list[str]:
    """The methods the OpenAPI document lists for ``path`` (a literal segment or a {parameter})."""
    methods: set[str] = set()
    for template, ops in app.openapi().get("paths", {}).items():
        if re.fullmatch(re.sub(r"\{[^/]+\}", "[^/]+", template), path):
            methods |= {m.upper() for m in ops}
    return sorted(methods)


def create_app(srv: Any) -> FastAPI:
    """The API of ``srv`` (a training_server.server.Server, or a test double with its attributes)."""
    # FastAPIOffline: the /docs and /redoc pages load Swagger UI and ReDoc from the server itself, not
    # a CDN (robot sites' networks are often offline)
    app = FastAPIOffline(title="MuRES fleet training server", version="1", description=__doc__)
    app.state.server = srv
    app.state.metrics = metrics.registry_for(srv)
    for module in (health, maps, fleet, live, missions, detections, episodes, policies, training_runs):
        app.include_router(module.router, prefix=API_PREFIX)
    app.include_router(metrics.router)
    mount_console(app)
    app.add_middleware(BodyLimit)

    @app.middleware("http")
    async def audit_operator_actions(request: Request, call_next: Any) -> Any:
        """Every operator action (and every attempt at one) in the audit log: who, what, when, answer."""
        response = await call_next(request)
        if getattr(request.state, "audit", False):
            srv.audit.write(
                who=getattr(request.state, "who", "unknown"),
                client=request.client.host if request.client else "unknown",
                action=f"{request.method} {request.url.path}",
                query=str(request.url.query) or None,
                status=response.status_code,
            )
        return response

    @app.exception_handler(StarletteHTTPException)
    def _http_error(req: Request, exc: StarletteHTTPException) -> JSONResponse:
        headers = dict(exc.headers or {})
        detail = str(exc.detail)
        if exc.status_code == 405:  # every method the path has, not only those of the first route matched
            headers["Allow"] = ", ".join(_methods_of(app, req.url.path)) or headers.get("Allow", "GET")
            detail = f"{req.method} is not allowed on {req.url.path}; use {headers['Allow']}"
        elif exc.status_code == 400 and detail == "There was an error parsing the body":
            detail = "the request body is not valid JSON (UTF-8)"
        return JSONResponse({"error": detail}, status_code=exc.status_code, headers=headers)

    @app.exception_handler(RequestValidationError)
    def _invalid(_req: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"error": _validation_message(exc)}, status_code=422)

    @app.exception_handler(Exception)
    def _server_error(req: Request, exc: Exception) -> JSONResponse:
        log.exception("%s %s failed", req.method, req.url.path)
        return JSONResponse({"error": "internal server error (logged)"}, status_code=500)

    def openapi() -> dict[str, Any]:
        """FastAPI's document, with its default 422 (HTTPValidationError) replaced by our Error
        (validation failures are answered by ``_invalid`` above), and the 413 of ``BodyLimit``,
        which any request can meet, on every operation."""
        if app.openapi_schema is None:
            spec = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
            error = {"application/json": {"schema": {"$ref": "#/components/schemas/Error"}}}
            for ops in spec.get("paths", {}).values():
                for op in ops.values():
                    responses = op.setdefault("responses", {})
                    if "422" in responses:
                        responses["422"] = {"description": DESCRIPTIONS[422], "content": error}
                    if "requestBody" in op:  # a body that is not JSON at all
                        responses["400"] = {"description": DESCRIPTIONS[400], "content": error}
                    responses["413"] = {"description": DESCRIPTIONS[413], "content": error}
            schemas = spec.get("components", {}).get("schemas", {})
            for name in ("HTTPValidationError", "ValidationError"):
                schemas.pop(name, None)
            app.openapi_schema = spec
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    return app

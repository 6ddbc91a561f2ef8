"""The operator console: server-rendered pages (Jinja2) at / on the server's HTTP port, with the
static assets shipped in this package (no build step, no CDN).

Pages hold no fleet data themselves: the browser keeps the token the operator signs in with for
the browser session (sessionStorage) and fills each page from the REST API and the event stream
(GET /api/v1/events), sending the token as every API client does. So a page needs no token, and
the API's roles apply unchanged: the agent token gives a read-only view, operator actions need the
operator token. Pages are sent with a Content-Security-Policy that allows this server's own
scripts, styles and connections only.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import HTMLResponse, RedirectResponse
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates

import shared

HERE = Path(__file__).resolve().parent
STATIC_PREFIX = "/console/static"
CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; "
    "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'"
)

PAGES = {  # path -> (template, title, navigation label or None)
    "/": ("fleet.html", "Fleet", "Fleet"),
    "/missions": ("missions.html", "Missions", "Missions"),
    "/policies": ("policies.html", "Policies", "Policies"),
    "/training": ("training.html", "Training", "Training"),
    "/data": ("data.html", "Data", "Data"),
    "/signin": ("signin.html", "Sign in", None),
}

templates = Jinja2Templates(directory=str(HERE / "templates"))
router = APIRouter(include_in_schema=False)


def _render(request: Request, template: str, title: str, **extra: Any) -> HTMLResponse:
    srv = request.app.state.server
    context = {
        "title": title,
        "fleet": srv.fleet,
        "map_name": srv.graph.name,
        "nodes": srv.graph.n,
        "release": shared.__version__,
        "nav": [(path, label) for path, (_t, _ti, label) in PAGES.items() if label],
        "path": request.url.path,
        "static": STATIC_PREFIX,
        **extra,
    }
    t0 = time.perf_counter()
    response = templates.TemplateResponse(request, template, context)
    response.headers["Server-Timing"] = f"render;dur={(time.perf_counter() - t0) * 1e3:.3f}"  # ms
    response.headers["Content-Security-Policy"] = CSP
    response.headers["X-Content-Type-Options"] = "nosniff"
    response.headers["Referrer-Policy"] = "no-referrer"
    response.headers["Cache-Control"] = "no-store"
    return response


def _page(template: str, title: str) -> Any:
    def handler(request: Request) -> HTMLResponse:
        from training_server.jobs import TrainingParams
        from training_server.methods import DEFAULT_CANDIDATES, METHODS

        return _render(  # the retrain form's defaults and choices
            request,
            template,
            title,
            defaults=TrainingParams(),
            beta_help=TrainingParams.model_fields["beta"].description,
            methods=METHODS,
            candidates=DEFAULT_CANDIDATES,
        )

    return handler


for _path, (_template, _title, _label) in PAGES.items():
    router.add_api_route(_path, _page(_template, _title), methods=["GET"], response_class=HTMLResponse)


@router.get("/missions/{mission_id}", response_class=HTMLResponse)
def replay_page(request: Request, mission_id: str) -> HTMLResponse:
    return _render(request, "replay.html", f"Mission {mission_id}", mission_id=mission_id)


@router.get("/console")
def console_root() -> RedirectResponse:
    return RedirectResponse("/", status_code=308)


def mount(app: FastAPI) -> None:
    """Add the console's pages and static assets to ``app``."""
    app.include_router(router)
    app.mount(STATIC_PREFIX, StaticFiles(directory=str(HERE / "static")), name="console-static")

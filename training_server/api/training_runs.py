"""/api/v1/training-runs: retrain (EM on the fleet's records, CE-PG, the gate, a new version)."""

from __future__ import annotations

import time
import uuid

from fastapi import APIRouter, HTTPException, Response

from training_server.api.deps import READ, WRITE, Srv, errors
from training_server.api.models import TrainingRun, TrainingRunList
from training_server.jobs import TrainingParams

router = APIRouter(prefix="/training-runs", tags=["training-runs"])


def run_view(srv: Srv, run_id: str) -> TrainingRun:
    r = srv.store.get_run(run_id)
    if r is None:
        raise HTTPException(404, f"no training run {run_id!r}")
    return TrainingRun(**r)


@router.post("", status_code=202, dependencies=WRITE, responses=errors(401, 403, 409, 422))
def start_run(response: Response, srv: Srv, req: TrainingParams | None = None) -> TrainingRun:
    """Queue a retrain: EM on the stored records, CE-PG from the current policy, the gate, a new version."""
    params = req or TrainingParams()
    usable = srv.store.episode_stats(srv.fleet)["usable_missions"]
    if usable < params.min_missions:
        raise HTTPException(
            409,
            f"too little data to retrain: {usable} missions recorded, {params.min_missions} needed "
            f"({params.min_missions - usable} more); fly more missions (or lower min_missions)",
        )
    if params.speed is not None and srv.graph.edge_lengths is None:
        raise HTTPException(
            409,
            f"speed retrains on travel times, and the map {srv.graph.name} has no edge lengths: import it with "
            "`mures map import` (edge_lengths_m)",
        )
    run_id = f"run-{time.strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:6]}"
    srv.store.add_run(run_id, params.model_dump())
    srv.supervisor.submit(run_id)
    response.headers["Location"] = f"/api/v1/training-runs/{run_id}"
    return run_view(srv, run_id)


@router.get("", dependencies=READ, responses=errors(401))
def runs(srv: Srv) -> TrainingRunList:
    return TrainingRunList(items=[TrainingRun(**r) for r in srv.store.runs()])


@router.get("/{run_id}", dependencies=READ, responses=errors(401, 404))
def get_run(run_id: str, srv: Srv) -> TrainingRun:
    return run_view(srv, run_id)


@router.post("/{run_id}/cancel", status_code=202, dependencies=WRITE, responses=errors(401, 403, 404, 409))
def cancel_run(run_id: str, srv: Srv) -> TrainingRun:
    """Cancel a queued run (at once) or a running one (its process stops at its next check; the run
    stays cancelled across a server restart)."""
    r = run_view(srv, run_id)
    if srv.store.request_cancel(run_id) is None:
        raise HTTPException(409, f"run {run_id!r} is {r.status}; nothing to cancel")
    srv.supervisor.cancel(run_id)
    return run_view(srv, run_id)

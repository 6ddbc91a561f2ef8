"""GET /metrics: Prometheus text exposition (prometheus-client). A fleet token is needed, as for
the API's reads, unless the server was started with ``--metrics-without-token``.

A collector reads the server's state at scrape time (what the store and the bus already count),
so nothing is double-counted and a restart shows the stored totals."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request, Response
from fastapi.security import HTTPAuthorizationCredentials
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from training_server.api.deps import _bearer, errors, role

RUN_STATUSES = ("queued", "running", "succeeded", "failed", "cancelled")

router = APIRouter(tags=["metrics"])


class ServerCollector(Collector):
    def __init__(self, srv: Any) -> None:
        self.srv = srv

    def collect(self) -> Iterator[Metric]:
        srv = self.srv
        st = srv.store.episode_stats(srv.fleet)
        yield GaugeMetricFamily("mures_episodes_stored", "Episode records stored.", value=st["stored"])
        rejected = CounterMetricFamily(
            "mures_episodes_rejected", "Episode records rejected, by reason.", labels=["reason"]
        )
        for reason, count in st["rejected"].items():
            rejected.add_metric([reason], count)
        yield rejected
        yield GaugeMetricFamily(
            "mures_agents_online", "Agents with a liveliness token.", value=len(srv.bus.agents_online())
        )
        runs = GaugeMetricFamily("mures_training_runs", "Training runs by status.", labels=["status"])
        statuses = [r["status"] for r in srv.store.runs()]
        for s in RUN_STATUSES:
            runs.add_metric([s], statuses.count(s))
        yield runs
        yield GaugeMetricFamily(
            "mures_policy_current_version", "The policy version agents are told to fly.", value=srv.current_version()
        )
        yield CounterMetricFamily(
            "mures_ingest_seconds",
            "Time spent validating and storing episode batches.",
            value=srv.bus.stats["ingest_seconds"],
        )
        yield CounterMetricFamily(
            "mures_ingest_batches", "Episode batches validated and stored.", value=srv.bus.stats["ingest_batches"]
        )


def registry_for(srv: Any) -> CollectorRegistry:
    """A registry of this server's own (not the process-global one: tests run several apps)."""
    reg = CollectorRegistry(auto_describe=False)  # collect() only when scraped
    reg.register(ServerCollector(srv))
    return reg


def metrics_reader(request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> None:
    """Any fleet token (401 without one), unless the server serves metrics without a token."""
    if not getattr(request.app.state.server, "metrics_without_token", False):
        role(request, creds)


@router.get(
    "/metrics",
    response_class=Response,
    dependencies=[Depends(metrics_reader)],
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text exposition"}, **errors(401)},
)
def metrics(request: Request) -> Response:
    return Response(generate_latest(request.app.state.metrics), media_type=CONTENT_TYPE_LATEST)

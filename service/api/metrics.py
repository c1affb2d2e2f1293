"""``/metrics``: the instance's Prometheus registry in the text exposition format.

Rendered by prometheus_client (``generate_latest``), never by hand; the series are described in
:mod:`randt.service.metrics`. Scrape it like any exporter::

    scrape_configs:
      - job_name: randt
        static_configs: [{targets: ["127.0.0.1:8080"]}]
        # with RANDT_PROTECT_READS=true:  authorization: {credentials: "<RANDT_API_TOKEN>"}
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from randt.service.api.deps import ServiceDep, require_reader

__all__ = ["router"]

router = APIRouter(tags=["metrics"])


@router.get(
    "/metrics",
    response_class=Response,
    dependencies=[Depends(require_reader)],
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format"}},
)
def metrics(svc: ServiceDep) -> Response:
    """Scans received, processed, rejected by reason, dropped; registration and latency histograms;
    queue depth per session; tiles written; store errors; tiles and points per map."""
    return Response(generate_latest(svc.metrics.registry), media_type=CONTENT_TYPE_LATEST)

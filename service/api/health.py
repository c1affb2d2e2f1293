"""``/healthz``, ``/readyz`` and ``/status``: is the process alive, can it work, what is it doing."""

from __future__ import annotations

import time

from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse
from prometheus_client import Metric

from randt.service.api.deps import ServiceDep, require_reader
from randt.service.api.models import CapacityStatus, GraphStatus, Health, MapSummary, Ready, Status
from randt.service.api.views import map_summary, session_summary
from randt.service.runtime import Service
from randt.service.sessions import SessionManager

__all__ = ["router"]

router = APIRouter(tags=["health"])


def _total(metric_collect: list[Metric]) -> int:
    """Sum of a counter's ``*_total`` samples over all its labels."""
    return int(sum(s.value for m in metric_collect for s in m.samples if s.name.endswith("_total")))


def readiness(svc: Service) -> Ready:
    """Each readiness condition (``/readyz``) on its own."""
    zenoh = not svc.with_zenoh or (svc.transport is not None and svc.transport.is_open)
    store = svc.store is not None and svc.store.writable()
    workers = svc.sessions is not None and svc.sessions.running
    warm = svc.sessions is not None and svc.sessions.matchers_warm
    g = None if svc.sessions is None else svc.sessions.graph
    graph = g is None or not g.started or (g.running and not g.replaying)
    return Ready(
        ready=zenoh and store and workers and warm and graph,
        zenoh=zenoh,
        store_writable=store,
        workers=workers,
        matchers_warm=warm,
        graph=graph,
    )


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """The process is alive (a liveness probe: no checks, always open)."""
    return Health()


@router.get("/readyz", response_model=Ready, responses={503: {"model": Ready}})
def readyz(svc: ServiceDep) -> JSONResponse:
    """Zenoh open, store writable, session workers running, matchers warm, the pose graph process
    running (once started): 200, else 503 (always open)."""
    ready = readiness(svc)
    return JSONResponse(ready.model_dump(), status_code=200 if ready.ready else 503)


@router.get("/status", response_model=Status, dependencies=[Depends(require_reader)])
def status(svc: ServiceDep) -> Status:
    """Instance, uptime, running sessions, scan counts, queue depths, drops, maps (extent, tiles)."""
    mgr = svc.sessions
    m = svc.metrics
    workers = mgr.sessions() if mgr else []
    depths = mgr.queue_depths() if mgr else {}
    g = None if mgr is None else mgr.graph
    maps: dict[str, MapSummary] = {}
    if mgr is not None:
        for name, grid in sorted(dict(mgr.maps).items()):
            maps[name] = map_summary(name, grid, workers)
    return Status(
        instance=svc.settings.instance,
        uptime_s=time.time() - svc.started_at,
        ready=readiness(svc).ready,
        sessions=[session_summary(info, None, depths) for info in workers],
        scans_received=_total(list(m.scans_received.collect())),
        scans_processed=_total(list(m.scans_processed.collect())),
        scans_rejected=_total(list(m.scans_rejected.collect())),
        scans_dropped=_total(list(m.scans_dropped.collect())),
        queue_depths=depths,
        maps=maps,
        graph=GraphStatus(
            enabled=g is not None,
            running=g is not None and g.running,
            restarts=0 if g is None else g.restarts,
            last_exit=None if g is None else g.last_exit,
            pending=0 if g is None else g.pending,
            replaying=g is not None and g.replaying,
        ),
        capacity=_capacity(mgr),
    )


def _capacity(mgr: SessionManager | None) -> CapacityStatus | None:
    f = None if mgr is None else mgr.capacity_figures()
    if f is None:
        return None
    return CapacityStatus(
        cores=f.cores,
        target=f.target,
        load=round(f.load, 4),
        used_cores=round(f.used_cores, 4),
        sweep_cpu_ms=round(1000 * f.sweep_cpu_s, 3),
        service_cpu_ms=round(1000 * f.service_cpu_s, 3),
        sessions_more=f.sessions_more,
        measured_sessions=f.measured_sessions,
    )

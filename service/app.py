"""FastAPI app factory: the service's HTTP face, its lifespan starting and stopping the Service.

Routers per resource come with issue 5; this module holds the factory and the health and status
routes ``randt serve`` needs from the start.
"""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from service.runtime import Service
from service.settings import ServiceSettings

__all__ = ["create_app"]


def create_app(settings: ServiceSettings | None = None, *, with_zenoh: bool = True) -> FastAPI:
    """Build the app; settings are read here (environment), not at import time."""
    settings = settings or ServiceSettings()
    service = Service(settings, with_zenoh=with_zenoh)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service.start()
        try:
            yield
        finally:
            service.stop()

    app = FastAPI(title="randt-fleet", version="0.1.0", lifespan=lifespan)
    app.state.service = service

    @app.get("/healthz")
    def healthz() -> dict[str, str]:
        """The process is alive."""
        return {"status": "ok"}

    @app.get("/readyz")
    def readyz(request: Request) -> JSONResponse:
        """Zenoh session open, store writable, session manager running."""
        svc: Service = request.app.state.service
        ok = svc.ready
        return JSONResponse({"ready": ok}, status_code=200 if ok else 503)

    @app.get("/status")
    def status(request: Request) -> dict[str, object]:
        """Instance, uptime, sessions, scans processed, queue depths, drops, maps."""
        svc: Service = request.app.state.service
        mgr = svc.sessions
        sessions = mgr.sessions() if mgr else []
        return {
            "instance": svc.settings.instance,
            "uptime_s": time.time() - svc.started_at,
            "sessions": [
                {
                    "vehicle": s.vehicle,
                    "session": s.session,
                    "map": s.map_name,
                    "frame": s.frame,
                    "scans": s.n_scans,
                    "fallbacks": s.n_fallbacks,
                    "errors": s.n_errors,
                    "last_seq": s.last_seq,
                    "last_status": s.last_status,
                }
                for s in sessions
            ],
            "queue_depths": mgr.queue_depths() if mgr else {},
            "scans_dropped": int(svc.metrics.registry.get_sample_value("randt_scans_dropped_total") or 0),
            "maps": {
                name: {"tiles": len(grid), "points": grid.n_points}
                for name, grid in (mgr.maps.items() if mgr else [])
            },
        }

    return app

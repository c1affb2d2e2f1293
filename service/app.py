"""FastAPI app factory: the service's HTTP face, its lifespan starting and stopping the Service.

``create_app`` builds the settings (from the environment unless given), the
:class:`~randt.service.runtime.Service` (store, session workers, Zenoh transport) and the app; the
lifespan starts the service before the first request and stops it (drain, flush, close Zenoh) on
shutdown, so ``randt serve``'s SIGTERM and SIGINT stop everything cleanly. The routes live in
:mod:`randt.service.api`, one router per resource; ``docs/api.md`` documents them, ``/docs`` serves the
OpenAPI UI (Swagger UI vendored: it works offline). The project's errors (:mod:`randt.core.errors`)
become HTTP answers in one exception handler, registered here, with one table
(:mod:`randt.service.api.errors`).
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from randt.service import api
from randt.service.api.errors import HTTP_STATUS, error_response
from randt.service.runtime import Service
from randt.service.settings import ServiceSettings

__all__ = ["HeadAsGet", "create_app"]

_DESCRIPTION = """Status, sessions, Prometheus metrics, trajectories and map tiles of a randt-fleet
service. Mutating endpoints need `Authorization: Bearer <RANDT_API_TOKEN>`; reads are open unless
`RANDT_PROTECT_READS=true`. The map viewer is at `/`."""


class HeadAsGet:
    """``HEAD`` answered wherever ``GET`` is (RFC 9110 9.3.2: the same status and headers, no
    body): FastAPI routes ``GET`` only, so ``HEAD`` would answer 405. The request runs as its
    ``GET`` (a ``HEAD`` costs what the ``GET`` does) and the body is dropped."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return
        done = False

        async def headers_only(message: Message) -> None:
            nonlocal done
            if message["type"] != "http.response.body":
                await send(message)
            elif not done and not message.get("more_body", False):
                done = True
                await send({"type": "http.response.body", "body": b"", "more_body": False})

        get: dict[str, Any] = {**scope, "method": "GET"}
        await self.app(get, receive, headers_only)


def create_app(settings: ServiceSettings | None = None, *, with_zenoh: bool = True) -> FastAPI:
    """Build the app; settings are read here (environment), not at import time.

    Parameters
    ----------
    settings:
        The service's settings; ``None`` reads ``RANDT_*`` from the environment.
    with_zenoh:
        ``False`` runs without the Zenoh transport (tests feed scans to ``app.state.service``).
    """
    settings = settings or ServiceSettings()
    service = Service(settings, with_zenoh=with_zenoh)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        service.start()
        try:
            yield
        finally:
            service.stop()

    app = FastAPI(
        title="randt-fleet",
        version="0.1.0",
        description=_DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # served from vendored assets instead (service/api/docs.py): works offline
        redoc_url=None,  # ReDoc would load from a CDN too
    )
    app.state.service = service
    for error_class in HTTP_STATUS:  # one handler, one table: the project's errors -> status codes
        app.add_exception_handler(error_class, error_response)
    api.install(app)
    app.add_middleware(HeadAsGet)
    return app

"""The HTTP API: one router per resource, assembled by :func:`install`.

=================  ===========================================================  ==============
module             paths                                                        auth
=================  ===========================================================  ==============
``health``         ``/healthz``, ``/readyz``, ``/status``                       probes open
``sessions``       ``/sessions``, ``/sessions/{vehicle}/{session}[/trajectory]``  read
                   ``POST /sessions/{vehicle}/{session}/close``                 token
``maps``           ``/maps``, ``/maps/{map}[/tiles[/{ix}/{iy}]|/metadata.yaml|    read
                   /export]``
``metrics``        ``/metrics``                                                 read
``viewer``         ``/`` and ``/static/*``                                      open
=================  ===========================================================  ==============

``deps`` holds what they share (service, auth, validated names), ``models`` the response
models, ``views`` the builders of those models, ``encoding`` the point-cloud file bodies.
Errors: a missing resource raises :class:`~service.api.deps.NotFoundHTTPError`, rendered by one
handler here as ``404 {"detail", "resource", "id"}``; every other error is FastAPI's
``{"detail": ...}`` (422 for invalid names, coordinates and parameters).
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse

from service.api import health, maps, metrics, sessions, viewer
from service.api.deps import NotFoundHTTPError
from service.api.maps import PduCache

__all__ = ["install"]


async def _not_found(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, NotFoundHTTPError)
    return JSONResponse({"detail": exc.detail, "resource": exc.resource, "id": exc.ident}, status_code=404)


def install(app: FastAPI) -> None:
    """Add every router, the viewer and the not-found handler to ``app``."""
    app.state.pdu_cache = PduCache()
    app.add_exception_handler(NotFoundHTTPError, _not_found)
    for module in (health, sessions, maps, metrics):
        app.include_router(module.router)
    viewer.mount_viewer(app)

"""The HTTP API: one router per resource, assembled by :func:`install`.

=================  ===========================================================  ==============
module             paths                                                        auth
=================  ===========================================================  ==============
``health``         ``/healthz``, ``/readyz``, ``/status``                       probes open
``sessions``       ``/sessions``, ``/sessions/{vehicle}/{session}[/trajectory]``  read
                   ``POST /sessions/{vehicle}/{session}/close``                 token
``maps``           ``/maps``, ``/maps/{map}[/tiles[/{ix}/{iy}]|/metadata.yaml|    read
                   /export|/graph]``
``metrics``        ``/metrics``                                                 read
``viewer``         ``/`` and ``/static/*``                                      open
``docs``           ``/docs`` (Swagger UI from ``/static/vendor/swagger-ui``)    open
=================  ===========================================================  ==============

``deps`` holds what they share (service, auth, validated names), ``models`` the response
models, ``views`` the builders of those models, ``encoding`` the point-cloud file bodies.
Errors: routes raise the project's errors (:mod:`randt.core.errors`: a missing resource is a
:class:`~randt.core.errors.NotFoundError` naming its ``resource`` and ``ident``);
:mod:`randt.service.api.errors`
maps them to status codes in one table, registered by the app factory. A 404 answers
``{"detail", "resource", "id"}``, every other error ``{"detail": ...}`` (FastAPI's own 422 for
invalid names, coordinates and parameters).
"""

from __future__ import annotations

from fastapi import FastAPI

from randt.service.api import docs, health, maps, metrics, sessions, viewer
from randt.service.api.maps import PduCache

__all__ = ["install"]


def install(app: FastAPI) -> None:
    """Add every router and the viewer to ``app``."""
    app.state.pdu_cache = PduCache()
    for module in (health, sessions, maps, metrics, docs):
        app.include_router(module.router)
    viewer.mount_viewer(app)

"""The HTTP API: one router per resource (``health``, ``sessions``, ``maps``, ``metrics``,
``viewer``, ``docs``), assembled by :func:`install`.

``deps`` holds what they share (service, auth, validated names), ``models`` the response models,
``views`` their builders, ``encoding`` the point-cloud file bodies, ``errors`` the one table from
the project's errors to status codes. Endpoints, auth and error bodies: docs/api.md.
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

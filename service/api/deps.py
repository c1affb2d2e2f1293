"""What the routers share: the service, auth, validated path parameters and the not-found error.

Auth
----
``RANDT_API_TOKEN`` is a bearer token (``Authorization: Bearer <token>``).

* mutating endpoints depend on :func:`require_writer`: no token configured -> **403** (they are
  refused, never open); missing or wrong token -> **401** with ``WWW-Authenticate: Bearer``;
* read endpoints depend on :func:`require_reader`: open unless ``RANDT_PROTECT_READS=true``, then
  the same check (the settings refuse ``protect_reads`` without a token).
* ``/healthz`` and ``/readyz`` stay open (probes carry no secrets), as do the viewer's static files
  (the page asks for the token when the API answers 401).

Ids
---
Map, vehicle and session names are checked against the id rule
(:data:`wire.ids.ID_REGEX`) by FastAPI before a handler runs (**422** otherwise), and tile
indices are bounded integers. Handlers look names up in the live maps and sessions; no file is ever
opened from a client-supplied string.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from core.tiles import TileGrid
from service.api.models import ErrorBody
from service.runtime import Service
from service.sessions import SessionManager
from wire.ids import ID_MAX_LENGTH, ID_REGEX

__all__ = [
    "MAX_TILE_INDEX",
    "MapName",
    "NotFoundHTTPError",
    "ServiceDep",
    "SessionName",
    "TileIx",
    "VehicleName",
    "get_grid",
    "get_manager",
    "get_service",
    "require_reader",
    "require_writer",
]

#: Largest |ix|, |iy| a tile index may have (the grid packs indices into 31 bits).
MAX_TILE_INDEX = (1 << 30) - 1

MapName = Annotated[
    str, Path(pattern=ID_REGEX, max_length=ID_MAX_LENGTH, description="map name, e.g. 'default'")
]
VehicleName = Annotated[str, Path(pattern=ID_REGEX, max_length=ID_MAX_LENGTH, description="vehicle id")]
SessionName = Annotated[
    str, Path(pattern=ID_REGEX, max_length=ID_MAX_LENGTH, description="session id of the vehicle")
]
TileIx = Annotated[int, Path(ge=-MAX_TILE_INDEX, le=MAX_TILE_INDEX, description="tile index")]


class NotFoundHTTPError(Exception):
    """A session, map or tile that does not exist; rendered as 404 ``{detail, resource, id}``."""

    def __init__(self, resource: str, ident: str, detail: str | None = None) -> None:
        self.resource = resource
        self.ident = ident
        self.detail = detail or f"{resource} {ident!r} not found"
        super().__init__(self.detail)


def get_service(request: Request) -> Service:
    """The :class:`~service.runtime.Service` the app factory attached to the app."""
    return request.app.state.service


ServiceDep = Annotated[Service, Depends(get_service)]


def get_manager(svc: ServiceDep) -> SessionManager:
    """The running session manager (503 while the service is starting or stopped)."""
    if svc.sessions is None:
        raise HTTPException(status.HTTP_503_SERVICE_UNAVAILABLE, "the service is not running")
    return svc.sessions


def get_grid(mgr: SessionManager, name: str) -> TileGrid:
    """The live map ``name`` (404 if there is none)."""
    grid = mgr.maps.get(name)
    if grid is None:
        raise NotFoundHTTPError("map", name)
    return grid


_bearer = HTTPBearer(auto_error=False, description="RANDT_API_TOKEN")
_Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


def _check_token(expected: str, credentials: HTTPAuthorizationCredentials | None) -> None:
    if credentials is None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing bearer token (Authorization: Bearer <RANDT_API_TOKEN>)",
            headers={"WWW-Authenticate": "Bearer"},
        )
    if not hmac.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "wrong bearer token",
            headers={"WWW-Authenticate": 'Bearer error="invalid_token"'},
        )


#: The answers :func:`require_writer` can give, for a mutating route's ``responses``.
WRITER_RESPONSES: dict[int | str, dict[str, object]] = {
    401: {"model": ErrorBody, "description": "missing or wrong bearer token"},
    403: {"model": ErrorBody, "description": "no RANDT_API_TOKEN configured: mutations are disabled"},
}


def require_writer(svc: ServiceDep, credentials: _Credentials) -> None:
    """Guard of mutating endpoints (module docstring): 403 without a configured token, else 401."""
    token = svc.settings.api_token
    if not token:
        raise HTTPException(
            status.HTTP_403_FORBIDDEN,
            "mutating endpoints are disabled: no RANDT_API_TOKEN is configured on the service",
        )
    _check_token(token, credentials)


def require_reader(svc: ServiceDep, credentials: _Credentials) -> None:
    """Guard of read endpoints: open unless ``RANDT_PROTECT_READS`` is set (module docstring)."""
    token = svc.settings.api_token
    if svc.settings.protect_reads and token:
        _check_token(token, credentials)

"""What the routers share: the service, auth and validated path parameters.

Mutating endpoints depend on :func:`require_writer` (no ``RANDT_API_TOKEN`` configured: 403;
a missing or wrong bearer token: 401), read endpoints on :func:`require_reader` (open unless
``RANDT_PROTECT_READS=true``); ``/healthz``, ``/readyz`` and the viewer's files stay open. Names
are checked against the id rule before a handler runs (422), so no file is ever opened from a
client-supplied string (docs/api.md, "Conventions" and "Auth").
"""

from __future__ import annotations

import hmac
import re
from typing import Annotated, Any

from fastapi import Depends, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BeforeValidator

from randt.core.errors import AuthError, ForbiddenError, NotFoundError, UnavailableError
from randt.core.tiles import TileGrid
from randt.service.api.models import ErrorBody
from randt.service.runtime import Service
from randt.service.sessions import SessionManager
from randt.wire.ids import ID_MAX_LENGTH, ID_REGEX

__all__ = [
    "MAX_TILE_INDEX",
    "MapName",
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
#: A tile index as ``tile_id`` writes it: an optional minus, then digits without leading zeros.
#: Python's and pydantic's lax ``int`` would also take ``1.0``, ``+1``, `` 1``, ``0_0`` and ``01``.
TILE_INDEX_REGEX = re.compile(r"0|-?[1-9][0-9]{0,9}")


def _strict_tile_index(value: object) -> object:
    if isinstance(value, str) and TILE_INDEX_REGEX.fullmatch(value) is None:
        raise ValueError(f"a tile index is an integer written as 0 or -?[1-9][0-9]*, not {value[:40]!r}")
    return value


TileIx = Annotated[
    int,
    BeforeValidator(_strict_tile_index),
    Path(ge=-MAX_TILE_INDEX, le=MAX_TILE_INDEX, description="tile index (an integer as written: 0, 12, -3)"),
]


def get_service(request: Request) -> Service:
    """The :class:`~randt.service.runtime.Service` the app factory attached to the app."""
    return request.app.state.service


ServiceDep = Annotated[Service, Depends(get_service)]


def get_manager(svc: ServiceDep) -> SessionManager:
    """The running session manager (503 while the service is starting or stopped)."""
    if svc.sessions is None:
        raise UnavailableError("the service is not running")
    return svc.sessions


def get_grid(mgr: SessionManager, name: str) -> TileGrid:
    """The live map ``name`` (404 if there is none)."""
    grid = mgr.maps.get(name)
    if grid is None:
        raise NotFoundError(resource="map", ident=name)
    return grid


_bearer = HTTPBearer(auto_error=False, description="RANDT_API_TOKEN")
_Credentials = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


def _check_token(expected: str, credentials: HTTPAuthorizationCredentials | None) -> None:
    if credentials is None:
        raise AuthError("missing bearer token (Authorization: Bearer <RANDT_API_TOKEN>)", challenge="Bearer")
    if not hmac.compare_digest(credentials.credentials.encode(), expected.encode()):
        raise AuthError("wrong bearer token", challenge='Bearer error="invalid_token"')


#: The answers :func:`require_writer` can give, for a mutating route's ``responses``.
WRITER_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorBody, "description": "missing or wrong bearer token"},
    403: {"model": ErrorBody, "description": "no RANDT_API_TOKEN configured: mutations are disabled"},
}


def require_writer(svc: ServiceDep, credentials: _Credentials) -> None:
    """Guard of mutating endpoints: 403 without a configured token, else 401 on a missing or
    wrong one."""
    token = svc.settings.api_token
    if not token:
        raise ForbiddenError(
            "mutating endpoints are disabled: no RANDT_API_TOKEN is configured on the service"
        )
    _check_token(token, credentials)


def require_reader(svc: ServiceDep, credentials: _Credentials) -> None:
    """Guard of read endpoints: open unless ``RANDT_PROTECT_READS`` is set, then as :func:`require_writer`."""
    token = svc.settings.api_token
    if svc.settings.protect_reads and token:
        _check_token(token, credentials)

"""The one map from the project's exception tree (:mod:`randt.core.errors`) to HTTP answers.

Routes and dependencies raise the tree's errors; :func:`error_response`, registered by the app
factory for every class of :data:`HTTP_STATUS` (the most specific class wins), answers its status
with an :class:`~randt.service.api.models.ErrorBody` (a 404 also names ``resource`` and ``id``; a
401 carries ``WWW-Authenticate``). Errors outside the table stay 500. The table: docs/api.md,
"Conventions".
"""

from __future__ import annotations

from fastapi import Request
from fastapi.responses import JSONResponse

from randt.core.errors import (
    AuthError,
    BadMessageError,
    ConflictError,
    ForbiddenError,
    FormatError,
    InvalidCloudError,
    InvalidRequestError,
    NotFoundError,
    RandtError,
    UnavailableError,
)

__all__ = ["HTTP_STATUS", "error_response", "status_of"]

#: Status code of each error class the API answers (subclasses included, most specific first).
HTTP_STATUS: dict[type[RandtError], int] = {
    InvalidRequestError: 422,
    BadMessageError: 422,
    InvalidCloudError: 422,
    FormatError: 422,
    AuthError: 401,
    ForbiddenError: 403,
    NotFoundError: 404,
    ConflictError: 409,
    UnavailableError: 503,
}


def status_of(exc: BaseException) -> int | None:
    """The status code :data:`HTTP_STATUS` gives ``exc``'s most specific class (None: not mapped)."""
    for cls in type(exc).__mro__:
        code = HTTP_STATUS.get(cls)
        if code is not None:
            return code
    return None


async def error_response(request: Request, exc: Exception) -> JSONResponse:
    """The answer to an error of :data:`HTTP_STATUS` (the module docstring's table)."""
    code = status_of(exc)
    if code is None:  # registered only for the table's classes: a mistake in the app factory
        raise exc
    body: dict[str, str | None] = {"detail": str(exc)}
    headers: dict[str, str] = {}
    if isinstance(exc, NotFoundError) and exc.resource is not None:
        body.update(resource=exc.resource, id=exc.ident)
    if isinstance(exc, AuthError) and exc.challenge and code == 401:
        headers["WWW-Authenticate"] = exc.challenge
    return JSONResponse(body, status_code=code, headers=headers or None)

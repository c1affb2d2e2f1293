"""The one map from the project's exception tree (:mod:`randt.core.errors`) to HTTP answers.

Routes and dependencies raise the tree's errors; :func:`error_response`, registered by the app
factory (:func:`randt.service.app.create_app`) for every class of :data:`HTTP_STATUS`, turns them into
status codes and the :class:`~randt.service.api.models.ErrorBody` JSON:

======================================================  ======  ===================================
error (and its subclasses)                              status  body
======================================================  ======  ===================================
:class:`~randt.core.errors.InvalidRequestError`,              422     ``{"detail"}``
:class:`~randt.core.errors.BadMessageError`,
:class:`~randt.core.errors.InvalidCloudError`,
:class:`~randt.core.errors.FormatError`
:class:`~randt.core.errors.AuthError`                         401     ``{"detail"}``, ``WWW-Authenticate``
:class:`~randt.core.errors.ForbiddenError`                    403     ``{"detail"}``
:class:`~randt.core.errors.NotFoundError`                     404     ``{"detail", "resource", "id"}``
:class:`~randt.core.errors.ConflictError`                     409     ``{"detail"}``
:class:`~randt.core.errors.UnavailableError`                  503     ``{"detail"}``
======================================================  ======  ===================================

The most specific class wins (a :class:`~randt.core.errors.ForbiddenError` is an
:class:`~randt.core.errors.AuthError` answered 403). Errors outside the table (a failed registration,
a broken store) stay server errors: 500, logged by the server. FastAPI's own request validation
answers 422 ``{"detail": [...]}`` before a handler runs.
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

"""The project's exception tree: one root, a handful of subclasses.

::

    RandtError                      root of every error this project raises on purpose
    ├── InvalidCloudError           empty, too few points, wrong shape or dtype
    ├── DegenerateProblemError      the geometry does not constrain all 6 DoF (e.g. one plane)
    ├── RegistrationFailedError     the optimiser diverged or produced a non-finite pose
    │   └── NotRelocalizedError     a sweep did not match the map at the place guessed for it
    ├── FormatError                 a file could not be read or written in the named format
    │   └── NoScansError            a sequence folder holds no scan files (randt.core.datasets)
    ├── BadMessageError             a wire message failed to decode or validate (service)
    ├── InvalidRequestError         an API request's parameters are malformed (service)
    ├── NotFoundError               a session, map, tile or file that does not exist
    ├── ConflictError               the request conflicts with the current state
    │   └── MapInUseError           running sessions fold scans into the map (randt.service.sessions)
    ├── AuthError                   missing or wrong credentials (service)
    │   └── ForbiddenError          refused whatever the credentials (mutations disabled)
    ├── UnavailableError            the service is starting or stopping (service)
    ├── ConfigurationError          the Ray executor cannot start as configured (randt.service.ray_executor)
    ├── MatcherProcessError         a matcher worker process failed (randt.service.matchers)
    │   └── MatcherProcessDiedError     ... and is gone: its sessions resume from the store
    ├── DataDirInUseError           another process holds the data directory (randt.service.store)
    ├── ApiError                    the service answered with an HTTP error (randt.clients.rest)
    │   └── ApiNotFoundError        ... 404; also a NotFoundError
    ├── PortInUseError              a port a command would listen on is taken (randt.cli.errors)
    └── WrongInputError             a directory where a file is expected, or the reverse (randt.cli.errors)

One place maps these to HTTP status codes (``randt.service.api.errors``) and one place to CLI exit codes
(``randt.cli.errors``); library code only raises them.

Every error of the tree survives pickling with its class, message and attributes
(``pickle.loads(pickle.dumps(exc))``): the service's matcher processes send the errors raised
there back to the session threads, which see the same :class:`DegenerateProblemError` (with its
``weak_directions``) or :class:`BadMessageError` (with its ``code``) as an in-process call would.
"""

from __future__ import annotations

from typing import Any

__all__ = [
    "AuthError",
    "BadMessageError",
    "ConflictError",
    "DegenerateProblemError",
    "ForbiddenError",
    "FormatError",
    "InvalidCloudError",
    "InvalidRequestError",
    "NotFoundError",
    "NotRelocalizedError",
    "RandtError",
    "RegistrationFailedError",
    "UnavailableError",
]


def _restore(cls: type[RandtError], args: tuple[Any, ...]) -> RandtError:
    """Unpickle ``cls`` without calling its ``__init__`` (its state follows: ``__setstate__``)."""
    exc = cls.__new__(cls, *args)
    exc.args = args
    return exc


class RandtError(Exception):
    """Root of every error raised on purpose by randt-fleet.

    Pickled as class, ``args`` and instance attributes, rebuilt without calling ``__init__``: a
    subclass may take any constructor arguments (keyword-only, or several formatted into one
    message) and still cross a process boundary unchanged.
    """

    def __reduce__(self) -> tuple[Any, ...]:
        return (_restore, (type(self), self.args), self.__dict__ or None)


class InvalidCloudError(RandtError, ValueError):
    """A point cloud is unusable: empty, too few points, wrong shape or dtype."""


class DegenerateProblemError(RandtError):
    """The registration problem does not constrain every degree of freedom.

    Attributes
    ----------
    result:
        The :class:`randt.core.registration.RegistrationResult` reached anyway, so a caller can
        inspect it; its pose must not be trusted along ``weak_directions``.
    weak_directions:
        Human-readable names of the poorly constrained directions (``"tx"``, ``"rz"``...).
    """

    def __init__(self, message: str, *, result: Any = None, weak_directions: tuple[str, ...] = ()):
        super().__init__(message)
        self.result = result
        self.weak_directions = weak_directions


class RegistrationFailedError(RandtError):
    """The optimiser could not produce a usable transform (diverged, non-finite)."""


class NotRelocalizedError(RegistrationFailedError):
    """A sweep relocalized on the map (``IncrementalMatcher.register_scan``'s ``relocalize``)
    did not match it at the place guessed for it: the matcher is left as it was."""


class FormatError(RandtError, ValueError):
    """A file could not be read or written: unknown extension, malformed header, bad data."""


class BadMessageError(RandtError, ValueError):
    """A wire message failed to decode or validate. ``code`` is a stable machine-readable reason."""

    def __init__(self, message: str, *, code: str = "bad_message"):
        super().__init__(message)
        self.code = code


class InvalidRequestError(RandtError, ValueError):
    """A request's parameters are malformed or contradict each other (an inverted bounding box)."""


class NotFoundError(RandtError, LookupError):
    """A named session, map, tile or file does not exist.

    Attributes
    ----------
    resource:
        What was looked for (``"session"``, ``"map"``, ``"tile"``), when the raiser says so.
    ident:
        The name or id that was asked for, with ``resource``.
    """

    def __init__(self, message: str = "", *, resource: str | None = None, ident: str | None = None):
        super().__init__(message or f"{resource or 'resource'} {ident!r} not found")
        self.resource = resource
        self.ident = ident


class ConflictError(RandtError):
    """The request conflicts with the current state (deleting a map that is being written)."""


class AuthError(RandtError):
    """Credentials are missing or wrong. ``challenge`` is the ``WWW-Authenticate`` answer."""

    def __init__(self, message: str, *, challenge: str = "Bearer"):
        super().__init__(message)
        self.challenge = challenge


class ForbiddenError(AuthError):
    """The action is refused whatever the credentials (mutating endpoints without a configured token)."""

    def __init__(self, message: str):
        super().__init__(message, challenge="")


class UnavailableError(RandtError):
    """The service cannot answer now: it is starting or stopping (retry later)."""

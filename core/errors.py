"""The project's exception tree: one root, a handful of subclasses.

::

    RandtError                      root of every error this project raises on purpose
    ├── InvalidCloudError           empty, too few points, wrong shape or dtype
    ├── DegenerateProblemError      the geometry does not constrain all 6 DoF (e.g. one plane)
    ├── RegistrationFailedError     the optimiser diverged or produced a non-finite pose
    ├── FormatError                 a file could not be read or written in the named format
    ├── BadMessageError             a wire message failed to decode or validate (service)
    └── NotFoundError               a session, map or tile that does not exist

One place maps these to HTTP status codes (``service``) and one place to CLI exit codes
(``cli.errors``); library code only raises them.
"""

from __future__ import annotations

from typing import Any


class RandtError(Exception):
    """Root of every error raised on purpose by randt-fleet."""


class InvalidCloudError(RandtError, ValueError):
    """A point cloud is unusable: empty, too few points, wrong shape or dtype."""


class DegenerateProblemError(RandtError):
    """The registration problem does not constrain every degree of freedom.

    Attributes
    ----------
    result:
        The :class:`core.registration.RegistrationResult` reached anyway, so a caller can
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


class FormatError(RandtError, ValueError):
    """A file could not be read or written: unknown extension, malformed header, bad data."""


class BadMessageError(RandtError, ValueError):
    """A wire message failed to decode or validate. ``code`` is a stable machine-readable reason."""

    def __init__(self, message: str, *, code: str = "bad_message"):
        super().__init__(message)
        self.code = code


class NotFoundError(RandtError, LookupError):
    """A named session, map, tile or file does not exist."""

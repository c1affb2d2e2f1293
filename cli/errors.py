"""THE exit codes of ``randt`` and the one-line ``randt: error: ...`` printing.

Every command is wrapped by :func:`exits_on_error`: an error of the project's tree, an ``OSError`` or
a ``ValueError`` (a pydantic ``ValidationError`` too) becomes one line on stderr and the exit code of
:data:`EXIT_CODES` (first match wins); Ctrl-C becomes one line and :attr:`ExitCode.INTERRUPTED`.
Anything else is a bug and keeps its traceback (exit code 1).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from enum import IntEnum
from typing import ParamSpec, TypeVar

import typer

from core.errors import (
    DegenerateProblemError,
    FormatError,
    InvalidCloudError,
    NotFoundError,
    RandtError,
    RegistrationFailedError,
)

__all__ = ["EXIT_CODES", "ExitCode", "exits_on_error", "fail"]


class ExitCode(IntEnum):
    """Exit codes of every ``randt`` command (README "Exit codes", ``randt --help``)."""

    OK = 0
    CRASH = 1  #: an unexpected error (a bug: the traceback is printed)
    NOT_FOUND = 2  #: a file or folder, session, map or tile that does not exist; a usage error
    FORMAT = 3  #: a file that cannot be read or written in its format
    INVALID_CLOUD = 4  #: empty, too few points, wrong shape
    DEGENERATE = 5  #: the geometry does not constrain all 6 DoF (e.g. a single plane)
    REGISTRATION_FAILED = 6  #: no overlap, the optimiser diverged
    OTHER_ERROR = 7  #: any other error of the project
    INVALID_VALUE = 8  #: an invalid option or setting value
    NOT_CONVERGED = 9  #: registration finished without converging (the result is still printed)
    NO_SERVICE = 10  #: no service answered (connection refused, timed out)
    INCOMPLETE = 11  #: replay/simulate: some scan got no pose (the summary says which)
    INTERRUPTED = 130  #: Ctrl-C


#: Exit codes by error class (first match wins); 0 is success, 1 is an unexpected crash.
EXIT_CODES: tuple[tuple[type[BaseException], ExitCode], ...] = (
    (ConnectionError, ExitCode.NO_SERVICE),
    (FileNotFoundError, ExitCode.NOT_FOUND),
    (NotFoundError, ExitCode.NOT_FOUND),
    (FormatError, ExitCode.FORMAT),
    (InvalidCloudError, ExitCode.INVALID_CLOUD),
    (DegenerateProblemError, ExitCode.DEGENERATE),
    (RegistrationFailedError, ExitCode.REGISTRATION_FAILED),
    (RandtError, ExitCode.OTHER_ERROR),
    (ValueError, ExitCode.INVALID_VALUE),
)

#: What :func:`exits_on_error` turns into a one-line error (anything else is a bug: traceback).
HANDLED: tuple[type[BaseException], ...] = (RandtError, OSError, ValueError)


def exit_code(exc: BaseException) -> int:
    """The exit code of an error (:data:`EXIT_CODES`, first match; 1 if none)."""
    return next((int(c) for cls, c in EXIT_CODES if isinstance(exc, cls)), int(ExitCode.CRASH))


def message(exc: BaseException) -> str:
    """One line saying what went wrong (a validation error: its first field and reason)."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError) and exc.errors():
        first = exc.errors()[0]
        loc = ".".join(map(str, first["loc"]))
        return f"{loc}: {first['msg']}" if loc else str(first["msg"])
    text = str(exc)
    return text.splitlines()[0] if text else type(exc).__name__


def fail(exc: BaseException) -> typer.Exit:
    """Print ``randt: error: <one line>`` on stderr; the ``typer.Exit`` to raise (its exit code)."""
    typer.echo(f"randt: error: {message(exc)}", err=True)
    return typer.Exit(exit_code(exc))


P = ParamSpec("P")
R = TypeVar("R")


def exits_on_error(command: Callable[P, R], name: str) -> Callable[P, R]:
    """Wrap the command ``randt <name>``: handled errors and Ctrl-C end it with one line and a code."""

    @functools.wraps(command)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return command(*args, **kwargs)
        except HANDLED as exc:
            raise fail(exc) from exc
        except KeyboardInterrupt:
            typer.echo(f"randt {name}: interrupted", err=True)
            raise typer.Exit(ExitCode.INTERRUPTED) from None

    return wrapper

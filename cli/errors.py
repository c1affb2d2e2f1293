"""THE exit codes of ``randt`` and the one-line ``randt: error: ...`` printing.

Every command is wrapped by :func:`exits_on_error`: an error of the project's tree, an ``OSError`` or
a ``ValueError`` (a pydantic ``ValidationError`` too) becomes one line on stderr and the exit code of
:data:`EXIT_CODES` (first match wins); Ctrl-C becomes one line and :attr:`ExitCode.INTERRUPTED`.
Anything else is a bug and keeps its traceback (exit code 1).
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable
from enum import IntEnum
from pathlib import Path
from typing import ParamSpec, TypeVar

import typer

from randt.cli import interrupt
from randt.core.errors import (
    DegenerateProblemError,
    FormatError,
    InvalidCloudError,
    InvalidRequestError,
    NotFoundError,
    RandtError,
    RegistrationFailedError,
)

__all__ = [
    "DESCRIPTIONS",
    "EXIT_CODES",
    "ExitCode",
    "PortInUseError",
    "WrongInputError",
    "exit_code_table",
    "exits_on_error",
    "fail",
    "input_file",
]


QUIET_INTERRUPT_ENV = interrupt.QUIET_ENV


class ExitCode(IntEnum):
    """Exit codes of every ``randt`` command; :data:`DESCRIPTIONS` says what each means."""

    OK = 0
    CRASH = 1
    NOT_FOUND = 2
    FORMAT = 3
    INVALID_CLOUD = 4
    DEGENERATE = 5
    REGISTRATION_FAILED = 6
    OTHER_ERROR = 7
    INVALID_VALUE = 8
    NOT_CONVERGED = 9
    NO_SERVICE = 10
    INCOMPLETE = 11
    PORT_IN_USE = 12
    DATA_DIR_IN_USE = 13
    WRONG_INPUT = 14
    NOT_CONFIDENT = 15
    INTERRUPTED = 130
    BROKEN_PIPE = 141


#: The exit-code table, as ``randt --help`` and the README print it.
DESCRIPTIONS: dict[ExitCode, str] = {
    ExitCode.OK: "success",
    ExitCode.CRASH: "unexpected error (a bug: the traceback is printed)",
    ExitCode.NOT_FOUND: "file, folder, session, map or tile not found; or a usage error",
    ExitCode.FORMAT: "unreadable file",
    ExitCode.INVALID_CLOUD: "invalid point cloud (empty, too few points)",
    ExitCode.DEGENERATE: "degenerate geometry (e.g. a single plane)",
    ExitCode.REGISTRATION_FAILED: "registration failed (no overlap, diverged)",
    ExitCode.OTHER_ERROR: "another error of randt",
    ExitCode.INVALID_VALUE: "invalid option or setting value",
    ExitCode.NOT_CONVERGED: "registration finished without converging (result still printed)",
    ExitCode.NO_SERVICE: "no service answered",
    ExitCode.INCOMPLETE: "replay/simulate: some scan got no pose (the summary says which)",
    ExitCode.PORT_IN_USE: "serve: the HTTP port or a Zenoh listen port is in use (nothing started)",
    ExitCode.DATA_DIR_IN_USE: "serve/demo: the data directory is in use by another process",
    ExitCode.WRONG_INPUT: "a directory where a file is expected, or a folder holding no scan files",
    ExitCode.NOT_CONFIDENT: "register --global: the pose found is not to be trusted (printed, with why)",
    ExitCode.INTERRUPTED: "interrupted (Ctrl-C)",
    ExitCode.BROKEN_PIPE: "the reader of the output went away (output piped into `head`): no message",
}


def exit_code_table() -> str:
    """The table of :data:`DESCRIPTIONS`, one code a line (``randt --help``'s epilog)."""
    return "\n".join(f"{int(code):>5}  {text}" for code, text in DESCRIPTIONS.items())


class PortInUseError(RandtError):
    """A port the command would listen on is taken (checked before anything starts)."""


class WrongInputError(RandtError):
    """A path of the wrong kind: a directory where a file is expected (and the reverse)."""


#: Exit codes by error class (first match wins); 0 is success, 1 is an unexpected crash.
#: Classes of ``service`` and ``randt.core.datasets`` are named by their import path, so ``--help`` does
#: not import them; :func:`exit_code` resolves them when an error is being mapped.
EXIT_CODES: tuple[tuple[type[BaseException] | str, ExitCode], ...] = (
    (PortInUseError, ExitCode.PORT_IN_USE),
    ("randt.service.data_dir_lock:DataDirInUseError", ExitCode.DATA_DIR_IN_USE),
    (WrongInputError, ExitCode.WRONG_INPUT),
    (IsADirectoryError, ExitCode.WRONG_INPUT),
    (NotADirectoryError, ExitCode.WRONG_INPUT),
    ("randt.core.datasets:NoScansError", ExitCode.WRONG_INPUT),
    (ConnectionError, ExitCode.NO_SERVICE),
    (FileNotFoundError, ExitCode.NOT_FOUND),
    (NotFoundError, ExitCode.NOT_FOUND),
    (FormatError, ExitCode.FORMAT),
    (InvalidCloudError, ExitCode.INVALID_CLOUD),
    (DegenerateProblemError, ExitCode.DEGENERATE),
    (RegistrationFailedError, ExitCode.REGISTRATION_FAILED),
    (InvalidRequestError, ExitCode.INVALID_VALUE),
    (RandtError, ExitCode.OTHER_ERROR),
    (ValueError, ExitCode.INVALID_VALUE),
)

#: What :func:`exits_on_error` turns into a one-line error (anything else is a bug: traceback).
HANDLED: tuple[type[BaseException], ...] = (RandtError, OSError, ValueError)


def _resolve(cls: type[BaseException] | str) -> type[BaseException] | None:
    """The class of an :data:`EXIT_CODES` row; a ``module:Name`` one only if that module is loaded."""
    if not isinstance(cls, str):
        return cls
    module, _, name = cls.partition(":")
    loaded = sys.modules.get(module)  # an error of a module never imported cannot have been raised
    return getattr(loaded, name) if loaded is not None else None


def exit_code(exc: BaseException) -> int:
    """The exit code of an error (:data:`EXIT_CODES`, first match; 1 if none)."""
    for cls, code in EXIT_CODES:
        resolved = _resolve(cls)
        if resolved is not None and isinstance(exc, resolved):
            return int(code)
    return int(ExitCode.CRASH)


def message(exc: BaseException) -> str:
    """One line saying what went wrong (a validation error: its first field and reason)."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError) and exc.errors():
        first = exc.errors()[0]
        loc = ".".join(map(str, first["loc"]))
        return f"{loc}: {first['msg']}" if loc else str(first["msg"])
    if isinstance(exc, OSError) and exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"  # not "[Errno 21] Is a directory: 'x'"
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
            interrupt.check()  # (a Ctrl-C while the command loaded, swallowed where it was raised)
            return command(*args, **kwargs)
        except BrokenPipeError:
            # The reader left (``randt config | head``): stop quietly, as cat and grep do. Point
            # stdout at /dev/null so the interpreter's final flush does not raise again.
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            raise typer.Exit(ExitCode.BROKEN_PIPE) from None
        except HANDLED as exc:
            raise fail(exc) from exc
        except (KeyboardInterrupt, Exception) as exc:
            if not interrupt.explains(exc):  # (a Ctrl-C wrapped in another error is one too)
                raise
            interrupt.say(f"randt {name}: interrupted")
            raise typer.Exit(ExitCode.INTERRUPTED) from None

    return wrapper


def input_file(path: Path) -> Path:
    """``path`` itself, or :class:`WrongInputError` if it is a directory (a missing file is the reader's)."""
    if path.is_dir():
        raise WrongInputError(f"{path} is a directory, expected a file")
    return path

"""A Ctrl-C that is never lost.

Python's own SIGINT handler raises ``KeyboardInterrupt`` wherever the main thread happens to be,
and where that is a weakref callback or a ``__del__`` (the import system runs one at every module
lock it drops), the interpreter prints ``Exception ignored in ...`` with a traceback and carries
on: the Ctrl-C is gone, and the command goes on as if nobody had asked it to stop
(docs/reliability.md, ``bench/ctrl_c.py``).

:func:`install` replaces that handler with one that first *notes* the signal, then raises as
Python's does; the commands' long waits (:func:`sleep`, :func:`check`) raise it again from the
note, so a swallowed one still stops the command at its next wait (and its traceback is not
printed: ``sys.unraisablehook``). Only this module's handler writes the note; nothing clears it
(an interrupted command ends).

:func:`say` prints the one line an interrupted command ends with, once: the command's own
(``randt.cli.errors.exits_on_error``), or ``randt: interrupted`` where the interrupt came outside it
(the imports; Typer's argument handling, which turns a ``KeyboardInterrupt`` into exit code 130
without a word).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from types import FrameType
from typing import Any

#: Set to "1" in the environment of a ``randt`` command another one runs (``randt demo``'s fleet):
#: a Ctrl-C, which reaches both, is then reported by the parent alone, in one line.
QUIET_ENV = "RANDT_QUIET_INTERRUPT"

_noted = threading.Event()
_said = threading.Event()


def _handler(signum: int, frame: FrameType | None) -> None:
    _noted.set()
    raise KeyboardInterrupt


def _unraisable(unraisable: Any) -> None:
    """``sys.unraisablehook``: a noted interrupt that a callback swallowed is not printed (its
    ``Exception ignored in ...`` traceback); everything else as before."""
    if issubclass(unraisable.exc_type, KeyboardInterrupt) and _noted.is_set():
        return
    _previous_unraisable(unraisable)


_previous_unraisable = sys.unraisablehook


def install(*signals: signal.Signals) -> None:
    """Handle SIGINT (and ``signals``, e.g. SIGTERM) by noting it and raising ``KeyboardInterrupt``,
    and keep a swallowed one off the terminal. From the main thread only, as ``signal.signal``."""
    for sig in (signal.SIGINT, *signals):
        signal.signal(sig, _handler)
    sys.unraisablehook = _unraisable


def check() -> None:
    """Raise ``KeyboardInterrupt`` if one was signalled (even if a callback swallowed it)."""
    if _noted.is_set():
        raise KeyboardInterrupt


def explains(exc: BaseException) -> bool:
    """Whether ``exc`` is (or came of) a signalled interrupt: a ``KeyboardInterrupt``, or any error
    raised after one was noted. Code the interrupt lands in may wrap it in its own error (pydantic
    building a model's schema during an import raised ``SchemaError``): the command was stopped
    by the user all the same, and ends as interrupted, not with that error's traceback."""
    return isinstance(exc, KeyboardInterrupt) or _noted.is_set()


def sleep(seconds: float) -> None:
    """``time.sleep`` that ends in ``KeyboardInterrupt`` once one was signalled."""
    check()
    time.sleep(seconds)
    check()


def say(line: str) -> None:
    """Print ``line`` on stderr as the interrupted command's last word, unless one was printed
    already or a parent command reports it (:data:`QUIET_ENV`)."""
    if not _said.is_set() and os.environ.get(QUIET_ENV) != "1":
        sys.stderr.write(line + "\n")
        sys.stderr.flush()
    _said.set()

"""A Ctrl-C that is never lost.

Python's own SIGINT handler raises ``KeyboardInterrupt`` wherever the main thread happens to be,
and where that is a weakref callback or a ``__del__`` (the import system runs one at every module
lock it drops), the interpreter prints ``Exception ignored in ...`` and carries on: the Ctrl-C is
gone. ``randt demo`` interrupted in its first second (its imports) once went on to serve until it
was killed 90 s later (bench/ctrl_c.py; docs/reliability.md).

:func:`install` replaces that handler with one that first *notes* the signal, then raises as
Python's does; the commands' long waits (:func:`sleep`, :func:`check`) raise it again from the
note, so a swallowed one still stops the command at its next wait. Only this module's handler
writes the note; nothing clears it (an interrupted command ends).
"""

from __future__ import annotations

import signal
import threading
import time
from types import FrameType

_noted = threading.Event()


def _handler(signum: int, frame: FrameType | None) -> None:
    _noted.set()
    raise KeyboardInterrupt


def install(*signals: signal.Signals) -> None:
    """Handle SIGINT (and ``signals``, e.g. SIGTERM) by noting it and raising ``KeyboardInterrupt``.
    From the main thread only, as ``signal.signal``."""
    for sig in (signal.SIGINT, *signals):
        signal.signal(sig, _handler)


def check() -> None:
    """Raise ``KeyboardInterrupt`` if one was signalled (even if a callback swallowed it)."""
    if _noted.is_set():
        raise KeyboardInterrupt


def sleep(seconds: float) -> None:
    """``time.sleep`` that ends in ``KeyboardInterrupt`` once one was signalled."""
    check()
    time.sleep(seconds)
    check()

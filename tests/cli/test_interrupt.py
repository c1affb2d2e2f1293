"""A Ctrl-C that lands in a weakref callback (where the import system's module locks are dropped)
is swallowed by the interpreter ("Exception ignored in ..."): ``randt.cli.interrupt`` notes it first, so
the command's next wait still raises it (a ``randt demo`` interrupted during its imports served on
until killed, bench/ctrl_c.py)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import os, signal, sys, time, weakref
    from randt.cli import interrupt

    # (Python's handler even when started with SIGINT ignored, as a background job of a script is)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    if sys.argv[1] == "installed":
        interrupt.install()

    class Thing:
        pass

    def callback(_ref):
        os.kill(os.getpid(), signal.SIGINT)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:  # the handler runs here, inside the callback
            pass

    thing = Thing()
    ref = weakref.ref(thing, callback)
    del thing  # the callback runs; its KeyboardInterrupt is printed and ignored
    print("went on", flush=True)
    try:
        interrupt.sleep(0.01)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        sys.exit(130)
    print("lost", flush=True)
    """
)


@pytest.mark.parametrize("mode", ["installed", "python's own"])
def test_a_ctrl_c_swallowed_in_a_callback_still_stops_the_next_wait(mode: str) -> None:
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT, "installed" if mode == "installed" else "default"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    lines, seen = run.stdout.split(), f"exit {run.returncode}, stdout {run.stdout!r}, stderr {run.stderr!r}"
    if mode == "installed":
        assert lines == ["went", "on", "interrupted"] and run.returncode == 130, seen
        # the noted interrupt's 'Exception ignored' traceback is not printed
        assert "Exception ignored" not in run.stderr and "Traceback" not in run.stderr, seen
    else:  # the failure mode itself: without the note, the Ctrl-C is gone (with a traceback)
        assert lines == ["went", "on", "lost"] and run.returncode == 0, seen
        assert "Exception ignored in" in run.stderr and "KeyboardInterrupt" in run.stderr, seen


def test_other_unraisable_exceptions_are_still_printed() -> None:
    script = textwrap.dedent(
        """
        import weakref
        from randt.cli import interrupt

        interrupt.install()

        class Thing:
            pass

        def callback(_ref):
            raise ValueError("in a callback")

        thing = Thing()
        ref = weakref.ref(thing, callback)
        del thing
        """
    )
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert "Exception ignored in" in run.stderr and "ValueError: in a callback" in run.stderr, run.stderr


WRAPPED = textwrap.dedent(
    """
    import os, signal, sys, time
    from randt.cli import interrupt

    interrupt.install()
    try:
        try:  # a library that catches the KeyboardInterrupt and raises its own error instead
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            raise RuntimeError("schema building failed") from None
    except Exception as exc:
        print("interrupt" if interrupt.explains(exc) else "error", flush=True)
    print("noted" if interrupt.explains(ValueError()) else "clean", flush=True)
    """
)


def test_an_error_raised_in_place_of_a_ctrl_c_is_the_ctrl_c() -> None:
    # pydantic wrapped a Ctrl-C that landed while it built a model's schema into a SchemaError:
    # ``randt demo`` ended with exit code 1 and a traceback instead of 130 (tests/cli/test_ctrl_c.py)
    run = subprocess.run([sys.executable, "-c", WRAPPED], capture_output=True, text=True, timeout=60)
    assert run.stdout.split() == ["interrupt", "noted"], (run.stdout, run.stderr)
    clean = subprocess.run(
        [sys.executable, "-c", "from randt.cli import interrupt; print(interrupt.explains(ValueError()))"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert clean.stdout.strip() == "False", clean.stderr

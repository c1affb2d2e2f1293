"""``python -m cli``: the ``randt`` command.

A Ctrl-C while the command loads, or in the command-line framework around a command (each command
reports its own: ``cli.errors.exits_on_error``), ends it with one line and exit code 130 too; one
the import system swallowed is noted (:mod:`cli.interrupt`) and ends the command before it starts.
"""

import os
import sys

from cli import interrupt

interrupt.install()  # before the imports below: a Ctrl-C swallowed in them is still noted


def _interrupted() -> None:
    if os.environ.get("RANDT_QUIET_INTERRUPT") != "1":  # (cli.errors.QUIET_INTERRUPT_ENV)
        sys.stderr.write("randt: interrupted\n")
    raise SystemExit(130)


try:
    from cli.main import main

    main()
except KeyboardInterrupt:
    _interrupted()

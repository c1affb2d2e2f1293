"""``python -m randt.cli``: the ``randt`` command.

A Ctrl-C while the command loads, or in the command-line framework around a command (each command
reports its own: ``randt.cli.errors.exits_on_error``), ends it with one line and exit code 130 too; one
the import system swallowed is noted (:mod:`randt.cli.interrupt`) and ends the command before it starts.
"""

try:
    from randt.cli import interrupt

    interrupt.install()  # before the imports below: a Ctrl-C swallowed in them is still noted
    from randt.cli.main import main

    main()
except (KeyboardInterrupt, Exception) as exc:
    from randt.cli import interrupt

    if not interrupt.explains(exc):  # (a Ctrl-C wrapped in another error ends as one too)
        raise
    interrupt.say("randt: interrupted")
    raise SystemExit(130) from None

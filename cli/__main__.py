"""``python -m cli``: the ``randt`` command."""

from cli.main import main

main()

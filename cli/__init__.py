"""The ``randt`` command: a thin shell over ``core``, ``service`` and ``clients``, above all of them.

One module per command group (:mod:`randt.cli.main` assembles them); :mod:`randt.cli.errors` is the one place
mapping errors to exit codes. Commands import what they need lazily so ``randt --help`` stays fast.
"""

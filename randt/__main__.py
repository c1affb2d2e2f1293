"""``python -m randt``: the ``randt`` command (as ``python -m randt.cli``)."""

import runpy

runpy.run_module("randt.cli", run_name="__main__", alter_sys=True)

"""Ctrl-C on ``randt demo`` 20 times in a row, at random moments, with both cores busy (issue 33).

``bench/ctrl_c.py`` does the work (two CPU burners beside each run, SIGINT to the demo's whole
process group at a random moment from the interpreter's start to serving): every run must end
with exit code 130, at most one line on stderr and no traceback, no process of its group left
and nothing left in its temporary folder. About a minute.
"""

from __future__ import annotations

import pytest

from bench import ctrl_c


@pytest.mark.slow
def test_ctrl_c_on_the_demo_twenty_times_at_random_moments_with_both_cores_busy(capsys) -> None:
    failed = ctrl_c.main(["--runs", "20", "--seed", "33", "--latest", "4.5"])
    out = capsys.readouterr().out
    assert failed == 0, out
    assert "20 of 20 runs clean" in out

"""Shared pytest fixtures.

Tests that need the real data set go through :func:`require_data` (also importable from
``tests.data``) or the ``data_dir`` fixture built on it: absent data skip with a clear reason,
except in CI (``CI=true``) where they fail.
"""

from __future__ import annotations

import os
import resource
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import pytest

from randt.core.shared_data import DATA_DIR_ENV_VAR, data_root
from tests.data import require_data

__all__ = ["DATA_DIR_ENV_VAR", "data_dir", "data_root", "require_data"]

# Admission by measured capacity (service/capacity.py) admits what this machine's measured CPU
# allows, so a test of anything else that opens several sessions at once would pass or fail by the
# machine's speed: tests run without it (as with a count limit) unless they ask for it, as
# tests/service/test_admission.py does; bench/service.py measures it on the real service. Services
# the tests start as child processes inherit it.
os.environ.setdefault("RANDT_CAPACITY_TARGET", "0")


#: Test files that take a minute or more (``--durations`` and the CPU summary below): they start
#: first, so that pytest-xdist's workers end on many short files rather than one waiting for the
#: other's last long one (addopts: ``--no-loadscope-reorder`` keeps this order; without it xdist
#: starts the files with the most tests first).
LONG_FIRST = (
    "tests/sim/test_scenarios.py",
    "tests/service/test_graph.py",
    "tests/service/test_bad_messages.py",
    "tests/cli/test_demo.py",
    "tests/test_corpus.py",
    "tests/service/test_agreement.py",
    "tests/service/test_graph_durable.py",
    "tests/service/test_kill9.py",
    "tests/deploy/test_compose_smoke.py",
    "tests/core/test_odometry.py",
    "tests/cli/test_ctrl_c.py",
    "tests/service/test_ray_executor.py",
    "tests/service/test_faults.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The files of :data:`LONG_FIRST` first, in its order; every file's tests in their order."""
    rank = {path: i for i, path in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared real-data directory (``$RANDT_SHARED_DATA`` or ``<repo>/../shared/data``)."""
    return require_data()


# -- CPU per test file (CI time is budgeted on 2 shared cores: CPU, not wall time, is what adds up
# when the tests run on every core) ---------------------------------------------------------------
_last_cpu_s: float | None = None


def _cpu_s() -> float:
    """This process's CPU time and its waited-for children's (servers, matcher processes)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def pytest_runtest_logstart(nodeid: str, location: tuple[str, int | None, str]) -> None:
    """Counting starts at this process's first test (a module fixture built in its setup counts)."""
    global _last_cpu_s
    if _last_cpu_s is None:
        _last_cpu_s = _cpu_s()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """Each phase's report carries the CPU spent since the previous report of this process
    (``cpu_s``: pytest-xdist sends it to the controller with the report)."""
    global _last_cpu_s
    outcome = yield
    now = _cpu_s()
    report = outcome.get_result()
    report.cpu_s = now - (_last_cpu_s if _last_cpu_s is not None else now)
    _last_cpu_s = now


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """The test files that cost the most CPU, after the slowest durations."""
    by_file: dict[str, float] = defaultdict(float)
    seen: set[int] = set()
    for reports in terminalreporter.stats.values():
        for r in reports:
            cpu = getattr(r, "cpu_s", None)
            if cpu is None or id(r) in seen:
                continue
            seen.add(id(r))
            by_file[r.nodeid.split("::")[0]] += cpu
    if not by_file:
        return
    terminalreporter.write_sep("=", f"CPU by test file: {sum(by_file.values()):.0f} s in all, the top 25")
    for path, cpu in sorted(by_file.items(), key=lambda kv: -kv[1])[:25]:
        terminalreporter.write_line(f"{cpu:8.1f}s  {path}")

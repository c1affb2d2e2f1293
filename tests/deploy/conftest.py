"""In one process (-n0) the deployment tests run last, and their images are built in the background
from the moment they are collected: the build (a Debian base from packages, the router stand-in,
the project's image, about three minutes that mostly wait on disk and the package index) overlaps
the rest of the suite instead of adding to it (``test_compose_smoke.Images``). With pytest-xdist
(the suite's default) every worker collects every test but only one runs this directory's file:
the images are built when its fixture asks (``Images.wait`` starts the build), while the other
worker runs other tests; two workers starting the build at collection started two Docker
daemons, and the second could not open the first's volume store."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

HERE = Path(__file__).parent


@pytest.hookimpl(trylast=True)  # after -k/-m deselection: only when deployment tests will run
def pytest_collection_modifyitems(
    session: pytest.Session, config: pytest.Config, items: list[pytest.Item]
) -> None:
    deploy = [item for item in items if HERE in Path(item.path).parents]
    if not deploy or config.option.collectonly or hasattr(config, "workerinput"):
        return  # (an xdist worker: the module docstring)
    items[:] = [item for item in items if item not in deploy] + deploy
    from tests.deploy.test_compose_smoke import IMAGES

    IMAGES.start()


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    from tests.deploy.test_compose_smoke import IMAGES

    IMAGES.close(timeout_s=10.0 if exitstatus == pytest.ExitCode.INTERRUPTED else 900.0)


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    """The deployment test's stage timings in every run's log (CI's too), not only on failure."""
    from tests.deploy.test_compose_smoke import IMAGES

    if IMAGES.timings:
        timings = {k: round(v, 1) for k, v in IMAGES.timings.items()}
        terminalreporter.write_line(f"deployment smoke test timings (s): {json.dumps(timings)}")

"""The benchmarks run without pytest and without ``tests/`` (they import neither).

Each ``bench/*.py`` is run to its ``--help`` in a fresh interpreter whose import system refuses
``pytest``, ``_pytest`` and ``tests`` (a ``sys.meta_path`` finder that raises on them), as on a
machine with only the ``bench`` extra installed. The peers a benchmark compares with (small_gicp,
KISS-ICP: the ``bench`` extra, not the ``test`` one) are stood in for by empty modules when they
are not installed, so the test checks our imports, not theirs.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

_RUNNER = r"""
import importlib.abc
import importlib.util
import runpy
import sys
import types
from pathlib import Path

BLOCKED = ("pytest", "_pytest", "tests")


class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"import of {name} blocked: a benchmark must run without it")
        return None


sys.meta_path.insert(0, Block())


class Absent(types.ModuleType):
    def __getattr__(self, attr):
        return Absent(f"{self.__name__}.{attr}")


absent = {top for top in ("small_gicp", "kiss_icp", "open3d") if importlib.util.find_spec(top) is None}
for name in ("small_gicp", "kiss_icp", "kiss_icp.config", "kiss_icp.kiss_icp", "open3d"):
    if name.split(".")[0] in absent:
        sys.modules[name] = Absent(name)

script = Path(sys.argv[1])
sys.path.insert(0, str(script.parent))
sys.argv = [str(script), "--help"]
runpy.run_path(str(script), run_name="__main__")
"""


def _run(script: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", _RUNNER, str(script)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )


_SCRIPTS = [
    "register",
    "odometry",
    "service",
    "workers",
    "corpus",
    "hostile",
    "faults",
    "soak",
    "reliability",
    "crash",
    "link",
    "fleet_map",
    "global_registration",
    "main_process",
]


@pytest.mark.parametrize("name", _SCRIPTS)
def test_benchmark_runs_without_pytest_or_tests(name: str) -> None:
    done = _run(REPO / "bench" / f"{name}.py")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"usage: {name}.py"), done.stdout


def test_the_import_block_refuses_tests_and_pytest(tmp_path: Path) -> None:
    """The control: a script importing the tests' data helper fails under the same block."""
    script = tmp_path / "uses_tests.py"
    script.write_text("import argparse\nimport tests.data\nargparse.ArgumentParser().parse_args()\n")
    done = _run(script)
    assert done.returncode != 0
    assert "import of tests blocked" in done.stderr


@pytest.mark.parametrize("path", sorted((REPO / "bench").glob("*.py")), ids=lambda p: p.name)
def test_no_benchmark_imports_tests_or_pytest_even_inside_a_function(path: Path) -> None:
    """``--help`` runs only the top-level imports; a lazy import in a function shows here."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    imported = [
        alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names
    ] + [node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)]
    offending = [m for m in imported if m.split(".")[0] in ("tests", "pytest", "_pytest")]
    assert offending == [], f"{path.name} imports {offending}"

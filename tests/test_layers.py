"""The layers never reach sideways: every import of every module, read with ``ast``.

``core`` imports nothing else of ours; ``wire`` and ``sim`` (the LiDAR simulator) only ``core``;
``service`` never ``clients``, ``sim`` or ``cli``; ``clients`` never ``service`` or ``cli`` (its
fleet runner uses ``sim``; the vehicle library, ``clients.publisher``, does not: tested below);
``cli`` sits above all of them. Imports inside functions
and under ``TYPE_CHECKING`` count too: a lazy import is still a dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: package -> the project's packages it must never import
FORBIDDEN: dict[str, frozenset[str]] = {
    "core": frozenset({"service", "clients", "cli", "wire", "sim"}),
    "wire": frozenset({"service", "clients", "cli", "sim"}),
    "sim": frozenset({"service", "clients", "cli", "wire"}),
    "service": frozenset({"clients", "cli", "sim"}),
    "clients": frozenset({"service", "cli"}),
}


def imported_packages(path: Path, root: Path = REPO) -> set[tuple[str, int]]:
    """Top-level names of every module ``path`` imports, with their line (relative ones resolved).

    ``ast.walk`` visits every node, so imports inside functions and ``if TYPE_CHECKING:`` count.
    A relative import resolves to the module's own top-level package (``root`` is the repository).
    """
    tree = ast.parse(path.read_text(), filename=str(path))
    top = path.relative_to(root).parts[0]
    found: set[tuple[str, int]] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {(alias.name.split(".")[0], node.lineno) for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            name = top if node.level else (node.module or "").split(".")[0]
            found.add((name, node.lineno))
    return found


def _modules(package: str) -> list[Path]:
    return sorted(p for p in (REPO / package).rglob("*.py") if "__pycache__" not in p.parts)


def test_the_walker_sees_lazy_type_checking_and_relative_imports(tmp_path: Path) -> None:
    sample = tmp_path / "core" / "sub" / "probe.py"
    sample.parent.mkdir(parents=True)
    sample.write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from service.store import Store\n"
        "def f():\n    import clients.rest, numpy as np\n"
        "class C:\n    def g(self):\n        from cli.errors import fail\n"
        "from .. import io\n"
    )
    assert imported_packages(sample, tmp_path) == {
        ("typing", 1), ("service", 3), ("clients", 5), ("numpy", 5), ("cli", 8), ("core", 9)
    }  # fmt: skip


@pytest.mark.parametrize("package", sorted(p for p in FORBIDDEN if (REPO / p).is_dir()))
def test_no_package_imports_a_layer_it_must_not(package: str) -> None:
    bad = [
        f"{path.relative_to(REPO)}:{line} imports {name}"
        for path in _modules(package)
        for name, line in sorted(imported_packages(path))
        if name in FORBIDDEN[package]
    ]
    assert not bad, "\n".join(bad)


def test_the_packages_exist() -> None:
    """The walk above covers real code: the packages are where the test looks."""
    for package in ("core", "wire", "sim", "service", "clients", "cli"):
        assert _modules(package), package


def test_the_vehicle_library_does_not_load_the_simulator() -> None:
    """A vehicle computer imports ``clients.publisher``: neither it nor what it imports of ours
    pulls in the simulator (or the service)."""
    import subprocess
    import sys

    code = (
        "import sys, clients.publisher; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'sim', 'service', 'cli', 'tests'}))"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"

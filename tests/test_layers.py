"""The layers never reach sideways or up: every import of every module, read with ``ast``.

Between packages: ``core`` imports nothing else of ours; ``wire`` and ``sim`` (the LiDAR simulator)
only ``core``; ``service`` never ``clients``, ``sim`` or ``cli``; ``clients`` never ``service`` or
``cli`` (its fleet runner uses ``sim``; the vehicle library, ``randt.clients.publisher``, does not:
tested below); ``cli`` sits above all of them. Between modules: the imports form no cycle, so the
modules stand in layers, and no module imports the package it is part of (a package's
``__init__`` gathers its modules; a module that reached up into it would depend on its siblings
through it). Imports inside functions and under ``TYPE_CHECKING`` count too: a lazy import is still
a dependency.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("core", "wire", "sim", "service", "clients", "cli")
#: package -> the project's packages it must never import
FORBIDDEN: dict[str, frozenset[str]] = {
    "core": frozenset({"service", "clients", "cli", "wire", "sim"}),
    "wire": frozenset({"service", "clients", "cli", "sim"}),
    "sim": frozenset({"service", "clients", "cli", "wire"}),
    "service": frozenset({"clients", "cli", "sim"}),
    "clients": frozenset({"service", "cli"}),
}


def module_name(path: Path, root: Path = REPO) -> str:
    """``core/io/bags.py`` -> ``randt.core.io.bags``; a package's ``__init__.py`` is the package."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(["randt", *parts])


def imports(path: Path, root: Path = REPO) -> set[tuple[str, int]]:
    """Every module ``path`` imports (``from m import n`` as ``m.n``), with its line, relative
    imports resolved; ``ast.walk`` visits every node, so lazy and ``TYPE_CHECKING`` imports count."""
    tree = ast.parse(path.read_text(), filename=str(path))
    own = module_name(path, root)
    package = own if path.name == "__init__.py" else own.rpartition(".")[0]
    found: set[tuple[str, int]] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {(alias.name, node.lineno) for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            found |= {(f"{base}.{alias.name}", node.lineno) for alias in node.names}
    return found


def package_of(module: str) -> str:
    """The top-level name of an imported module, ours without the ``randt.`` prefix."""
    parts = module.split(".")
    return parts[1] if parts[0] == "randt" and len(parts) > 1 else parts[0]


def _modules(package: str) -> list[Path]:
    return sorted(p for p in (REPO / package).rglob("*.py") if "__pycache__" not in p.parts)


def module_graph(root: Path = REPO) -> dict[str, set[str]]:
    """Our module -> the modules of ours it imports (a ``from package import name`` of a name that
    is not a module counts as an import of the package)."""
    paths = {
        module_name(p, root): p for pkg in PACKAGES if (root / pkg).is_dir() for p in _modules_in(root, pkg)
    }

    def ours(name: str) -> str | None:
        while name and name not in paths:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for module, path in paths.items():
        targets = {ours(name) for name, _ in imports(path, root) if name.startswith("randt.")}
        graph[module] = {t for t in targets if t is not None and t != module}
    return graph


def _modules_in(root: Path, package: str) -> list[Path]:
    return sorted(p for p in (root / package).rglob("*.py") if "__pycache__" not in p.parts)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _sample_tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    return tmp_path


def test_the_walker_sees_lazy_type_checking_and_relative_imports(tmp_path: Path) -> None:
    sample = tmp_path / "core" / "sub" / "probe.py"
    sample.parent.mkdir(parents=True)
    sample.write_text(
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n    from randt.service.store import Store\n"
        "def f():\n    import randt.clients.rest, numpy as np\n"
        "class C:\n    def g(self):\n        from randt.cli.errors import fail\n"
        "from .. import io\n"
    )
    assert {(package_of(name), line) for name, line in imports(sample, tmp_path)} == {
        ("typing", 1), ("service", 3), ("clients", 5), ("numpy", 5), ("cli", 8), ("core", 9)
    }  # fmt: skip
    assert ("randt.core.io", 9) in imports(sample, tmp_path)


def test_the_graph_finds_a_cycle_through_a_lazy_import_and_a_reach_up(tmp_path: Path) -> None:
    root = _sample_tree(
        tmp_path,
        {
            "service/__init__.py": "from randt.service.a import A\n",
            "service/a.py": "from randt.service.b import B\nA = 1\n",
            "service/b.py": "def f():\n    from randt.service import a\nB = 2\n",
            "service/c.py": "from randt.service import A\n",
        },
    )
    graph = module_graph(root)
    assert graph["randt.service.c"] == {"randt.service"}  # A is a name of the package, not a module
    assert graph["randt.service.b"] == {"randt.service.a"}
    assert cycles(graph) == [["randt.service.a", "randt.service.b"]]


@pytest.mark.parametrize("package", sorted(p for p in FORBIDDEN if (REPO / p).is_dir()))
def test_no_package_imports_a_layer_it_must_not(package: str) -> None:
    bad = [
        f"{path.relative_to(REPO)}:{line} imports {name}"
        for path in _modules(package)
        for name, line in sorted(imports(path))
        if package_of(name) in FORBIDDEN[package] and name.startswith("randt.")
    ]
    assert not bad, "\n".join(bad)


def test_every_import_of_ours_names_the_one_package() -> None:
    """``randt.core...``, never ``core...``: a bare name would load a second copy of the module (or,
    installed, nothing)."""
    bare = [
        f"{path.relative_to(REPO)}:{line} imports {name}"
        for package in (*PACKAGES, "tests", "bench")
        for path in _modules(package)
        for name, line in sorted(imports(path))
        if name.split(".")[0] in PACKAGES
    ]
    assert not bare, "\n".join(bare)


def test_no_import_cycle_between_modules() -> None:
    graph = module_graph()
    assert len(graph) > 90 and sum(map(len, graph.values())) > 300  # the real code is walked
    assert cycles(graph) == []


def test_no_module_imports_its_own_package() -> None:
    graph = module_graph()
    up = [f"{m} imports {t}" for m, targets in graph.items() for t in targets if m.startswith(t + ".")]
    assert not up, "\n".join(up)


def test_the_packages_exist() -> None:
    """The walk above covers real code: the packages are where the test looks."""
    for package in PACKAGES:
        assert _modules(package), package


def test_the_vehicle_library_does_not_load_the_simulator() -> None:
    """A vehicle computer imports ``randt.clients.publisher``: neither it nor what it imports of ours
    pulls in the simulator (or the service)."""
    code = (
        "import sys, randt.clients.publisher; "
        "print(sorted(set(sys.modules) & {'randt.sim', 'randt.service', 'randt.cli', 'tests'}))"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"

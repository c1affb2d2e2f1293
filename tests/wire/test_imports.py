"""The wire package's place in the layers: it imports ``core`` and itself, and only its Zenoh
helper imports Zenoh."""

from __future__ import annotations

import ast
from pathlib import Path

from randt import wire

REPO = Path(__file__).resolve().parents[2]
OURS = {"core", "wire", "service", "clients", "cli", "bench", "tests"}


def _root(module: str) -> str:
    """``randt.core.io`` -> ``core``; any other module -> its top-level name."""
    parts = module.split(".")
    return parts[1] if parts[0] == "randt" and len(parts) > 1 else parts[0]


def imported_roots(path: Path) -> set[str]:
    """Top-level names of every module ``path`` imports (lazy imports inside functions included)."""
    roots: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            roots |= {_root(alias.name) for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(_root(node.module))
    return roots


def test_wire_imports_only_core_and_itself() -> None:
    files = sorted((REPO / "wire").glob("*.py"))
    assert {f.name for f in files} >= {"__init__.py", "messages.py", "keys.py", "ids.py", "codes.py"}
    for path in files:
        ours = imported_roots(path) & OURS
        assert ours <= {"core", "wire"}, f"{path.name} imports {sorted(ours - {'core', 'wire'})}"


def test_only_the_zenoh_helper_names_zenoh() -> None:
    users = sorted(p.name for p in (REPO / "wire").glob("*.py") if "zenoh" in imported_roots(p))
    assert users == ["zenoh_config.py"]


def test_the_package_exports_what_it_documents() -> None:
    assert wire.__doc__ is not None
    for name in wire.__all__:
        assert hasattr(wire, name), name
    for module in (
        "randt.wire.messages",
        "randt.wire.keys",
        "randt.wire.ids",
        "randt.wire.codes",
        "randt.wire.zenoh_config",
    ):
        assert f":mod:`{module}`" in wire.__doc__, module

"""What ``pip install .`` and ``pip install -e .`` put into a fresh virtual environment: one top-level
package, ``randt``, and the ``randt`` command; nothing a user's own ``core`` or ``service`` could
collide with."""

from __future__ import annotations

import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("core", "wire", "sim", "service", "clients", "cli")


def _venv(path: Path) -> Path:
    venv.EnvBuilder(with_pip=True).create(path)
    return path / "bin" / "python"


def _pip(python: Path, *args: str) -> None:
    done = subprocess.run(
        [str(python), "-m", "pip", "--disable-pip-version-check", "-q", *args],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr


def _run(python: Path, code: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(python), "-c", code], cwd=cwd, capture_output=True, text=True, timeout=120)


def _site_packages(python: Path) -> Path:
    out = subprocess.run(
        [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    return Path(out.stdout.strip())


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    done = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(REPO)],
        capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    (found,) = out.glob("randt_fleet-*.whl")
    return found


def test_the_wheel_holds_one_top_level_package_with_every_module(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")} == {"randt"}
    (top_level,) = [n for n in names if n.endswith(".dist-info/top_level.txt")] or [None]
    if top_level:
        assert zipfile.ZipFile(wheel).read(top_level).decode().split() == ["randt"]
    sources = {
        f"randt/{p.relative_to(REPO).as_posix()}" for f in FOLDERS for p in (REPO / f).rglob("*.py")
    } | {"randt/__init__.py", "randt/__main__.py"}
    assert not sources - set(names), sorted(sources - set(names))[:5]
    assert "randt/service/static/index.html" in names  # the viewer is package data


def test_the_installed_wheel_adds_randt_and_nothing_else(wheel: Path, tmp_path: Path) -> None:
    python = _venv(tmp_path / "venv")
    before = {p.name for p in _site_packages(python).iterdir()}
    _pip(python, "install", "--no-deps", str(wheel))
    added = {p.name for p in _site_packages(python).iterdir()} - before
    assert {a for a in added if not a.endswith(".dist-info")} == {"randt"}, added
    assert (python.parent / "randt").is_file()
    for name in FOLDERS:
        assert _run(python, f"import {name}", tmp_path).returncode != 0, f"`import {name}` works"
    found = _run(
        python, "import importlib.util as u; print(u.find_spec('randt.core.odometry').origin)", tmp_path
    )
    assert found.returncode == 0, found.stderr
    assert Path(found.stdout.strip()) == _site_packages(python) / "randt" / "core" / "odometry.py"


def test_the_editable_install_maps_randt_onto_the_folders(tmp_path: Path) -> None:
    python = _venv(tmp_path / "venv")
    _pip(python, "install", "--no-deps", "-e", str(REPO))
    for name in FOLDERS:
        assert _run(python, f"import {name}", tmp_path).returncode != 0, f"`import {name}` works"
    code = "import importlib.util as u; print(u.find_spec('randt.service.sessions').origin)"
    found = _run(python, code, tmp_path)
    assert found.returncode == 0, found.stderr
    assert Path(found.stdout.strip()) == REPO / "service" / "sessions.py"
    assert (python.parent / "randt").is_file()

"""The README's first contact (issue 33): its two commands first, and the text before its first
section fits one screen. CI runs the second command (.ci/run); the first is the demo
(tests/cli/test_demo.py runs ``randt demo`` itself)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
#: One screen: a terminal or an editor's first view.
SCREEN_LINES, SCREEN_COLUMNS = 40, 110


def test_the_readme_starts_with_exactly_the_two_commands() -> None:
    block = re.search(r"```bash\n(.*?)```", README, flags=re.S)
    assert block is not None and README.startswith("# randt-fleet\n\n" + block[0])
    commands = block[1].strip().splitlines()
    assert commands == ["pip install -e . && randt demo", 'pip install -e ".[test]" && python -m pytest -q']
    ci = (ROOT / ".ci" / "run").read_text()
    assert "python -m pytest -q" in ci and 'pip install --quiet -e ".[test]"' in ci
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["scripts"]["randt"].startswith("randt.cli")  # `randt demo` is this package's command
    assert "test" in project["optional-dependencies"]


def test_the_text_before_the_first_section_fits_one_screen() -> None:
    intro = README.split("\n## ", 1)[0].splitlines()
    assert len(intro) <= SCREEN_LINES, f"{len(intro)} lines before the first section"
    assert max(len(line) for line in intro) <= SCREEN_COLUMNS
    # the terms it uses are defined where they first appear
    for term in ("NDT", "IQR", "PDU", "Zenoh"):
        first = next(line for line in intro if term in line)
        assert "(" in first or "[" in first, f"{term} is not defined where it first appears: {first}"

"""The README's first contact (issue 33): its two commands first, the text before its first section
on one screen, the whole of it on a few (like KISS-ICP's), every command of ``randt`` in its table,
every link resolving, and the citation of the paper and of this software. CI runs the second
command (.ci/run); the first is the demo (tests/cli/test_demo.py runs ``randt demo`` itself). The
exit-code table is checked against ``randt.cli.errors`` in tests/cli/test_first_run.py."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import typer

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
#: One screen: a terminal or an editor's first view.
SCREEN_LINES, SCREEN_COLUMNS = 40, 110
#: The whole README: a few screens, as KISS-ICP's (about 100 lines).
README_LINES = 150
DOI = "10.1371/journal.pone.0345709"
PAPER_TITLE = (
    "Density-equalized RANDT scan matching with integrated outlier removal and point density uniformity"
)


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip())  # a link's text only
    return re.sub(r"[^\w\- ]", "", text.lower()).replace(" ", "-")


def _prose(markdown: str) -> list[str]:
    """The lines outside fenced code blocks."""
    lines, fenced = [], False
    for line in markdown.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced:
            lines.append(line)
    return lines


def headings(markdown: str) -> list[str]:
    """Every heading's text, in order (``#`` marks and fenced code left out)."""
    return [m[2].strip() for line in _prose(markdown) if (m := re.match(r"(#{1,6}) (.+)$", line))]


def anchors(markdown: str) -> set[str]:
    """The anchors GitHub gives the headings of ``markdown`` (repeats get ``-1``, ``-2``, ...)."""
    seen: dict[str, int] = {}
    for text in headings(markdown):
        base = slug(text)
        seen[base] = seen.get(base, -1) + 1
    return {base if n == 0 else f"{base}-{n}" for base, count in seen.items() for n in range(count + 1)}


def links(markdown: str) -> list[str]:
    """The targets of the links and images outside code (fenced blocks and inline spans)."""
    prose = re.sub(r"`[^`\n]*`", "", "\n".join(_prose(markdown)))
    return re.findall(r"\]\(([^)\s]+)\)", prose)


def _project() -> dict[str, object]:
    project: dict[str, object] = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return project


def test_the_readme_starts_with_exactly_the_two_commands() -> None:
    block = re.search(r"```bash\n(.*?)```", README, flags=re.S)
    assert block is not None and README.startswith("# randt-fleet\n\n" + block[0])
    commands = block[1].strip().splitlines()
    assert commands == ["pip install -e . && randt demo", 'pip install -e ".[test]" && python -m pytest -q']
    ci = (ROOT / ".ci" / "run").read_text()
    assert "python -m pytest -q" in ci and 'pip install --quiet -e ".[test]"' in ci
    project = _project()
    scripts = project["scripts"]
    assert isinstance(scripts, dict) and scripts["randt"].startswith("randt.cli")  # `randt demo` is ours
    extras = project["optional-dependencies"]
    assert isinstance(extras, dict) and "test" in extras


def test_the_text_before_the_first_section_fits_one_screen() -> None:
    intro = README.split("\n## ", 1)[0].splitlines()
    assert len(intro) <= SCREEN_LINES, f"{len(intro)} lines before the first section"
    assert max(len(line) for line in intro) <= SCREEN_COLUMNS
    # the terms it uses are defined where they first appear
    for term in ("NDT", "IQR", "PDU", "Zenoh"):
        first = next((line for line in intro if term in line), None)
        assert first is not None, f"{term} is not introduced before the first section"
        assert "(" in first or "[" in first, f"{term} is not defined where it first appears: {first}"


def test_the_readme_fits_a_few_screens() -> None:
    lines = README.splitlines()
    assert len(lines) <= README_LINES, f"{len(lines)} lines; the long form is in docs/"


def test_the_command_table_names_every_command() -> None:
    from randt.cli.main import app

    commands = typer.main.get_command(app).commands  # type: ignore[attr-defined]
    names = {name for name, command in commands.items() if not command.hidden}
    table = README.split("\n## Commands\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in table.splitlines() if line.startswith("| `randt ")]
    missing = {name for name in names if not any(f"`randt {name}" in row for row in rows)}
    assert not missing, f"commands missing from the README's table: {sorted(missing)}"
    assert len(rows) >= 9


def test_every_link_of_the_readme_resolves() -> None:
    """Files exist; an anchor into a markdown file names one of its headings (GitHub's slugs)."""
    checked = 0
    for target in links(README):
        if re.match(r"[a-z]+://", target):
            continue
        path, _, anchor = target.partition("#")
        file = ROOT / path if path else ROOT / "README.md"
        assert file.exists(), f"README links to {path}, which does not exist"
        if anchor:
            assert anchor in anchors(file.read_text()), f"README links to {target}: no such heading"
        checked += 1
    assert checked >= 10
    for doc in ("architecture", "clients", "api", "ros2", "deploy", "mapping", "registration"):
        assert f"docs/{doc}.md" in README
    for doc in ("reliability", "security", "wire-format", "benchmarks"):
        assert f"docs/{doc}.md" in README


def test_the_headline_figures_link_to_their_tables() -> None:
    stands = README.split("\n## Where it stands\n", 1)[1].split("\n## ", 1)[0]
    items = [item for item in stands.split("\n- ")[1:]]
    assert 3 <= len(items) <= 4, "three or four headline figures"
    for item in items:
        assert re.search(r"\]\(docs/benchmarks\.md#[\w-]+\)", item), f"no link to its table: {item}"


def _bibtex(kind: str) -> str:
    blocks = re.findall(r"```bibtex\n(.*?)```", README, flags=re.S)
    found = [block for block in blocks if block.lstrip().startswith(f"@{kind}{{")]
    assert len(found) == 1, f"one @{kind} BibTeX block in the README's citation"
    return found[0]


def _field(entry: str, name: str) -> str:
    match = re.search(rf"^\s*{name}\s*=\s*\{{(.*)\}},?\s*$", entry, flags=re.M)
    assert match is not None, f"{name} missing from {entry}"
    return match[1]


def test_the_citation_gives_the_paper_and_the_software() -> None:
    assert "\n## Citation\n" in README
    paper = _bibtex("article")
    assert _field(paper, "doi") == DOI
    assert _field(paper, "title").replace("{", "").replace("}", "") == PAPER_TITLE
    assert _field(paper, "journal") == "PLoS One" and _field(paper, "year") == "2026"
    issue = (_field(paper, "volume"), _field(paper, "number"), _field(paper, "pages"))
    assert issue == ("21", "4", "e0345709")
    assert "Johnson" in _field(paper, "author")
    software = _bibtex("software")
    assert software.lstrip().startswith("@software{randt_fleet,")
    project = _project()
    assert _field(software, "version") == project["version"]  # bump both together
    assert _field(software, "license") == project["license"]
    assert _field(software, "title").startswith(str(project["name"]))

"""docs/benchmarks.md: today's figures first, one table per benchmark, each linked to its full
section; the paper section where ``bench/paper.py --write`` rewrites it; every link resolving,
and every section another doc names ("docs/benchmarks.md, "<heading>"") findable by that name."""

from __future__ import annotations

import ast
import re
from pathlib import Path

from tests.test_readme import anchors, headings, links

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "benchmarks.md"
TEXT = DOC.read_text()
#: Today's figures open the file: the seven main tables within the first screens.
HEADLINE_LINES = 100


def _section(text: str, heading: str) -> str:
    """From ``heading`` (a ``## `` line) to the next ``## `` heading."""
    start = text.index(f"\n{heading}\n") + 1
    end = re.compile(r"^## ", flags=re.M).search(text, start + len(heading))
    return text[start : end.start() if end else len(text)]


def _paper_marks() -> tuple[str, str]:
    """``MARK_BEGIN`` and ``MARK_END`` as bench/paper.py writes them (read, not imported)."""
    tree = ast.parse((ROOT / "bench" / "paper.py").read_text())
    marks = {
        target.id: ast.literal_eval(node.value)
        for node in tree.body
        if isinstance(node, ast.Assign)
        for target in node.targets
        if isinstance(target, ast.Name) and target.id in ("MARK_BEGIN", "MARK_END")
    }
    return marks["MARK_BEGIN"], marks["MARK_END"]


def test_todays_figures_come_first() -> None:
    assert headings(TEXT)[:2] == ["Benchmarks", "Today's figures"]
    headline = _section(TEXT, "## Today's figures")
    assert len(headline.splitlines()) <= HEADLINE_LINES
    own = anchors(TEXT)
    blocks = re.split(r"^### ", headline, flags=re.M)[1:]
    names = [block.splitlines()[0] for block in blocks]
    for expected in ("Pair registration", "Incremental matcher", "Service capacity", "Reliability"):
        assert any(name.startswith(expected) for name in names), f"no headline table for {expected}"
    for block in blocks:
        name = block.splitlines()[0]
        assert re.search(r"^\|---", block, flags=re.M), f"{name}: no table"
        targets = links(block)
        assert targets, f"{name}: no link to its full section"
        for target in targets:
            if target.startswith("#"):
                assert target[1:] in own, f"{name}: {target} is not a heading of this file"


def test_the_paper_section_is_where_bench_paper_writes_it() -> None:
    begin, end = _paper_marks()
    assert TEXT.count(begin) == 1 and TEXT.count(end) == 1
    assert TEXT.index(begin) < TEXT.index(end)
    # under its own heading: without the marks, --write would append a second section
    assert TEXT.index("\n## The paper, checked (bench/paper.py)\n") < TEXT.index(begin)


def test_every_link_resolves() -> None:
    for target in links(TEXT):
        if re.match(r"[a-z]+://", target):
            continue
        path, _, anchor = target.partition("#")
        file = (DOC.parent / path).resolve() if path else DOC
        assert file.exists(), f"docs/benchmarks.md links to {path}, which does not exist"
        if anchor:
            assert anchor in anchors(file.read_text()), f"docs/benchmarks.md links to {target}: no heading"


def _collapse(text: str) -> str:
    return re.sub(r"\s+", " ", text.replace("`", "")).strip()


def test_sections_named_elsewhere_are_found_by_name() -> None:
    """A section another doc names is a heading here, or a link here to where it moved."""
    names_here = [_collapse(h) for h in headings(TEXT)]
    names_here += [_collapse(m) for m in re.findall(r"\[([^\]]+)\]\([^)]+\)", TEXT)]
    cited = 0
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        if doc == DOC:
            continue
        text = _collapse(doc.read_text())
        for name in re.findall(r"docs/benchmarks\.md,? \"([^\"]+)\"", text):
            cited += 1
            assert any(here.startswith(name) for here in names_here), (
                f'{doc.relative_to(ROOT)} names "{name}" in docs/benchmarks.md: no such section'
            )
    assert cited >= 1

"""``bench/reliability.py`` rewrites ``docs/reliability.md`` from its own run, and keeps the
sections other commands measured (the overload runs, the pose graph under kill -9, Ctrl-C on the
demo) as they stand: rerunning it must not erase them."""

from __future__ import annotations

from pathlib import Path

from bench.reliability import DOC, GENERATED, generate, kept_sections


def _headings(text: str) -> list[str]:
    return [line.removeprefix("## ").strip() for line in text.splitlines() if line.startswith("## ")]


def test_a_rerun_keeps_the_sections_it_does_not_measure_and_replaces_its_own(tmp_path: Path) -> None:
    earlier = DOC.read_text(encoding="utf-8")
    others = [h for h in _headings(earlier) if h not in GENERATED]
    assert "Overload (issue 32)" in others
    doc = tmp_path / "reliability.md"
    doc.write_text(earlier, encoding="utf-8")

    text = generate(soak_minutes=0.0, kill_cycles=0, skip=("corpus", "faults", "crash", "soak"), doc=doc)

    assert doc.read_text(encoding="utf-8") == text
    # every part skipped: this run wrote its totals and the kill -9 section's note; the others
    # stand whole, in order, once, between them
    assert _headings(text) == ["Totals", *others, "kill -9 during ingest and tile writes"]
    for section in kept_sections(earlier):
        assert section in text
    assert "kill -9 | skipped in this run" in text
    assert "Hostile-input corpus" in earlier and "## Hostile-input corpus" not in text


def test_kept_sections_split_at_level_two_headings_only() -> None:
    text = "# Reliability\n\nintro\n\n## Totals\n\n| a |\n\n## Mine\n\n### sub\n\nbody\n\n## Soak\n\nx\n"
    assert kept_sections(text) == ["## Mine\n\n### sub\n\nbody\n"]
